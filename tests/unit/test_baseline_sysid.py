"""SysID baseline: STLSQ recovers a sparse polynomial + trigonometric residual exactly."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from arcade_core.baselines import sysid

# Ground truth over x = (x0, x1, x2 = angle), u = (u0); three residual components.
TRUTH = {
    0: {"x1": 0.5, "x0*x2": -0.3, "sin(x2)": 0.8},
    1: {"1": -0.1, "u0*cos(x2)": 1.2, "x1^2": 0.05},
    2: {},  # no residual at all
}


def _truth(x, u):
    x0, x1, x2, u0 = x[:, 0], x[:, 1], x[:, 2], u[:, 0]
    return jnp.stack(
        [
            0.5 * x1 - 0.3 * x0 * x2 + 0.8 * jnp.sin(x2),
            -0.1 + 1.2 * u0 * jnp.cos(x2) + 0.05 * x1**2,
            jnp.zeros_like(x0),
        ],
        axis=1,
    )


@pytest.fixture(scope="module")
def data():
    k1, k2 = jax.random.split(jax.random.PRNGKey(0))
    x = jax.random.uniform(k1, (400, 3), minval=-2.0, maxval=2.0)
    u = jax.random.uniform(k2, (400, 1), minval=-1.0, maxval=1.0)
    return x, u, _truth(x, u)


def test_library_terms():
    lib = sysid.make_library(3, 1, degree=2, angle_indices=(2,))
    # 1 + 4 linear + 10 quadratic, then sin/cos of x2 alone and times each variable.
    assert lib.size == 15 + 2 * 5
    assert lib.names[:6] == ("1", "x0", "x1", "x2", "u0", "x0^2")
    assert {"sin(x2)", "cos(x2)", "u0*cos(x2)", "x0*sin(x2)", "x1*u0"} <= set(lib.names)
    z = jnp.array([0.5, -1.0, 0.3, 2.0])
    row = dict(zip(lib.names, np.asarray(lib(z))))
    np.testing.assert_allclose(row["u0*cos(x2)"], 2.0 * np.cos(0.3))
    np.testing.assert_allclose(row["x1^2"], 1.0)
    np.testing.assert_allclose(row["1"], 1.0)
    cubic = sysid.make_library(2, 1, degree=3)
    assert cubic.size == 20 and "x0^2*u0" in cubic.names


def test_recovers_sparse_coefficients_exactly(data):
    x, u, delta = data
    model = sysid.fit(x, u, delta, degree=2, angle_indices=(2,), threshold=0.02)
    names = model.terms.names
    coef, active = np.asarray(model.coef), np.asarray(model.active)
    for j, terms in TRUTH.items():
        assert {names[t] for t in np.flatnonzero(active[:, j])} == set(terms)
        expected = np.array([terms.get(n, 0.0) for n in names])
        np.testing.assert_allclose(coef[:, j], expected, atol=1e-6)
    listing = sysid.active_terms(model, ["dx1", "dx2", "dx3"])
    assert dict(listing["dx2"]) == pytest.approx(TRUTH[1], abs=1e-6)
    assert listing["dx3"] == []
    # Predictions are exact and differentiable (used inside MPC rollouts).
    pred = jax.vmap(lambda a, b: sysid.predict(model, a, b))(x[:20], u[:20])
    np.testing.assert_allclose(pred, delta[:20], atol=1e-6)
    g = jax.grad(lambda a: sysid.predict(model, a, jnp.zeros(1))[0])(jnp.zeros(3))
    assert np.all(np.isfinite(np.asarray(g)))
    np.testing.assert_allclose(g, [0.0, 0.5, 0.8], atol=1e-6)


def test_threshold_prunes_small_terms(data):
    x, u, delta = data
    # Normalised contributions in component 1: u0*cos(x2) ~ 1.0, x1^2 ~ 0.2, 1 ~ 0.2.
    model = sysid.fit(x, u, delta, degree=2, angle_indices=(2,), threshold=0.3)
    listing = dict(sysid.active_terms(model)["delta1"])
    assert set(listing) == {"u0*cos(x2)"}
    assert listing["u0*cos(x2)"] == pytest.approx(1.2, abs=0.05)
