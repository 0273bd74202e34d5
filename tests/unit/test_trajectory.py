"""Reference trajectories: built-ins, fitted splines, the file formats, the limit checks, and
how the stack's processes get them (``arcade_control.trajectory``,
``arcade_io.trajectory_file``, ``deploy.trajectories``, ``services.options``)."""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.interpolate import BPoly, make_interp_spline

from arcade_control import trajectory as traj
from arcade_control.scenario import RampedPath, Scenario, planned
from arcade_core import frames
from arcade_core.px4_command import Geofence
from arcade_core.trajectories import Chain, FigureEight, Hover, Takeoff
from arcade_io.trajectory_file import load_fitted, read_samples, save_fitted
from arcade_io.vehicle import load_vehicle
from deploy import trajectories as deploy_traj
from deploy.stack_config import StackConfig
from services import options


@jax.jit
def _derivs(path, t):
    """Position, velocity and acceleration of ``path`` at the scalar ``t`` (forward mode)."""

    def d(f):
        return lambda s: jax.jvp(f, (s,), (jnp.ones_like(s),))[1]

    p = path.position
    return jnp.stack([p(t), d(p)(t), d(d(p))(t)])


def _derivatives(path, t):
    return np.asarray(_derivs(path, jnp.asarray(t, jnp.float64)))


_positions = jax.jit(lambda path, ts: jax.vmap(path.position)(ts))


# ------------------------------------------------------------------ the plan


def test_figure_eight_plan_is_the_shipped_one_bit_for_bit():
    """No trajectory (and ``figure-eight``): the path of the plan as it always was."""
    f = jnp.asarray
    s = Scenario()
    fig = FigureEight(f(s.center), f(s.half_length_m), f(s.half_width_m), f(s.speed_mps))
    old = Chain(
        Takeoff(f(s.start), f(s.center), f(s.takeoff_s)),
        Chain(Hover(f(s.center)), RampedPath(fig, f(s.ramp_s)), f(s.hover_s)),
        f(s.takeoff_s),
    )
    leaves, tree = jax.tree.flatten(old)
    for scen in (s, planned(), planned(trajectory=traj.builtin("figure-eight", s.center, 2.5))):
        # The same tree of the same numbers: the same reference, bit for bit.
        got, got_tree = jax.tree.flatten(scen.path())
        assert got_tree == tree
        assert all(a.dtype == b.dtype and np.array_equal(a, b) for a, b in zip(got, leaves))
        assert (scen.t_end, scen.t_release, scen.t_figure) == (s.t_end, s.t_release, 4.0)


def test_plan_climbs_to_the_first_point_and_flies_the_trajectory():
    t = np.linspace(0.0, 2.0, 5)
    p = np.c_[3.0 * t / 2, 0 * t, 2.0 + 0 * t]
    scen = planned(trajectory=traj.sampled("line", traj.fit_samples(t, p)))
    assert np.allclose(scen.first_point, (0.0, 0.0, 2.0))
    assert scen.t_figure == 2.5 + 1.5 and scen.t_end == pytest.approx(6.0)
    assert scen.t_release == pytest.approx(4.0 + 0.95 * 2.0)
    path = scen.path()
    assert np.allclose(_positions(path, jnp.asarray([0.0]))[0], scen.start)
    assert np.allclose(_positions(path, jnp.asarray([3.0]))[0], (0.0, 0.0, 2.0))  # hovering
    assert np.allclose(_positions(path, jnp.asarray([6.0]))[0], (3.0, 0.0, 2.0))
    # A first point 2 m away: the climb takes 4 s (0.5 m/s mean) instead of 2.5 s.
    far = traj.sampled("far", traj.fit_samples(t, p + np.array([2.0, 0.0, 0.0])))
    assert planned(trajectory=far).climb_s == pytest.approx(np.hypot(2.0, 0.5) / 0.5)
    # The origin moves the trajectory with the plan.
    moved = planned(origin=(1.0, -1.0), trajectory=scen.trajectory)
    assert np.allclose(moved.first_point, (1.0, -1.0, 2.0))


# ------------------------------------------------------------------ built-ins


