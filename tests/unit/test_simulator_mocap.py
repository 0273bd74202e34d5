"""Motion-capture and gyro emulation: statistics match the configuration, timing is honest."""

from __future__ import annotations

import numpy as np
import pytest

from arcade_core import frames
from simulator import GyroConfig, MocapConfig, QuadrotorSim
from simulator.mocap import GyroEmulator, MocapEmulator


def rotvec_error(q_true: np.ndarray, q_meas: np.ndarray) -> np.ndarray:
    """Body-frame rotation vector of q_true^-1 q_meas (small angles)."""
    d = frames.multiply_np(frames.conjugate_np(q_true), q_meas)
    return 2.0 * np.sign(d[0]) * d[1:]


def test_mocap_noise_latency_and_drops_match_the_configuration():
    cfg = MocapConfig(
        rate_hz=200.0,
        position_noise_m=3e-4,
        attitude_noise_rad=np.deg2rad(0.2),
        latency_s=0.008,
        latency_jitter_s=0.001,
        drop_probability=0.1,
    )
    emu = MocapEmulator(cfg, np.random.default_rng(7))
    p0 = np.array([0.3, -1.2, 0.9])
    q0 = frames.from_rotation_vector_np(np.array([0.1, -0.2, 0.7]))
    for k in range(40000):  # 40 s on a 1 ms physics clock
        emu.observe(k * 1e-3, p0, q0)
    assert emu.n_captured == 8000
    half = emu.read(20.0)
    rest = emu.read(1e9)
    samples = half + rest
    assert all(s.arrival <= 20.0 for s in half) and rest[0].arrival > 20.0
    n = len(samples)
    # Drops: binomial(8000, 0.1) has a standard deviation of 0.0034 in the fraction.
    drop_fraction = 1.0 - n / 8000
    assert drop_fraction == pytest.approx(0.1, abs=0.015)
    pos = np.array([s.position for s in samples])
    np.testing.assert_allclose(pos.mean(axis=0), p0, atol=4 * 3e-4 / np.sqrt(n))
    # The sample std of n ~ 7200 Gaussians is within 2.5 % (3 sigma) of the true one.
    np.testing.assert_allclose(pos.std(axis=0), 3e-4, rtol=0.05)
    att = np.array([rotvec_error(q0, s.quaternion) for s in samples])
    np.testing.assert_allclose(att.std(axis=0), np.deg2rad(0.2), rtol=0.05)
    np.testing.assert_allclose(np.linalg.norm([s.quaternion for s in samples], axis=1), 1.0)
    lat = np.array([s.arrival - s.stamp for s in samples])
    assert lat.mean() == pytest.approx(0.008, abs=1e-4)
    assert lat.std() == pytest.approx(0.001, rel=0.1)
    stamps = np.array([s.stamp for s in samples])
    gaps = np.diff(stamps) / 0.005
    np.testing.assert_allclose(gaps, np.round(gaps), atol=1e-6)  # on the 200 Hz grid
    assert np.all(np.diff([s.arrival for s in samples]) >= 0.0)  # in order


def test_gyro_bias_noise_rate_and_latency():
    cfg = GyroConfig(rate_hz=250.0, noise_rad_s=0.004, bias_std_rad_s=0.01, latency_s=0.003)
    emu = GyroEmulator(cfg, np.random.default_rng(3))
    omega = np.array([0.5, -0.2, 0.1])
    for k in range(20000):
        emu.observe(k * 1e-3, omega)
    s = emu.read(1e9)
    assert len(s) == 5000
    w = np.array([x.omega for x in s])
    np.testing.assert_allclose(w.mean(axis=0), omega + emu.bias, atol=4 * 0.004 / np.sqrt(5000))
    np.testing.assert_allclose(w.std(axis=0), 0.004, rtol=0.05)
    assert np.linalg.norm(emu.bias) > 0.0
    np.testing.assert_allclose([x.arrival - x.stamp for x in s], 0.003, atol=1e-12)
    np.testing.assert_allclose(np.diff([x.stamp for x in s]), 0.004, atol=1e-9)


