"""In-process MuJoCo quadrotor: the "real vehicle" of the project (paper Sec. V-B, App. D).

One :class:`QuadrotorSim` is a 0.55 kg quad-x with a 20 g electromagnet, an optional
payload (swinging on a light cable and releasable mid-flight, or rigidly attached), a
PX4-like body-rate loop, first-order motors, motion capture and a gyro stream, and the
injectable effects of :mod:`simulator.effects`.

Input, as PX4's offboard attitude-rate interface takes it (design §4):
``u = [collective thrust N, body-rate setpoints rad/s (roll, pitch, yaw; FLU)]``,
clamped to ``[0, 4 * max_thrust]`` and ``+-max_rate``. Ground truth
``x = [p(3), v(3), q(4, w first), omega(3)]`` of the airframe (world ENU, body FLU, SI;
``p``/``v`` of the airframe's geometric centre, the motion-capture origin).

Per physics step (default 1 ms): the rate loop runs when due (default 500 Hz, its gyro
reading is noisy and biased like the streamed one), each rotor's thrust follows its
command with the motor time constant (exact first-order discretisation; motor lag is done
here rather than with MuJoCo actuator dynamics so that thrust effects can act on the
lagged thrust), effects scale the thrust and add drag, MuJoCo integrates, and the sensors
sample the new state.

``command_delay_s`` delays every setpoint as a whole (thrust and body rates) between
:meth:`QuadrotorSim.set_setpoint` and the rate loop: the transport delay of the link from
the control computer to the autopilot (serial or radio, the autopilot's own scheduling),
which the offboard interface adds in front of the vehicle. It is a property of the link,
not of the vehicle, so it is an argument, not an effect of the discrepancy library.
"""

from __future__ import annotations

import math
from collections import deque
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from arcade_core import frames
from arcade_io.vehicle import DEFAULT_ELECTROMAGNET_MASS_KG, load_vehicle
from simulator.effects import (
    Effects,
    battery_gain,
    drag_force_body,
    ground_effect_gain,
    inflow_gain,
    load_effects,
    rotor_speed_ratio,
)
from simulator.mjcf import (
    PAYLOAD_RADIUS,
    RELEASE_EQUALITY,
    ROTOR_SITES,
    build_mjcf,
    rotor_geometry,
)
from simulator.mocap import (
    GyroConfig,
    GyroEmulator,
    GyroSample,
    MocapConfig,
    MocapEmulator,
    MocapSample,
)
from simulator.rate_controller import Mixer, RateController, RateGains, SetpointLag