def test_builtin_specs_parse_with_defaults_and_refuse_nonsense():
    assert traj.parse_builtin("circle") == ("circle", {"radius": 1.5, "laps": 2.0})
    assert traj.parse_builtin("circle:radius=2,laps=1")[1] == {"radius": 2.0, "laps": 1.0}
    assert traj.parse_builtin("my.csv") is None
    for bad, why in (
        ("circle:r=2", "circle: no parameter 'r=2' \\(parameters: radius, laps\\)"),
        ("circle:radius=x", "radius must be a number"),
        ("circle:radius=0", "radius must be positive"),
        ("lissajous:ny=1.5", "whole numbers"),
        ("hover:seconds=-1", "seconds must be a number >= 0"),
    ):
        with pytest.raises(ValueError, match=why):
            traj.parse_builtin(bad)


@pytest.mark.parametrize("spec", ["circle", "lissajous", "hover:seconds=3"])
def test_builtins_start_at_the_centre_at_rest(spec):
    tr = traj.builtin(spec, (0.0, 0.0, 2.0), 2.0)
    p, v, a = _derivatives(tr.path, 0.0)
    assert np.allclose(p, (0.0, 0.0, 2.0)) and np.allclose(v, 0) and np.allclose(a, 0)
    assert tr.duration_s == pytest.approx(tr.laps * tr.lap_s + tr.ramp_s / 2)


def test_circle_flies_its_radius_at_the_speed_after_the_ramp():
    tr = traj.builtin("circle:radius=1.2", (0.0, 0.0, 2.0), 1.5)
    assert tr.lap_s == pytest.approx(2 * np.pi * 1.2 / 1.5)
    for t in (3.0, 4.1, 7.7):
        p, v, _ = _derivatives(tr.path, t)
        assert np.linalg.norm(p[:2] - (-1.2, 0.0)) == pytest.approx(1.2)
        assert np.linalg.norm(v) == pytest.approx(1.5)


def test_lissajous_period_is_its_arc_length_at_the_mean_speed():
    tr = traj.builtin("lissajous:ax=1,ay=0.5,az=0,nx=1,ny=2,nz=1,laps=1", (0, 0, 2), 1.0)
    phi = np.linspace(0.0, 2 * np.pi, 200_001)
    pts = np.c_[np.sin(phi), 0.5 * np.sin(2 * phi)]
    length = np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=1))  # brute force
    assert tr.lap_s == pytest.approx(length, rel=1e-6)


# ------------------------------------------------------------------ fitted paths


def test_positions_become_the_clamped_quintic_spline():
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.uniform(0.2, 0.5, 12))
    p = rng.normal(size=(12, 3))
    path = traj.fit_samples(t, p)
    ref = make_interp_spline(t, p, k=5, bc_type=([(1, np.zeros(3)), (2, np.zeros(3))],) * 2)
    tt = np.linspace(t[0], t[-1], 97)
    got = np.asarray(_positions(path, jnp.asarray(tt - t[0])))
    assert np.allclose(got, ref(tt), atol=1e-9)
    for end in (0.0, t[-1] - t[0]):
        _, v, a = _derivatives(path, end)
        assert np.allclose(v, 0, atol=1e-9) and np.allclose(a, 0, atol=1e-9)
    # Outside its times the path holds its ends.
    assert np.allclose(_positions(path, jnp.asarray([100.0]))[0], p[-1])


def test_given_velocities_and_accelerations_are_matched():
    t = np.linspace(0.0, 3.0, 7)
    w = 2 * np.pi / 3
    p = np.c_[1 - np.cos(w * t), np.sin(w * t) ** 2, 2 + 0 * t]
    v = np.c_[w * np.sin(w * t), w * np.sin(2 * w * t), 0 * t]
    a = np.c_[w**2 * np.cos(w * t), 2 * w**2 * np.cos(2 * w * t), 0 * t]
    a[0] = a[-1] = 0.0  # at rest at the start
    path = traj.fit_samples(t, p, v, a)
    ref = BPoly.from_derivatives(t, np.stack([p, v, a], axis=1))
    for ti in np.linspace(0.0, 3.0, 13):
        got = _derivatives(path, ti)
        assert np.allclose(got[0], ref(ti), atol=1e-9)
    for i, ti in enumerate(t):
        got = _derivatives(path, ti)
        assert np.allclose(got[1], v[i], atol=1e-9) and np.allclose(got[2], a[i], atol=1e-9)
    # Velocities alone: the accelerations come from the quintic spline of the positions.
    v_only = traj.fit_samples(t, p, v)
    spline = traj.clamped_spline(t, p)
    for ti in t:
        assert np.allclose(_derivatives(v_only, ti)[2], spline(ti, 2), atol=1e-9)