def test_sim_delivers_only_arrived_samples_of_the_true_pose():
    cfg = MocapConfig(rate_hz=120.0, latency_s=0.006, drop_probability=0.05)
    sim = QuadrotorSim(mocap=cfg, seed=5)
    truth = {0: sim.reset(velocity=(1.0, 0.5, 0.0))}
    got = []
    last_read = 0.0
    for _ in range(400):  # 2 s in 5 ms control periods
        for _ in range(5):
            sim.step(0.001)
            truth[round(sim.time * 1000)] = sim.state()
        new = sim.read_mocap()
        for s in new:
            assert last_read < s.arrival <= sim.time + 1e-12  # delivered at the first read
        got.extend(new)
        last_read = sim.time
    assert 0.88 * 241 < len(got) <= 241
    err = np.array([s.position - truth[round(s.stamp * 1000)][0:3] for s in got])
    assert np.abs(err).max() < 5 * 3e-4  # the stamp names the pose that was measured
    att = np.array([rotvec_error(truth[round(s.stamp * 1000)][6:10], s.quaternion) for s in got])
    assert np.abs(att).max() < 5 * np.deg2rad(0.2)
    gyro = sim.read_gyro()
    assert len(gyro) == pytest.approx(999, abs=3) and gyro[-1].arrival <= sim.time


def test_sensor_streams_are_seeded():
    def run(seed):
        sim = QuadrotorSim(seed=seed)
        sim.step(0.3)
        return np.array([s.position for s in sim.read_mocap()]), sim.read_gyro()[-1].omega

    (p1, g1), (p2, g2), (p3, _) = run(11), run(11), run(12)
    np.testing.assert_array_equal(p1, p2)
    np.testing.assert_array_equal(g1, g2)
    assert not np.array_equal(p1, p3)


def test_sensor_configs_are_validated():
    with pytest.raises(ValueError):
        MocapConfig(drop_probability=1.0)
    with pytest.raises(ValueError):
        MocapConfig(rate_hz=0.0)
    with pytest.raises(ValueError):
        GyroConfig(noise_rad_s=-1.0)


def test_the_payload_is_a_second_body_of_each_capture_with_its_own_noise():
    """Tracking the payload leaves the vehicle's samples as they were (same seed, same
    drops and noise); the payload's pose is measured with the configured noise."""
    cfg = MocapConfig(rate_hz=200.0, drop_probability=0.1)
    p0, q0 = np.array([0.3, -1.2, 0.9]), frames.from_rotation_vector_np(np.array([0.1, 0, 0.7]))
    pay_p, pay_q = p0 - [0.0, 0.0, 0.5], frames.from_rotation_vector_np(np.array([0, 0.3, 0]))
    alone, tracked = (MocapEmulator(cfg, np.random.default_rng(7)) for _ in range(2))
    for k in range(10000):
        alone.observe(k * 1e-3, p0, q0)
        tracked.observe(k * 1e-3, p0, q0, lambda: (pay_p, pay_q))
    a, b = alone.read(1e9), tracked.read(1e9)
    assert len(a) == len(b) > 1700 and all(s.payload is None for s in a)
    for s, t in zip(a, b, strict=True):
        assert (s.stamp, s.arrival) == (t.stamp, t.arrival)
        np.testing.assert_array_equal(s.position, t.position)
    pos = np.array([t.payload[0] for t in b])
    np.testing.assert_allclose(pos.mean(axis=0), pay_p, atol=4 * 3e-4 / np.sqrt(len(b)))
    np.testing.assert_allclose(pos.std(axis=0), 3e-4, rtol=0.1)
    att = np.array([rotvec_error(pay_q, t.payload[1]) for t in b])
    np.testing.assert_allclose(att.std(axis=0), np.deg2rad(0.2), rtol=0.1)