class QuadrotorSim:
    """MuJoCo quadrotor with rate loop, payload, sensors and effects.

    Args:
        vehicle: vehicle file path, an already loaded vehicle dict, or ``None`` for the
            shipped default. Effects in its ``[effects]`` table are applied.
        payload_mass: payload [kg]; 0 means no payload (and no cable).
        cable_length: cable length [m]; ``None`` takes ``payload.cable_length_m``.
        rigid_payload: attach the payload rigidly under the electromagnet instead.
        effects: effects file, mapping or :class:`~simulator.effects.Effects`; an effect
            named here replaces the vehicle file's effect of the same name.
        mocap, gyro: sensor settings.
        motion_capture: run the motion-capture emulator; ``False``: no frames are captured
            (:meth:`read_mocap` returns none), for flights that only read the true state.
            The flight is the same either way (its noise has its own random stream).
        seed: seeds all sensor noise.
        timestep: physics step [s].
        command_delay_s: transport delay of every setpoint [s], rounded to whole physics
            steps (module docstring); 0: a setpoint acts from the next physics step.
    """

    def __init__(
        self,
        vehicle: str | Path | dict[str, Any] | None = None,
        *,
        payload_mass: float = 0.0,
        cable_length: float | None = None,
        rigid_payload: bool = False,
        effects: str | Path | dict[str, Any] | Effects | None = None,
        mocap: MocapConfig | None = None,
        gyro: GyroConfig | None = None,
        motion_capture: bool = True,
        seed: int = 0,
        timestep: float = 0.001,
        command_delay_s: float = 0.0,
    ):
        self.vehicle = vehicle if isinstance(vehicle, dict) else load_vehicle(vehicle)
        #: Motors follow the rate loop only while enabled (an autopilot's armed state).
        self.motors_enabled = True
        #: Hold the rate integrators at zero (an autopilot does this while landed).
        self.hold_integrators = False
        if not 1e-4 <= timestep <= 0.005:
            raise ValueError(f"timestep must be in [1e-4, 5e-3] s, got {timestep}")
        self.effects = load_effects(self.vehicle.get("effects")).merged(load_effects(effects))
        self.payload_mass = float(payload_mass)
        self.rigid_payload = bool(rigid_payload) and self.payload_mass > 0.0
        self._swinging = self.payload_mass > 0.0 and not self.rigid_payload

        xml = build_mjcf(
            self.vehicle,
            payload_mass=self.payload_mass,
            cable_length=cable_length,
            rigid_payload=self.rigid_payload,
            com_offset=self.effects.get("com_offset", "offset_m"),
            timestep=timestep,
        )
        self.model = mujoco.MjModel.from_xml_string(xml)
        self.data = mujoco.MjData(self.model)
        self.dt = float(self.model.opt.timestep)
        if not (math.isfinite(command_delay_s) and 0.0 <= command_delay_s <= 1.0):
            raise ValueError(f"command_delay_s must be in [0, 1] s, got {command_delay_s}")
        #: Setpoint transport delay in physics steps; setpoints in flight, with the step
        #: from which each one acts (oldest first).
        self.command_delay_steps = round(command_delay_s / self.dt)
        self._in_flight: deque[tuple[int, np.ndarray]] = deque()
        self.gravity = -float(self.model.opt.gravity[2])
        m = self.model
        self._airframe = m.body("airframe").id
        self._sites = np.array([m.site(n).id for n in ROTOR_SITES])
        self._anchor_site = m.site("magnet_anchor").id
        self._payload_body = m.body("payload").id if self.payload_mass > 0.0 else -1
        if self._swinging:
            self._hook_body = m.body("hook").id
            self._eq = m.equality(RELEASE_EQUALITY).id
            self._hook_qadr = m.jnt_qposadr[m.joint("hook_root").id]
            self._hook_vadr = m.jnt_dofadr[m.joint("hook_root").id]
            self._pay_qadr = m.jnt_qposadr[m.joint("payload_root").id]
            self._pay_vadr = m.jnt_dofadr[m.joint("payload_root").id]
            self.cable_length = float(m.tendon_range[m.tendon("cable").id, 1])
        else:
            self.cable_length = 0.0
        #: The motion capture tracks a swinging payload as a rigid body of its own, before
        #: and after its release (a rigid one is part of the vehicle's body).
        self._tracked_payload = self._payload_pose if self._swinging else None
        # Airframe + electromagnet (+ rigid payload): the subtree rooted at the airframe.
        self._airframe_subtree_mass = float(m.body_subtreemass[self._airframe])
        self.vehicle_mass = float(self.vehicle["body"]["mass_kg"]) + float(
            self.vehicle.get("payload", {}).get(
                "electromagnet_mass_kg", DEFAULT_ELECTROMAGNET_MASS_KG
            )
        )

        rotors = self.vehicle["rotors"]
        rl = self.vehicle["rate_loop"]
        self.max_thrust = float(rotors["max_thrust_n"])
        self.max_rate = np.asarray(rl["max_rate_rad_s"], dtype=float).reshape(3)
        self.mixer = Mixer(
            rotor_geometry(self.vehicle), float(rotors["yaw_moment_coeff_m"]), self.max_thrust
        )
        rate_hz = float(rl.get("rate_hz", 500.0))
        self._rate_div = max(1, round(1.0 / (rate_hz * self.dt)))
        rate_dt = self._rate_div * self.dt
        self.rate_controller = RateController(RateGains.from_vehicle(self.vehicle), rate_dt)
        self._lag = SetpointLag(
            self.effects.get("rate_lag", "delay_s", 0.0),
            self.effects.get("rate_lag", "time_constant_s", 0.0),
            rate_dt,
        )
        tau_m = self.effects.get(
            "motor_lag", "time_constant_s", float(rotors["motor_time_constant_s"])
        )
        self.motor_time_constant = float(tau_m)
        self._motor_alpha = 1.0 - math.exp(-self.dt / self.motor_time_constant)
        self._thrust_gain = float(self.effects.get("thrust_scale", "scale", 1.0))
        self._ge_radius = self.effects.get("ground_effect", "rotor_radius_m")
        self._drag = "rotor_drag" in self.effects or "quadratic_drag" in self.effects
        self._air = self._drag or "induced_inflow" in self.effects
        self._sag = "battery_sag" in self.effects
        self._hover_per_rotor = self.vehicle_mass * self.gravity / 4.0
        wind = self.effects.get("wind", "velocity_mps")
        self._wind = np.zeros(3) if wind is None else np.asarray(wind, dtype=float)

        mocap_rng, gyro_rng = (
            np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(2)
        )
        self.mocap = MocapEmulator(mocap or MocapConfig(), mocap_rng)
        self._motion_capture = bool(motion_capture)
        self.gyro = GyroEmulator(gyro or GyroConfig(), gyro_rng)
        self.reset()

    # ------------------------------------------------------------------ set-up

    def reset(
        self,
        position=(0.0, 0.0, 1.0),
        yaw: float = 0.0,
        velocity=(0.0, 0.0, 0.0),
    ) -> np.ndarray:
        """Place the vehicle level at ``position`` with ``yaw`` [rad] and ``velocity``.

        Time restarts at 0, the payload (re)attaches and hangs straight down on a taut
        cable (resting on the floor if the cable is longer than the height), motors spin
        at hover thrust and the setpoint is "hover, zero rates". Returns the state.
        """
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        p = np.asarray(position, dtype=float).reshape(3)
        v = np.asarray(velocity, dtype=float).reshape(3)
        d.qpos[0:3] = p
        d.qpos[3:7] = frames.from_yaw_py(yaw)
        d.qvel[0:3] = v
        if self._swinging:
            d.eq_active[self._eq] = 1
            mujoco.mj_kinematics(m, d)
            anchor = d.site_xpos[self._anchor_site].copy()
            below = anchor - np.array([0.0, 0.0, self.cable_length + PAYLOAD_RADIUS])
            below[2] = max(below[2], PAYLOAD_RADIUS)
            d.qpos[self._hook_qadr : self._hook_qadr + 7] = [*anchor, 1.0, 0.0, 0.0, 0.0]
            d.qpos[self._pay_qadr : self._pay_qadr + 7] = [*below, 1.0, 0.0, 0.0, 0.0]
            d.qvel[self._hook_vadr : self._hook_vadr + 3] = v
            d.qvel[self._pay_vadr : self._pay_vadr + 3] = v
        mujoco.mj_forward(m, d)
        self._k = 0
        self._t_goal = 0.0
        hover_cmd = self.hover_thrust() / self._thrust_gain
        self._setpoint = np.array([min(hover_cmd, 4.0 * self.max_thrust), 0.0, 0.0, 0.0])
        self._in_flight.clear()
        # Per-rotor and per-axis state as Python floats (see ``_physics_step``).
        self._thrust_cmd = [float(min(hover_cmd / 4.0, self.max_thrust))] * 4
        self._thrust = list(self._thrust_cmd)
        self._saturation = [0.0, 0.0, 0.0]
        self.rate_controller.reset(d.qvel[3:6])
        self._lag.reset(np.zeros(3))
        self.mocap.reset(0.0)
        self.gyro.reset(0.0)
        if self._motion_capture:
            self.mocap.observe(0.0, d.qpos[0:3], d.qpos[3:7], self._tracked_payload)
        self.gyro.observe(0.0, d.qvel[3:6])
        return self.state()

    # ------------------------------------------------------------------ inputs

    def set_setpoint(self, u) -> np.ndarray:
        """Set ``[thrust N, roll, pitch, yaw rate rad/s]``; returns it clamped to the limits.

        With a ``command_delay_s`` it reaches the rate loop that much later (until then
        the rate loop follows the setpoints sent before it)."""
        u = np.asarray(u, dtype=float).reshape(-1)
        if u.shape != (4,) or not np.all(np.isfinite(u)):
            raise ValueError(f"setpoint must be 4 finite numbers, got {u!r}")
        clamped = np.concatenate(
            [
                [min(max(u[0], 0.0), 4.0 * self.max_thrust)],
                np.clip(u[1:], -self.max_rate, self.max_rate),
            ]
        )
        if self.command_delay_steps == 0:
            self._setpoint = clamped
        else:
            self._in_flight.append((self._k + self.command_delay_steps, clamped))
        return clamped.copy()

    @property
    def setpoint(self) -> np.ndarray:
        """The (clamped) setpoint the rate loop currently follows."""
        return self._setpoint.copy()

    def release_payload(self) -> bool:
        """Switch the electromagnet off. True if a payload was attached and is now free."""
        if self.rigid_payload:
            raise RuntimeError("a rigidly attached payload cannot be released")
        if not self._swinging or not self.payload_attached:
            return False
        self.data.eq_active[self._eq] = 0
        return True

    # ------------------------------------------------------------------ stepping

    def step(self, duration: float) -> np.ndarray:
        """Advance by ``duration`` seconds; returns the state.

        Time moves in whole physics steps; the requested durations are accumulated, so
        e.g. repeated ``step(1 / 30)`` keeps 30 Hz on average instead of drifting.
        """
        if duration < 0.0:
            raise ValueError(f"duration must be >= 0, got {duration}")
        self._t_goal += duration
        for _ in range(round(self._t_goal / self.dt) - self._k):
            self._physics_step()
        return self.state()

    def stop_motors(self) -> None:
        """Disable the motors and spin them down at once (a disarmed vehicle)."""
        self.motors_enabled = False
        self._thrust = [0.0] * 4
        self._thrust_cmd = [0.0] * 4
        self._saturation = [0.0, 0.0, 0.0]

    def _rate_tick(self) -> None:
        if not self.motors_enabled:
            self._thrust_cmd = [0.0] * 4
            self._saturation = [0.0, 0.0, 0.0]
            self.rate_controller.reset(self.data.qvel[3:6])
            return
        if self.hold_integrators:  # on the ground: an autopilot keeps its integrators at zero
            self.rate_controller.reset(self.data.qvel[3:6])
        omega_meas = self.gyro.measure(self.data.qvel[3:6]).tolist()
        thrust, *rates = self._setpoint.tolist()
        rate_sp = self._lag.update_values(rates)
        torque = self.rate_controller.update_values(rate_sp, omega_meas, self._saturation)
        self._thrust_cmd, self._saturation = self.mixer.mix_values(thrust, torque)

    def _physics_step(self) -> None:
        m, d = self.model, self.data
        if self._k % self._rate_div == 0:
            self._rate_tick()
        # Four rotors: Python floats, since NumPy's per-call cost would dominate this loop
        # (the arithmetic is elementwise, so the results are those of the vector form).
        a, gain = self._motor_alpha, self._thrust_gain
        self._thrust = thrust = [f + a * (c - f) for f, c in zip(self._thrust, self._thrust_cmd)]
        if self._sag:
            gain *= battery_gain(self.effects, self._k * self.dt)
        if self._air:
            rot = d.xmat[self._airframe].reshape(3, 3)
            v_rel_b = rot.T @ (d.qvel[0:3] - self._wind)
            gain *= inflow_gain(self.effects, v_rel_b)
        force = [f * gain for f in thrust]
        if self._ge_radius is not None:
            force = np.array(force) * ground_effect_gain(
                d.site_xpos[self._sites, 2], self._ge_radius
            )
        d.ctrl[:] = force
        if self._drag:
            speed = rotor_speed_ratio(thrust, self._hover_per_rotor)
            f_w = rot @ drag_force_body(self.effects, v_rel_b, self.vehicle_mass, speed)
            # xfrc_applied acts at the airframe body's own CoM; the moment term moves the
            # force to the CoM of airframe + electromagnet (+ rigid payload): pure force.
            a = d.subtree_com[self._airframe] - d.xipos[self._airframe]
            d.xfrc_applied[self._airframe, 0:3] = f_w
            d.xfrc_applied[self._airframe, 3:6] = (
                a[1] * f_w[2] - a[2] * f_w[1],
                a[2] * f_w[0] - a[0] * f_w[2],
                a[0] * f_w[1] - a[1] * f_w[0],
            )
        mujoco.mj_step(m, d)
        self._k += 1
        while self._in_flight and self._in_flight[0][0] <= self._k:  # due from now on
            self._setpoint = self._in_flight.popleft()[1]
        t = self._k * self.dt
        if self._motion_capture:
            self.mocap.observe(t, d.qpos[0:3], d.qpos[3:7], self._tracked_payload)
        self.gyro.observe(t, d.qvel[3:6])

    # ------------------------------------------------------------------ outputs

    @property
    def time(self) -> float:
        """Simulation time [s] since the last reset."""
        return self._k * self.dt

    def state(self) -> np.ndarray:
        """Ground-truth airframe state ``[p, v, q (w first), omega]`` (13,)."""
        d = self.data
        return np.concatenate([d.qpos[0:3], d.qvel[0:3], d.qpos[3:7], d.qvel[3:6]])

    def read_mocap(self) -> list[MocapSample]:
        """Motion-capture samples that have arrived by now (each once), oldest first."""
        return self.mocap.read(self.time)

    def read_gyro(self) -> list[GyroSample]:
        """Gyro samples that have arrived by now (each once), oldest first."""
        return self.gyro.read(self.time)

    @property
    def payload_attached(self) -> bool:
        """Whether a payload hangs from (or is fixed to) the vehicle."""
        if self._swinging:
            return bool(self.data.eq_active[self._eq])
        return self.rigid_payload

    def payload_position(self) -> np.ndarray | None:
        """World position of the payload's centre, or ``None`` without a payload."""
        if self._payload_body < 0:
            return None
        return self.data.xpos[self._payload_body].copy()

    def _payload_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """True pose of the swinging payload: position (ENU) and attitude (w first)."""
        q = self.data.qpos[self._pay_qadr : self._pay_qadr + 7]
        return q[0:3].copy(), q[3:7].copy()

    def carried_mass(self) -> float:
        """Mass the rotors carry [kg]: airframe, electromagnet and attached payload/cable."""
        mass = self._airframe_subtree_mass
        if self._swinging and self.payload_attached:
            mass += float(self.model.body_mass[self._hook_body] + self.payload_mass)
        return mass

    def hover_thrust(self) -> float:
        """Total weight the rotors must carry [N] (with ``thrust_scale`` the command differs)."""
        return self.carried_mass() * self.gravity

    def rotor_thrusts(self) -> np.ndarray:
        """Actual rotor thrusts of the last step [N] (PX4 order), after all effects."""
        return self.data.ctrl.copy()