def test_samples_that_do_not_make_a_trajectory_are_refused():
    t = np.array([0.0, 1.0, 2.0])
    p = np.zeros((3, 3))
    with pytest.raises(ValueError, match="velocity at the first sample is 1"):
        traj.fit_samples(t, p, v=np.array([[1.0, 0, 0], [0, 0, 0], [0, 0, 0]]))
    with pytest.raises(ValueError, match=r"times must increase \(row 3: t = 1 s\)"):
        traj.fit_samples([0.0, 1.0, 1.0], p)
    with pytest.raises(ValueError, match="at least two points"):
        traj.fit_samples([0.0], p[:1])


def test_waypoints_are_timed_by_distance_and_passed_through():
    pts = np.array([[0.0, 0, 2], [3.0, 0, 2], [3.0, 4, 2]])
    assert np.allclose(traj.waypoint_times(pts, 2.0), [0.0, 1.5, 3.5])
    path = traj.fit_waypoints(pts, speed=2.0)
    for ti, pi in zip([0.0, 1.5, 3.5], pts, strict=True):
        assert np.allclose(_positions(path, jnp.asarray([ti]))[0], pi, atol=1e-9)
    two = traj.fit_waypoints(pts[:2], times=[0.0, 2.0])  # two points: one quintic
    assert np.allclose(_positions(two, jnp.asarray([1.0]))[0], [1.5, 0, 2])


def test_a_given_yaw_is_the_reference_heading(tmp_path):
    """Hovering in place while the yaw turns 0 -> 1 rad: the flat reference's heading is
    the fitted yaw, its body z rate the yaw's derivative; a yaw must start at 0."""
    from arcade_control.scenario import flat_reference
    from arcade_io.traced import load_or_trace

    f = tmp_path / "turn.csv"
    t = np.linspace(0.0, 4.0, 9)
    yaw = 0.5 * (1 - np.cos(np.pi * t / 4))
    f.write_text("t,px,py,pz,yaw\n" + "".join(f"{a},0,0,2,{float(b)!r}\n" for a, b in zip(t, yaw)))
    scen = planned(trajectory=deploy_traj.resolve(str(f), 2.5))
    times = scen.t_figure + t
    ref_args = (scen.path(), jnp.asarray(times))  # traced once, kept as the services keep it
    x = load_or_trace("reference", flat_reference, ref_args)(*ref_args)[0]
    heading = frames.to_rpy_np(np.asarray(x)[:, 6:10])[:, 2]
    assert np.allclose(heading, yaw, atol=1e-9)
    rate = np.asarray(_derivatives(scen.trajectory.yaw, 2.0))[1, 0]
    assert np.asarray(x)[4, 12] == pytest.approx(rate, abs=1e-9)
    with pytest.raises(ValueError, match=r"yaw at the first sample is 0\.3 rad, not 0"):
        traj.fit_yaw([0.0, 1.0], [0.3, 0.5])


# ------------------------------------------------------------------ files


def test_trajectory_and_waypoint_csv_read(tmp_path):
    f = tmp_path / "t.csv"
    f.write_text("# a comment\nt,px,py,pz,vx,vy,vz,yaw\n1,0,0,2,0,0,0,0\n2,1,0,2,0.5,0,0,0\n")
    s = read_samples(f)
    assert np.allclose(s.t, [1, 2]) and np.allclose(s.p[1], [1, 0, 2])
    assert np.allclose(s.v[1], [0.5, 0, 0]) and s.a is None and not s.waypoints
    w = tmp_path / "w.csv"
    w.write_text("x,y,z\n0,0,2\n1,1,2\n")
    s = read_samples(w)
    assert s.waypoints and s.t is None and np.allclose(s.p[1], [1, 1, 2])


