"""The estimator service's screening and fallbacks, in process: a frame held back to the
next control instant, a diverged or non-finite filter, the bounded frame buffer, the
vehicle's rigid body among others on the stream."""

from __future__ import annotations

import numpy as np
import pytest

from services import estimator as est_service
from services.estimator import Estimator
from services.messages import PAYLOAD_BODY, VEHICLE_BODY, Imu, Mocap

T0 = 100.0
MOCAP_DT = 1.0 / 120.0
CONTROL_DT = 0.05


def frame(t: float, body: str = VEHICLE_BODY) -> Mocap:
    """A vehicle (rigid body ``body``) moving at 1 m/s along x, captured at ``t`` (after
    ``T0``)."""
    return Mocap(
        position=[t, 0.0, 1.0],
        quaternion=[1.0, 0, 0, 0],
        body=body,
        capture_stamp=T0 + t,
        stamp=T0 + t,
    )


def payload_frame(t: float) -> Mocap:
    """The payload of the same capture: half a metre below and behind the vehicle."""
    return Mocap(
        position=[t - 0.3, 0.0, 0.5],
        quaternion=[0.0, 1.0, 0, 0],
        body=PAYLOAD_BODY,
        capture_stamp=T0 + t,
        stamp=T0 + t,
    )


def fly_to(est: Estimator, t_end: float, payload: bool = False, body: str = VEHICLE_BODY) -> None:
    """Frames of the vehicle named ``body`` every 1/120 s (``payload``: each followed by
    the payload's) and control instants every 50 ms up to ``t_end``."""
    captures = iter(np.arange(0.0, t_end, MOCAP_DT))
    c = next(captures)
    for k in range(round(t_end / CONTROL_DT) + 1):
        t = k * CONTROL_DT
        while c is not None and c <= t:
            est.on_mocap(frame(c, body))
            if payload:
                est.on_mocap(payload_frame(c))
            c = next(captures, None)
        est.on_imu(Imu(gyro=np.zeros(3), stamp=T0 + t))


def test_frames_of_other_rigid_bodies_are_not_the_vehicles(estimator_factory):
    """A stream that also carries the payload gives the same states as the vehicle's
    frames alone: the payload's are counted per body, never fused, frozen or faults."""
    alone, alone_bus = estimator_factory()
    fly_to(alone, 1.0)
    est, bus = estimator_factory()
    fly_to(est, 1.0, payload=True)
    assert len(bus.states) == len(alone_bus.states) == 21
    for s, ref in zip(bus.states, alone_bus.states, strict=True):
        np.testing.assert_array_equal(s.x, ref.x)
        assert s.meas_stamp == ref.meas_stamp and not s.mocap_stale
    assert est.stats["frames"] == alone.stats["frames"] == 120
    assert est.stats["other_bodies"] == {PAYLOAD_BODY: 120}
    assert est.stats["frozen_frames"] == est.stats["restamped_frames"] == 0
    assert not bus.events and int(est.filter.rejected) == 0


def test_the_vehicles_rigid_body_is_the_one_named_by_the_option(estimator_factory):
    """``--mocap-body cf1``: the frames of ``cf1`` are the vehicle's (the same states as
    the default name gives), those named ``vehicle`` another body's."""
    named, named_bus = estimator_factory("cf1")
    fly_to(named, 0.5, payload=True, body="cf1")
    named.on_mocap(frame(0.6))  # "vehicle" is not the vehicle's name here
    default, default_bus = estimator_factory()
    fly_to(default, 0.5, payload=True)
    assert len(named_bus.states) == len(default_bus.states) == 11
    for s, ref in zip(named_bus.states, default_bus.states, strict=True):
        np.testing.assert_array_equal(s.x, ref.x)
    assert named.stats["other_bodies"] == {PAYLOAD_BODY: 60, VEHICLE_BODY: 1}
    assert not named_bus.events


def test_only_other_bodies_for_a_second_is_one_fault_naming_them_and_the_option(
    estimator_factory,
):
    """A lab's mocap names the vehicle ``cf1`` and the estimator waits for ``vehicle``:
    no state, and after a second of frames one ``fault`` event (logged as a warning) that
    names the bodies seen and the option to set, not one per frame."""
    est, bus = estimator_factory()
    fly_to(est, 0.95, payload=True, body="cf1")
    assert not bus.events  # not yet a second
    for t in np.arange(0.95, 2.0, MOCAP_DT):  # no control instant: frames alone tell it
        est.on_mocap(frame(t, "cf1"))
    assert not bus.states
    (fault,) = bus.events
    assert fault.kind == "fault" and fault.severity == "warning"
    assert fault.data == {"fault": "mocap_body_missing", "mocap_body": VEHICLE_BODY}
    assert fault.stamp == pytest.approx(T0 + 1.0, abs=MOCAP_DT)
    assert "'vehicle'" in fault.text and "'cf1', 'payload'" in fault.text
    assert "--mocap-body NAME" in fault.text
    est.on_mocap(frame(2.0))  # the vehicle's frames after all: said once
    est.on_mocap(frame(2.01))
    assert [(e.kind, e.data["fault"]) for e in bus.events[1:]] == [("info", "mocap_body_missing")]
    # With the vehicle's frames from the start, nothing is said.
    other, other_bus = estimator_factory()
    fly_to(other, 1.5, payload=True)
    assert not other_bus.events and other_bus.states


