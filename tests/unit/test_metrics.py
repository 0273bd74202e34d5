"""Metrics of Sec. V against hand-computed values and numpy references."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from arcade_core import metrics


def test_crmse_hand_values():
    x = np.array([[1.0, 1.0], [2.0, -2.0], [3.0, 3.0]])
    x_hat = np.zeros_like(x)
    np.testing.assert_allclose(metrics.crmse_curve(x, x_hat), [1.0, 3.0, 6.0], rtol=0, atol=1e-15)
    assert float(metrics.crmse(x, x_hat)) == pytest.approx(6.0, abs=1e-15)
    # D = 1 given as a vector; unequal errors per component average inside the root.
    np.testing.assert_allclose(metrics.crmse_curve(np.array([3.0, -4.0]), np.zeros(2)), [3, 7])
    assert float(metrics.crmse(np.array([[3.0, 4.0]]), np.zeros((1, 2)))) == pytest.approx(
        np.sqrt(12.5), abs=1e-14
    )


def test_crmse_matches_footnote_formula_on_random_data():
    rng = np.random.default_rng(0)
    x, x_hat = rng.normal(size=(40, 5)), rng.normal(size=(40, 5))
    expected = sum(np.sqrt(np.mean((x[k] - x_hat[k]) ** 2)) for k in range(40))
    assert float(metrics.crmse(x, x_hat)) == pytest.approx(expected, rel=1e-13)


def test_rmse_family():
    p_ref = np.zeros((2, 3))
    p = np.array([[1.0, 2.0, 2.0], [0.0, 0.0, 0.0]])  # position error norms 3 and 0
    assert float(metrics.position_rmse(p, p_ref)) == pytest.approx(np.sqrt(9 / 2), abs=1e-15)
    assert float(metrics.z_rmse(p, p_ref)) == pytest.approx(np.sqrt(2.0), abs=1e-15)
    assert float(metrics.rmse(p, p_ref)) == pytest.approx(np.sqrt(9 / 6), abs=1e-15)
    np.testing.assert_allclose(metrics.rmse_per_component(p, p_ref), np.sqrt([0.5, 2.0, 2.0]))


def test_increment_rms_hand_values():
    # Channel 0 steps by +1, -1, +1; channel 1 is constant; a ramp has a constant increment.
    u = np.array([[0.0, 5.0], [1.0, 5.0], [0.0, 5.0], [1.0, 5.0]])
    np.testing.assert_allclose(metrics.increment_rms(u), [1.0, 0.0], atol=1e-15)
    ramp = np.linspace(0.0, 3.0, 7)[:, None]
    np.testing.assert_allclose(metrics.increment_rms(ramp), [0.5], rtol=1e-14)


def _drop_signal():
    t = np.round(np.arange(0.0, 3.0 + 1e-9, 0.1), 10)
    e = np.full_like(t, 0.01)
    e[t > 1.0] = [-0.1, -0.2, -0.15, -0.04, 0.03, 0.02, 0.06, 0.01, 0.0, 0.0] + [0.0] * 10
    e[t >= 2.5] = 0.3  # a later excursion outside the shift window
    return t, e


def test_shift_magnitude_uses_last_pre_drop_sample_and_window_extreme():
    t, e = _drop_signal()
    # e(t_drop^-) = 0.01 at t = 1.0; largest deviation in (1.0, 1.5] is -0.2 at t = 1.2.
    assert float(metrics.shift_magnitude(t, e, 1.0)) == pytest.approx(0.21, abs=1e-12)
    # A window of one sample sees only the first post-drop sample.
    assert float(metrics.shift_magnitude(t, e, 1.0, window=0.1)) == pytest.approx(0.11, abs=1e-12)
    # A window reaching the later excursion at 2.5 s picks it up.
    assert float(metrics.shift_magnitude(t, e, 1.0, window=2.0)) == pytest.approx(0.29, abs=1e-12)
    # No sample before the drop: undefined.
    assert np.isnan(float(metrics.shift_magnitude(t, e, -1.0)))


def test_settling_time_on_constructed_signal():
    t, e = _drop_signal()
    e = e.copy()
    e[t >= 2.5] = 0.0
    # Last sample outside the 0.05 band after the drop is 0.06 at t = 1.7 -> settled at 1.8.
    s = metrics.settling_time(t, e, 1.0)
    assert bool(s.settled) and float(s.time) == pytest.approx(0.8, abs=1e-12)
    # A wider band ignores the 0.06 bump: last outside is -0.15 at 1.3.
    assert float(metrics.settling_time(t, e, 1.0, band=0.1).time) == pytest.approx(0.4, abs=1e-12)
    # Errors before the drop do not count; inside the band from the start -> 0.
    e_pre = np.where(t < 1.0, 1.0, 0.0)
    assert float(metrics.settling_time(t, e_pre, 1.0).time) == 0.0


def test_settling_time_never_settles_is_flagged_inf():
    t, e = _drop_signal()  # ends at 0.3, outside the band
    s = metrics.settling_time(t, e, 1.0)
    assert not bool(s.settled)
    assert np.isinf(float(s.time))


def test_settling_time_counts_non_finite_error_as_outside_the_band():
    t, e = _drop_signal()
    e[t >= 2.5] = 0.0
    # A diverged sample after the drop is not inside the band: settled from the next one.
    e_nan = e.copy()
    e_nan[t == 2.0] = np.nan
    s = metrics.settling_time(t, e_nan, 1.0)
    assert bool(s.settled) and float(s.time) == pytest.approx(1.1, abs=1e-12)
    # A record that ends diverged never settled.
    e_inf = e.copy()
    e_inf[-1] = np.inf
    s = metrics.settling_time(t, e_inf, 1.0)
    assert not bool(s.settled) and np.isinf(float(s.time))
    e_nan[-1] = np.nan
    assert not bool(metrics.settling_time(t, e_nan, 1.0).settled)


def test_settling_time_without_samples_after_the_drop_is_undefined():
    t, e = _drop_signal()
    e[:] = 0.0
    s = metrics.settling_time(t, e, 5.0)  # the record ends at 3.0 s
    assert not bool(s.settled) and np.isnan(float(s.time))
    assert np.isnan(float(metrics.shift_magnitude(t, e, 5.0)))  # the two agree
    s = jax.jit(metrics.settling_time)(t, e, jnp.asarray(5.0))
    assert not bool(s.settled) and np.isnan(float(s.time))
    # The last sample exactly at the drop time still counts as "after".
    s = metrics.settling_time(t, e, 3.0)
    assert bool(s.settled) and float(s.time) == 0.0


def test_drop_metrics_jit_with_traced_drop_time():
    t, e = _drop_signal()
    e[t >= 2.5] = 0.0
    settle = jax.jit(metrics.settling_time)(t, e, jnp.asarray(1.0))
    shift = jax.jit(metrics.shift_magnitude)(t, e, jnp.asarray(1.0))
    assert float(settle.time) == pytest.approx(0.8, abs=1e-12)
    assert float(shift) == pytest.approx(0.21, abs=1e-12)


def test_gramian_diagnostics_match_numpy():
    rng = np.random.default_rng(1)
    z = rng.normal(size=(40, 3))
    diag = jax.jit(metrics.gramian_diagnostics, static_argnames="windows")(z, windows=(5, 15))
    for t in range(40):
        g = z[: t + 1].T @ z[: t + 1]
        lam = np.linalg.eigvalsh(g)
        assert float(diag.lambda_max[t]) == pytest.approx(lam[-1], rel=1e-10)
        if t >= 2:  # rank 3 from the third sample on
            assert float(diag.lambda_min[t]) == pytest.approx(lam[0], rel=1e-8)
            assert float(diag.condition[t]) == pytest.approx(lam[-1] / lam[0], rel=1e-8)
            assert float(diag.logdet[t]) == pytest.approx(np.linalg.slogdet(g)[1], rel=1e-9)
        for row, w in enumerate((5, 15)):
            if t < w - 1:
                assert np.isnan(float(diag.window_lambda_min[row, t]))
            else:
                zw = z[t - w + 1 : t + 1]
                ref = np.linalg.eigvalsh(zw.T @ zw)[0]
                assert float(diag.window_lambda_min[row, t]) == pytest.approx(ref, rel=1e-8)
    np.testing.assert_array_equal(diag.windows, [5, 15])


def test_gramian_singular_prefix_is_flagged():
    z = np.array([[1.0, 0.0], [2.0, 0.0], [0.0, 1.0]])
    diag = metrics.gramian_diagnostics(z, windows=(2, 10))
    # G_1, G_2 have rank 1 (exact zeros here): infinite condition, -inf log det.
    assert np.all(np.isinf(np.asarray(diag.condition[:2])))
    assert np.all(np.isneginf(np.asarray(diag.logdet[:2])))
    assert float(diag.logdet[2]) == pytest.approx(np.log(5.0), abs=1e-12)
    assert float(diag.condition[2]) == pytest.approx(5.0, abs=1e-12)
    # Window 2 at t=1 holds two parallel vectors: lambda_min 0; W > T: all NaN.
    assert float(diag.window_lambda_min[0, 1]) == pytest.approx(0.0, abs=1e-12)
    assert np.all(np.isnan(np.asarray(diag.window_lambda_min[1])))