@pytest.mark.parametrize(
    ("text", "why"),
    [
        ("", "empty"),
        ("t,px,py\n0,0,0\n1,0,0\n", "missing column pz"),
        ("t,px,py,pz,speed\n0,0,0,2,0\n1,0,0,2,0\n", "unknown column 'speed'"),
        ("t,px,py,pz,vx\n0,0,0,2,0\n1,0,0,2,0\n", "columns vx,vy,vz go together"),
        ("t,px,py,pz,ax,ay,az\n0,0,0,2,0,0,0\n1,0,0,2,0,0,0\n", "accelerations need vel"),
        ("t,px,py,pz\n0,0,0,2\n1,0,nan,2\n", "row 3, column py: not a number"),
        ("t,px,py,pz\n0,0,0,2\n1,0,2\n", "row 3 has 3 values, want 4"),
        ("t,px,py,pz\n0,0,0,2\n", "at least two rows"),
    ],
)
def test_bad_files_are_refused_with_the_file_and_the_place(tmp_path, text, why):
    f = tmp_path / "bad.csv"
    f.write_text(text)
    with pytest.raises(ValueError, match=why) as err:
        read_samples(f)
    assert str(f) in str(err.value) and "\n" not in str(err.value)


def test_fitted_path_file_round_trips_and_checks_its_hash(tmp_path):
    path = traj.fit_samples([0.0, 1.0, 2.5], [[0, 0, 2], [1, 0, 2], [1, 1, 2.5]])
    sha = save_fitted(tmp_path / "p.npz", "mine.csv", path.breaks, path.coeffs)
    name, breaks, coeffs, yaw = load_fitted(tmp_path / "p.npz", sha)
    assert name == "mine.csv" and yaw is None
    assert np.array_equal(breaks, path.breaks) and np.array_equal(coeffs, path.coeffs)
    heading = traj.fit_yaw([0.0, 1.0, 2.5], [0.0, 0.5, 1.0])
    sha = save_fitted(tmp_path / "y.npz", "y", path.breaks, path.coeffs, heading[:2])
    yaw = load_fitted(tmp_path / "y.npz", sha)[3]
    assert np.array_equal(yaw[0], heading.breaks) and np.array_equal(yaw[1], heading.coeffs)
    with pytest.raises(ValueError, match="is not the checked one"):
        load_fitted(tmp_path / "p.npz", "0" * 64)


# ------------------------------------------------------------------ to the services


def test_services_fly_what_the_command_line_checked(tmp_path):
    """The staged file and a built-in spec give every process the same trajectory."""
    path = traj.fit_samples([0.0, 1.0, 2.5], [[0, 0, 2], [1, 0, 2], [1, 1, 2.5]])
    value, sha = deploy_traj.stage(tmp_path, "mine.csv", traj.sampled("mine.csv", path))
    cfg = StackConfig(out=tmp_path, trajectory=value, trajectory_sha256=sha)
    for service in ("sim", "controller"):
        args = cfg.args(service)
        assert f"--trajectory={value}" in args and sha in args
    assert "--trajectory" not in " ".join(cfg.args("adapter"))
    parser = argparse.ArgumentParser()
    options.add_plan_arguments(parser)
    ns = parser.parse_args([f"--trajectory={value}", "--trajectory-sha256", sha])
    got = options.scenario(ns).trajectory
    assert np.array_equal(got.path.coeffs, path.coeffs) and got.lap_s == 2.5
    ns = parser.parse_args(["--trajectory=circle:radius=1", "--speed", "2"])
    assert options.scenario(ns).lap_s == pytest.approx(np.pi)
    assert deploy_traj.stage(tmp_path, "circle", traj.builtin("circle", (0, 0, 2), 1)) == (
        "circle",
        None,
    )


# ------------------------------------------------------------------ limits


def _limits(**kw) -> traj.Limits:
    base = deploy_traj.vehicle_limits(load_vehicle(), 175.0, Geofence.parse("-5,5,-5,5,-0.5,4"))
    return traj.Limits(**{**base.__dict__, **kw})