def test_a_frame_held_back_to_the_next_instant_is_fused_not_frozen(estimator_factory):
    est, bus = estimator_factory()
    fly_to(est, 0.95)
    frames_before, n_states = est.stats["frames"], len(bus.states)
    # 0.99 is on time for the instant 1.00; 1.02 was captured after it (a stalled
    # process delivers it early): it waits for the next instant.
    est.on_mocap(frame(0.99))
    est.on_mocap(frame(1.02))
    est.on_imu(Imu(gyro=np.zeros(3), stamp=T0 + 1.00))
    assert bus.states[-1].meas_stamp == pytest.approx(T0 + 0.99)
    est.on_imu(Imu(gyro=np.zeros(3), stamp=T0 + 1.05))  # no new frame this period
    state = bus.states[-1]
    assert len(bus.states) == n_states + 2
    assert state.meas_stamp == pytest.approx(T0 + 1.02)  # fused, not dropped as a repeat
    assert not state.mocap_stale
    assert est.stats["frozen_frames"] == 0
    assert not [e for e in bus.events if e.data.get("fault") == "mocap_frozen"]
    assert est.stats["frames"] == frames_before + 2  # each frame counted once


def _fake_step(x: np.ndarray):
    """A filter step whose output is ``x`` (initialised, one frame fused at the instant)."""

    def step(filt, frames, t, gyro, config):
        flags = [1.0, 0.0, 1.0, 0.0, 0.0, float(t)]
        return filt, np.concatenate([x, np.full(13, 1e-4), flags])

    return step


@pytest.mark.parametrize(
    "why, x",
    [
        # finite but no valid State: 20 km away (out of range)
        ("invalid estimate", np.r_[2e4, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0, 0, 0]),
        ("invalid estimate", np.r_[0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 0, 0]),
        ("non-finite estimate", np.r_[np.nan, np.zeros(12)]),
    ],
    ids=["out-of-range", "zero-quaternion", "non-finite"],
)
def test_a_diverged_filter_is_reset_with_a_fault_event(estimator_factory, why, x):
    est, bus = estimator_factory()
    fly_to(est, 0.5)
    n_states = len(bus.states)
    good = est._step
    est._step = _fake_step(x)
    est.on_imu(Imu(gyro=np.zeros(3), stamp=T0 + 0.55))  # never raises
    assert len(bus.states) == n_states  # nothing published
    assert est.stats["filter_resets"] == 1
    assert not bool(est.filter.initialised)  # starts again from the next frame
    (event,) = [e for e in bus.events if e.data.get("fault") == "estimator_reset"]
    assert event.kind == "fault" and event.text.startswith(why)
    est._step = good
    est.on_mocap(frame(0.56))
    est.on_imu(Imu(gyro=np.zeros(3), stamp=T0 + 0.60))
    assert len(bus.states) == n_states + 1  # running again


def test_frames_waiting_for_imu_are_bounded_and_counted(estimator_factory):
    est, _ = estimator_factory()
    for i in range(est_service.MAX_PENDING + 5):
        est.on_mocap(frame(i * MOCAP_DT))
    assert len(est._pending) == est_service.MAX_PENDING
    assert est.stats["pending_dropped"] == 5
    assert est._pending[0].capture_stamp == pytest.approx(T0 + 5 * MOCAP_DT)  # newest kept


def _options(*argv: str):
    from services import options

    parser = options.common_parser("estimator", "test")
    est_service._extra(parser)
    return parser.parse_args(list(argv))


def test_the_filter_s_noise_model_comes_from_the_options():
    from loopback import RecordingBus

    est = Estimator(_options("--jerk-psd", "7.5", "--mocap-noise", "0.001", "--lockstep"))
    est.setup(RecordingBus())
    assert est.config.jerk_psd == 7.5 and est.config.position_std == 0.001
    assert est.stats["filter"] == {"jerk_psd": 7.5, "position_std_m": 0.001}
    # Defaults: the core's (tuned for the closed loop).
    from arcade_core.estimation import FilterConfig

    default = _options()
    assert default.jerk_psd == FilterConfig().jerk_psd
    assert default.mocap_noise == FilterConfig().position_std


def test_the_vehicles_rigid_body_is_a_mocap_name():
    assert _options().mocap_body == VEHICLE_BODY
    assert _options("--mocap-body", "cf-1.quad_2").mocap_body == "cf-1.quad_2"


@pytest.mark.parametrize("value", ["", "cf 1", "cf1/body", "x" * 65])
def test_a_rigid_body_name_the_mocap_schema_refuses_is_refused(value, capsys):
    with pytest.raises(SystemExit) as exit_:
        _options(f"--mocap-body={value}")
    assert exit_.value.code == 2
    err = capsys.readouterr().err.splitlines()
    assert err[-1].endswith(
        f"argument --mocap-body: {value!r} is not a mocap rigid-body name "
        "(1 to 64 letters, digits, '_', '.', '-')"
    )


@pytest.mark.parametrize("value", ["0", "-1", "inf", "nan", "high"])
def test_a_noise_model_that_is_not_a_positive_number_is_refused(value, capsys):
    with pytest.raises(SystemExit) as exit_:
        _options("--jerk-psd", value)
    assert exit_.value.code == 2
    assert "--jerk-psd: must be a finite number above zero" in capsys.readouterr().err