def test_the_sim_tracks_a_swinging_payload_before_and_after_its_release():
    sim = QuadrotorSim(payload_mass=0.1, seed=3)
    sim.step(0.1)
    hanging = sim.read_mocap()
    truth = sim.payload_position()
    assert hanging and all(s.payload is not None for s in hanging)
    np.testing.assert_allclose(hanging[-1].payload[0], truth, atol=5 * 3e-4)
    assert hanging[-1].position[2] - truth[2] > sim.cable_length  # below the vehicle
    sim.release_payload()
    sim.step(0.2)
    falling = sim.read_mocap()[-1].payload[0]
    assert falling[2] < truth[2] - 0.1  # still seen: a tracked object does not vanish
    assert QuadrotorSim(seed=3).mocap.read(np.inf)[0].payload is None  # no payload: one body


def test_the_stream_puts_the_vehicle_then_the_payload_of_each_capture():
    """One record per body with the capture's stamps; a dropout loses the capture, a
    clock jump moves both bodies, a freeze holds only the vehicle's pose."""
    from services.messages import PAYLOAD_BODY, VEHICLE_BODY
    from services.sim_mocap import MocapStream
    from simulator.mocap import MocapSample

    class Bus:
        def __init__(self) -> None:
            self.put_records: list = []

        def publisher(self, topic):
            assert topic == "mocap"
            return type("Pub", (), {"put": lambda _, r: self.put_records.append(r)})()

    def capture(t: float) -> MocapSample:
        q = np.array([1.0, 0.0, 0.0, 0.0])
        return MocapSample(t, t + 0.007, np.array([t, 0, 1.0]), q, (np.array([t, 0, 0.5]), q))

    bus = Bus()
    faults = ["dropout@1+0.5", "clockjump@2+0.5,offset=3", "freeze@3+0.5"]
    stream = MocapStream(bus, faults, seed=0)
    stream.publish([capture(t) for t in (0.5, 1.2, 2.2, 2.9, 3.2)], lambda t: 10 + t, float)
    got = [(r.body, r.capture_stamp, r.stamp, r.position[0]) for r in bus.put_records]
    assert [g[0] for g in got] == [VEHICLE_BODY, PAYLOAD_BODY] * 4
    for v, p in zip(got[0::2], got[1::2], strict=True):
        assert v[1:3] == p[1:3]  # one capture
    assert [g[1] for g in got[0::2]] == pytest.approx([10.5, 15.2, 12.9, 13.2])
    assert got[-2][3] == pytest.approx(2.9) and got[-1][3] == pytest.approx(3.2)  # frozen
    assert stream.fault_counts == {"dropout": 1, "freeze": 1, "outliers": 0, "clockjump": 1}
    # The vehicle's rigid body under the name --mocap-body gives.
    bus = Bus()
    MocapStream(bus, [], seed=0, vehicle_body="cf1").publish([capture(0.5)], float, float)
    assert [r.body for r in bus.put_records] == ["cf1", PAYLOAD_BODY]


def test_the_simulators_refuse_to_name_the_vehicle_as_the_payload(capsys):
    from services import options
    from services.messages import PAYLOAD_BODY
    from services.sim_options import add_sim_arguments

    parser = options.common_parser("sim", "test")
    add_sim_arguments(parser)
    assert parser.parse_args(["--mocap-body", "cf1"]).mocap_body == "cf1"
    with pytest.raises(SystemExit):
        parser.parse_args(["--mocap-body", PAYLOAD_BODY])
    err = capsys.readouterr().err.splitlines()[-1]
    assert err.endswith("argument --mocap-body: 'payload' is the simulated payload's rigid body")


def test_without_motion_capture_the_flight_is_the_same_and_no_frame_is_captured():
    # Log flights read the true state only: without the emulator, the same states (the
    # mocap noise has its own random stream), and no frames.
    sims = [QuadrotorSim(seed=3, motion_capture=on) for on in (True, False)]
    states = []
    for sim in sims:
        sim.set_setpoint(np.array([6.0, 0.3, -0.2, 0.1]))
        states.append(np.stack([sim.step(0.01) for _ in range(50)]))
    np.testing.assert_array_equal(states[0], states[1])
    assert len(sims[0].read_mocap()) > 0 and sims[0].mocap.n_captured > 0
    assert sims[1].read_mocap() == [] and sims[1].mocap.n_captured == 0