def _reference(n=5, v=(0, 0, 0), tilt_deg=0.0, thrust=7.3, rates=(0, 0, 0), p=(0, 0, 2)):
    q = frames.from_rpy_np([np.radians(tilt_deg), 0.0, 0.0])
    x = np.tile(np.r_[p, v, q, 0, 0, 0], (n, 1))
    u = np.tile(np.r_[thrust, rates], (n, 1))
    return np.arange(n) * 0.01, x, u


def _violation(limits, t, x, u, late=None):
    if late is not None:  # the limit broken only from sample 3 on
        x[:3], u[:3] = _reference(3)[1:]
    return traj.first_violation(limits, t, x, u, nominal_mass_kg=0.57, gravity=9.81)


def test_vehicle_limits_come_from_the_vehicle_file():
    lim = _limits()
    assert (lim.max_speed_mps, lim.max_accel_mps2, lim.max_tilt_deg) == (5.0, 10.0, 45.0)
    assert lim.max_thrust_n == pytest.approx(0.9 * 16.0)
    assert lim.carried_mass_kg == pytest.approx(0.55 + 0.02 + 0.002 + 0.175)
    assert lim.max_rate_rad_s == (3.5, 3.5, 3.0)


@pytest.mark.parametrize(
    ("ref", "limit", "value"),
    [
        ({"v": (4.0, 3.0, 0.0)}, "speed", 5.0 + 0.0),
        ({"tilt_deg": 50.0, "thrust": 0.57 * 9.81 / np.cos(np.radians(50))}, "tilt", 50.0),
        ({"thrust": 0.57 * 22.0}, "acceleration", 22.0 - 9.81),
        ({"rates": (0.0, -3.6, 0.0)}, "y body rate", 3.6),
        ({"p": (0.0, 5.5, 2.0)}, "geofence: y = 5.50 m not in [-5, 5] m", 0.5),
    ],
)
def test_each_limit_is_named_with_its_time_and_value(ref, limit, value):
    lim = _limits(max_speed_mps=4.9, max_accel_mps2=12.0)  # a 50 deg tilt: 11.7 m/s^2
    t, x, u = _reference(**ref)
    found = _violation(lim, t, x, u, late=True)
    assert found is not None and found.limit == limit
    assert found.t == pytest.approx(0.03) and found.value == pytest.approx(value, rel=1e-9)
    text = found.describe(0.02)
    assert "t = 0.03 s (0.01 s into the trajectory)" in text
    assert _violation(_limits(), *_reference()) is None


def test_thrust_counts_the_payload_and_the_earliest_limit_wins():
    lim = _limits(max_accel_mps2=100.0, max_thrust_n=9.0)
    t, x, u = _reference(thrust=0.57 * 12.0)  # 12 m/s^2 for 0.747 kg: 8.96 N
    assert _violation(lim, t, x, u) is None
    t, x, u = _reference(thrust=0.57 * 12.1)
    found = _violation(lim, t, x, u)
    assert found.limit == "thrust (with the payload)"
    assert found.value == pytest.approx(0.747 * 12.1)
    x[0, 3:6] = (6.0, 0.0, 0.0)  # speed broken at the first sample: reported first
    assert _violation(lim, t, x, u).limit == "speed"


def test_an_infeasible_plan_is_refused_before_take_off(tmp_path, capsys):
    """The whole plan is checked (one compile of the flat reference): a circle that leaves
    the geofence is refused naming the box, the time and the distance."""
    trajectory, why = deploy_traj.prepare(
        "circle:radius=3",
        speed=2.5,
        payload_g=175.0,
        vehicle=load_vehicle(),
        geofence=Geofence.parse("-5,5,-5,5,-0.5,4"),
    )
    assert trajectory is None
    assert why.startswith("--trajectory circle:radius=3: geofence: x = -5.")
    assert "into the trajectory" in why and "m outside the box" in why


def test_one_process_alone_cannot_be_given_another_path(tmp_path):
    from arcade.commands.service_options import service_args_problem

    cfg = StackConfig(out=tmp_path, extra={"controller": ["--trajectory=circle"]})
    assert service_args_problem(cfg) == (
        "--service-arg controller: --trajectory set by the launcher (from arcade up's own "
        "options), not through --service-arg"
    )
