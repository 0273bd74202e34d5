"""VLD encoder/decoder (Sec. III-A, Eq. 2-3), the MAP encoder (Appendix E), training,
the residual dataset builder and weight files."""

import json

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from arcade_core import encoder as enc
from arcade_io import weights

C_TRUE = np.array([[1.0, 0.5], [-0.3, 2.0], [0.7, -1.0]])
N_TRAIN = 1536


def _synthetic(n: int = 2048, seed: int = 0):
    """Residual linear in two nonlinear features of (x, u), in small physical units."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(n, 3)) * np.array([1.0, 2.0, 0.5]) + np.array([0.0, 1.0, -3.0])
    u = rng.normal(size=(n, 1))
    h = np.stack([np.sin(2.0 * x[:, 0]), 0.5 * (x[:, 1] - 1.0) * u[:, 0]], axis=1)
    delta = 0.01 * h @ C_TRUE.T + 1e-4 * rng.normal(size=(n, 3))
    return x, u, delta


SMALL = enc.EncoderConfig(
    x_dim=3, u_dim=1, d=3, hidden=(32, 32), latent_dim=2, lr=1e-2, batch_size=64, epochs=40
)


def _r2(model, x, u, delta):
    pred = np.asarray(jax.vmap(model.predict_residual)(x, u))
    return 1.0 - np.sum((pred - delta) ** 2, 0) / np.sum((delta - delta.mean(0)) ** 2, 0)


@pytest.fixture(scope="module")
def data():
    return _synthetic()


@pytest.fixture(scope="module")
def trained(data):
    x, u, delta = data
    calls = []
    model, hist = enc.train(
        jax.random.PRNGKey(0),
        SMALL,
        x[:N_TRAIN],
        u[:N_TRAIN],
        delta[:N_TRAIN],
        val=(x[N_TRAIN:], u[N_TRAIN:], delta[N_TRAIN:]),
        callback=lambda *a: calls.append(a),
    )
    return model, hist, calls


@pytest.fixture(scope="module")
def trained_map(data):
    x, u, delta = data
    cfg = SMALL._replace(variational=False)
    model, hist = enc.train(jax.random.PRNGKey(0), cfg, x[:N_TRAIN], u[:N_TRAIN], delta[:N_TRAIN])
    return model, hist


# --------------------------------------------------------------------------- config


def test_presets_follow_appendix_d():
    cp, qr = enc.preset("cartpole"), enc.preset("quadrotor")
    assert (cp.hidden, cp.latent_dim, cp.activation, cp.kl_weight) == ((8, 16, 8), 2, "elu", 0.1)
    assert (cp.lr, cp.batch_size, cp.epochs, cp.variational) == (1e-3, 128, 50, True)
    assert (cp.x_dim, cp.u_dim, cp.d) == (4, 1, 4)
    assert (qr.hidden, qr.latent_dim, qr.activation, qr.kl_weight) == ((64, 128, 64), 8, "elu", 0.1)
    assert (qr.lr, qr.batch_size, qr.epochs) == (1e-3, 256, 100)
    assert (qr.x_dim, qr.u_dim, qr.d) == (13, 4, 13)
    with pytest.raises(ValueError):
        enc.preset("boat")


def test_config_dict_round_trip_and_validation():
    cfg = enc.quadrotor_config(variational=False, lambda_phi=0.5)
    again = enc.EncoderConfig.from_dict(json.loads(json.dumps(cfg.to_dict())))
    assert again == cfg and isinstance(again.hidden, tuple)
    with pytest.raises(ValueError, match="unknown"):
        enc.EncoderConfig.from_dict({**cfg.to_dict(), "dropout": 0.1})
    with pytest.raises(ValueError, match="activation"):
        enc.validate_config(cfg._replace(activation="sigmoidish"))
    with pytest.raises(ValueError, match="hidden"):
        enc.validate_config(cfg._replace(hidden=()))


# --------------------------------------------------------------------------- objective


def test_kl_matches_closed_form_and_monte_carlo():
    mu = np.array([0.3, -1.2, 2.0])
    logvar = np.array([-1.0, 0.5, -3.0])
    var = np.exp(logvar)
    # Multivariate normal KL to N(0, I): (tr S + mu^T mu - k - log det S) / 2.
    s = np.diag(var)
    closed = 0.5 * (np.trace(s) + mu @ mu - 3 - np.log(np.linalg.det(s)))
    assert float(enc.kl_divergence(mu, logvar)) == pytest.approx(closed, rel=1e-12)
    # Monte Carlo E_q[log q(z) - log p(z)] with the reparameterised sampler.
    z = np.asarray(enc.reparameterise(jax.random.PRNGKey(3), np.tile(mu, (200_000, 1)), logvar))
    log_q = -0.5 * np.sum((z - np.asarray(mu)) ** 2 / var + np.log(2 * np.pi * var), axis=1)
    log_p = -0.5 * np.sum(z**2 + np.log(2 * np.pi), axis=1)
    mc = log_q - log_p
    assert abs(mc.mean() - closed) < 4 * mc.std() / np.sqrt(mc.size)
    assert float(enc.kl_divergence(jnp.zeros(4), jnp.zeros(4))) == 0.0


def test_reparameterisation_moments():
    mu = jnp.array([1.5, -0.5])
    logvar = jnp.array([np.log(0.25), np.log(4.0)])
    n = 100_000
    z = np.asarray(enc.reparameterise(jax.random.PRNGKey(7), jnp.tile(mu, (n, 1)), logvar))
    sd = np.array([0.5, 2.0])
    assert np.all(np.abs(z.mean(0) - np.asarray(mu)) < 4 * sd / np.sqrt(n))
    # Var of the sample variance of a normal: 2 sigma^4 / (n - 1).
    assert np.all(np.abs(z.var(0, ddof=1) - sd**2) < 4 * np.sqrt(2 / (n - 1)) * sd**2)
    assert abs(np.corrcoef(z.T)[0, 1]) < 4 / np.sqrt(n)
    # Gradients flow through mu and logvar (the point of the trick).
    g = jax.grad(lambda m, lv: jnp.sum(enc.reparameterise(jax.random.PRNGKey(0), m, lv)), (0, 1))
    gm, glv = g(mu, logvar)
    np.testing.assert_allclose(gm, [1.0, 1.0])
    assert np.all(np.asarray(glv) != 0.0)


def test_vld_loss_is_reconstruction_plus_weighted_kl(data):
    x, u, delta = (a[:64] for a in data)
    model = enc.VLD.create(jax.random.PRNGKey(1), SMALL, x, u, delta)
    dn = model.normalise_residual(delta)
    key = jax.random.PRNGKey(5)
    terms = enc.vld_loss(model, key, x, u, dn, kl_weight=0.1)
    mu, logvar = (np.asarray(a) for a in jax.vmap(model.encode)(x, u))
    z = mu + np.exp(0.5 * logvar) * np.asarray(jax.random.normal(key, mu.shape))
    recon = np.mean(np.sum((np.asarray(dn) - np.asarray(z) @ np.asarray(model.theta0).T) ** 2, 1))
    kl = np.mean(0.5 * np.sum(np.exp(logvar) + mu**2 - 1 - logvar, 1))
    assert float(terms.recon) == pytest.approx(recon, rel=1e-12)
    assert float(terms.kl) == pytest.approx(kl, rel=1e-12)
    assert float(terms.total) == pytest.approx(recon + 0.1 * kl, rel=1e-12)
    # Stochastic objective: another key gives another value.
    other = enc.vld_loss(model, jax.random.PRNGKey(6), x, u, dn, kl_weight=0.1)
    assert float(other.recon) != float(terms.recon)


def test_map_encoder_is_deterministic_without_variance_head(data):
    x, u, delta = (a[:64] for a in data)
    cfg = SMALL._replace(variational=False, lambda_theta=0.3, lambda_phi=0.02)
    model = enc.VLD.create(jax.random.PRNGKey(1), cfg, x, u, delta)
    vld = enc.VLD.create(jax.random.PRNGKey(1), SMALL, x, u, delta)
    assert model.logvar_head is None and not model.variational
    assert vld.logvar_head is not None and vld.variational
    mu, logvar = model.encode(x[0], u[0])
    assert np.all(np.isneginf(np.asarray(logvar)))
    np.testing.assert_array_equal(model.latent_variance(x[0], u[0]), np.zeros(2))
    assert np.all(np.asarray(vld.latent_variance(x[0], u[0])) > 0.0)
    np.testing.assert_array_equal(mu, model.features(x[0], u[0]))

    dn = model.normalise_residual(delta)
    t1 = enc.objective(model, jax.random.PRNGKey(0), x, u, dn, cfg)
    t2 = enc.objective(model, jax.random.PRNGKey(9), x, u, dn, cfg)
    assert float(t1.total) == float(t2.total)  # no sampling in the MAP objective
    z = np.asarray(jax.vmap(model.features)(x, u))
    th = np.asarray(model.theta0)
    recon = np.mean(np.sum((np.asarray(dn) - z @ th.T) ** 2, 1))
    w2 = sum(np.sum(np.asarray(layer.weight) ** 2) for layer in model.layers)
    w2 += np.sum(np.asarray(model.mean_head.weight) ** 2)
    expected = recon + 0.3 * np.sum(th**2) + 0.02 * w2
    assert float(t1.total) == pytest.approx(expected, rel=1e-12)
    assert float(t1.kl) == 0.0


# --------------------------------------------------------------------------- module


def test_create_fits_normalisation(data):
    x, u, delta = data
    model = enc.VLD.create(jax.random.PRNGKey(0), SMALL, x, u, delta)
    np.testing.assert_allclose(model.x_mean, x.mean(0), rtol=1e-12)
    np.testing.assert_allclose(model.x_std, x.std(0), rtol=1e-12)
    np.testing.assert_allclose(model.u_std, u.std(0), rtol=1e-12)
    np.testing.assert_allclose(model.delta_scale, np.sqrt(np.mean(delta**2, 0)), rtol=1e-12)
    dn = model.normalise_residual(delta)
    np.testing.assert_allclose(np.sqrt(np.mean(np.asarray(dn) ** 2, 0)), 1.0, rtol=1e-12)
    np.testing.assert_allclose(model.denormalise_residual(dn), delta, rtol=1e-14)
    # A constant input column is floored, not divided by zero.
    xc = x.copy()
    xc[:, 2] = 4.0
    floored = enc.VLD.create(jax.random.PRNGKey(0), SMALL, xc, u, delta, min_std=1e-3)
    assert float(floored.x_std[2]) == 1e-3
    with pytest.raises(ValueError, match="expected"):
        enc.VLD.create(jax.random.PRNGKey(0), SMALL, x[:, :2], u, delta)


def test_features_invariant_to_affine_change_of_units(data):
    x, u, delta = data
    a = enc.VLD.create(jax.random.PRNGKey(2), SMALL, x, u, delta)
    scale, shift = np.array([10.0, 0.1, 3.0]), np.array([5.0, -2.0, 0.0])
    b = enc.VLD.create(jax.random.PRNGKey(2), SMALL, x * scale + shift, u, 1000.0 * delta)
    za = jax.vmap(a.features)(x[:10], u[:10])
    zb = jax.vmap(b.features)(x[:10] * scale + shift, u[:10])
    np.testing.assert_allclose(za, zb, rtol=1e-10, atol=1e-12)
    # Residuals come back in the caller's units.
    np.testing.assert_allclose(
        jax.vmap(b.predict_residual)(x[:10] * scale + shift, u[:10]),
        1000.0 * np.asarray(jax.vmap(a.predict_residual)(x[:10], u[:10])),
        rtol=1e-10,
    )


def test_predict_residual_uses_given_theta_and_batches_by_vmap(data):
    x, u, delta = data
    model = enc.VLD.create(jax.random.PRNGKey(0), SMALL, x, u, delta)
    theta = jnp.arange(6.0).reshape(3, 2)
    z = model.features(x[0], u[0])
    np.testing.assert_allclose(
        model.predict_residual(x[0], u[0], theta), model.delta_scale * (theta @ z), rtol=1e-14
    )
    batched = jax.jit(jax.vmap(model.features))(x[:5], u[:5])
    looped = np.stack([model.features(x[i], u[i]) for i in range(5)])
    np.testing.assert_allclose(batched, looped, rtol=1e-12)


# --------------------------------------------------------------------------- training


def test_training_reduces_loss_and_fits_linear_in_features_residual(data, trained):
    x, u, delta = data
    model, hist, calls = trained
    untrained = enc.VLD.create(
        jax.random.PRNGKey(0), SMALL, x[:N_TRAIN], u[:N_TRAIN], delta[:N_TRAIN]
    )
    tl, vm = np.asarray(hist.train_loss), np.asarray(hist.val_mse)
    assert tl.shape == (SMALL.epochs,) and np.all(np.isfinite(tl))
    assert tl[-1] < 0.25 * tl[0]
    assert vm[-1] < 0.1 * vm[0]
    held_out = (x[N_TRAIN:], u[N_TRAIN:], delta[N_TRAIN:])
    r2 = _r2(model, *held_out)
    assert np.all(r2 > 0.95), r2
    assert np.all(_r2(untrained, *held_out) < 0.5)
    # Progress callback: once per epoch, numbered from 1, with the recorded losses.
    assert [c[0] for c in calls] == list(range(1, SMALL.epochs + 1))
    assert [c[1] for c in calls] == pytest.approx(list(tl))
    assert [c[2] for c in calls] == pytest.approx(list(np.asarray(hist.val_loss)))


def test_training_keeps_normalisation_and_learns_a_variance(data, trained):
    x, u, delta = data
    model, _, _ = trained
    ref = enc.VLD.create(jax.random.PRNGKey(0), SMALL, x[:N_TRAIN], u[:N_TRAIN], delta[:N_TRAIN])
    for name in ("x_mean", "x_std", "u_mean", "u_std", "delta_scale"):
        np.testing.assert_array_equal(getattr(model, name), getattr(ref, name))
    # The KL term keeps the posterior variance positive but the reconstruction shrinks it
    # below the prior's unit variance along used directions.
    var = np.asarray(jax.vmap(model.latent_variance)(x[:200], u[:200]))
    assert np.all(var > 0.0) and np.median(var) < 0.5


def test_map_training_fits_and_reports_no_validation(data, trained_map):
    x, u, delta = data
    model, hist = trained_map
    assert model.logvar_head is None
    assert np.all(np.isnan(np.asarray(hist.val_loss)))
    assert float(hist.train_loss[-1]) < 0.25 * float(hist.train_loss[0])
    assert np.all(_r2(model, x[N_TRAIN:], u[N_TRAIN:], delta[N_TRAIN:]) > 0.95)


def test_training_is_deterministic_given_key(data):
    x, u, delta = (a[:256] for a in data)
    cfg = SMALL._replace(epochs=2)
    m1, h1 = enc.train(jax.random.PRNGKey(4), cfg, x, u, delta)
    m2, h2 = enc.train(jax.random.PRNGKey(4), cfg, x, u, delta)
    m3, _ = enc.train(jax.random.PRNGKey(5), cfg, x, u, delta)
    leaves = lambda m: jax.tree_util.tree_leaves(eqx.filter(m, eqx.is_array))  # noqa: E731
    assert all(np.array_equal(a, b) for a, b in zip(leaves(m1), leaves(m2)))
    np.testing.assert_array_equal(h1.train_loss, h2.train_loss)
    assert not np.array_equal(m1.theta0, m3.theta0)


# --------------------------------------------------------------------------- dataset


def test_residual_dataset():
    def f_nom(x, u):
        return x + 0.1 * jnp.array([x[1], u[0]])

    X = jnp.array([[0.0, 1.0], [0.2, 1.1], [0.3, 1.5], [0.5, 1.4]])
    U = jnp.array([[1.0], [2.0], [-1.0]])
    x, u, delta = enc.residual_dataset(f_nom, X, U)
    np.testing.assert_array_equal(x, X[:3])
    np.testing.assert_array_equal(u, U)
    expected = [X[k + 1] - f_nom(X[k], U[k]) for k in range(3)]
    np.testing.assert_allclose(delta, np.stack(expected), rtol=0, atol=1e-15)
    np.testing.assert_allclose(delta[0], [0.1, 0.0], atol=1e-15)
    with pytest.raises(ValueError, match="T\\+1"):
        enc.residual_dataset(f_nom, X, U[:2])


# --------------------------------------------------------------------------- weight files


def _leaves_equal(a, b):
    la = jax.tree_util.tree_leaves(eqx.filter(a, eqx.is_array))
    lb = jax.tree_util.tree_leaves(eqx.filter(b, eqx.is_array))
    return len(la) == len(lb) and all(
        x.dtype == y.dtype and np.array_equal(x, y) for x, y in zip(la, lb)
    )


def test_weights_round_trip_exact(tmp_path, trained, trained_map):
    model, _, _ = trained
    extra = {"system": "synthetic", "data": {"samples": N_TRAIN}, "val_mse": 0.01}
    path = weights.save_model(tmp_path / "m.vld", model, SMALL, extra)
    loaded, cfg, got_extra = weights.load_model(path, expected_config=SMALL)
    assert cfg == SMALL and got_extra == extra
    assert _leaves_equal(model, loaded)
    assert jax.tree_util.tree_structure(model) == jax.tree_util.tree_structure(loaded)
    np.testing.assert_array_equal(
        loaded.predict_residual(jnp.ones(3), jnp.ones(1)),
        model.predict_residual(jnp.ones(3), jnp.ones(1)),
    )
    header = weights.read_header(path)
    assert header["config"]["latent_dim"] == 2 and header["dtype"] == "float64"

    map_model, _ = trained_map
    map_cfg = SMALL._replace(variational=False)
    weights.save_model(tmp_path / "map.vld", map_model, map_cfg)
    loaded_map, cfg2, extra2 = weights.load_model(tmp_path / "map.vld")
    assert cfg2 == map_cfg and extra2 == {} and loaded_map.logvar_head is None
    assert _leaves_equal(map_model, loaded_map)


def test_weights_reject_corrupt_and_mismatched_files(tmp_path, trained):
    model, _, _ = trained
    path = weights.save_model(tmp_path / "m.vld", model, SMALL, {"system": "synthetic"})
    blob = path.read_bytes()

    def write(name, data):
        p = tmp_path / name
        p.write_bytes(data)
        return p

    flipped = bytearray(blob)
    flipped[-20] ^= 0x01
    with pytest.raises(weights.WeightFileError, match="checksum"):
        weights.load_model(write("flip.vld", bytes(flipped)))
    with pytest.raises(weights.WeightFileError, match="payload"):
        weights.load_model(write("trunc.vld", blob[:-100]))
    with pytest.raises(weights.WeightFileError, match="magic"):
        weights.load_model(write("magic.vld", b"NOT-A-MODEL" + blob[11:]))
    with pytest.raises(weights.WeightFileError, match="header"):
        weights.load_model(write("short.vld", blob[:30]))
    with pytest.raises(FileNotFoundError, match="not found"):
        weights.load_model(tmp_path / "missing.vld")
    with pytest.raises(weights.WeightFileError, match="mismatch"):
        weights.load_model(path, expected_config=SMALL._replace(latent_dim=3))

    # A header whose config no longer describes the payload (valid checksum).
    n = int.from_bytes(blob[11:19], "little")
    header = json.loads(blob[19 : 19 + n])
    header["config"]["hidden"] = [32, 16]
    hb = json.dumps(header).encode()
    tampered = blob[:11] + len(hb).to_bytes(8, "little") + hb + blob[19 + n :]
    with pytest.raises(weights.WeightFileError, match="does not match"):
        weights.load_model(write("tampered.vld", tampered))


def test_save_rejects_inconsistent_inputs(tmp_path, trained):
    model, _, _ = trained
    with pytest.raises(ValueError, match="does not match"):
        weights.save_model(tmp_path / "x.vld", model, SMALL._replace(latent_dim=4))
    with pytest.raises(ValueError, match="JSON"):
        weights.save_model(tmp_path / "y.vld", model, SMALL, {"bad": object()})
    assert not list(tmp_path.iterdir())  # nothing half-written
