"""Variational Latent Dynamics (VLD) encoder/decoder and its offline training (Sec. III-A).

The residual of the nominal model, ``delta_k = x_{k+1} - f_nom(x_k, u_k)``, is modelled
as ``delta_k ≈ theta z_k`` with ``z_k ~ q_phi(z | x_k, u_k) = N(mu_phi, diag sigma_phi^2)``
(Eq. 2). Training maximises the variational bound of Eq. 3 with the reparameterisation
trick; the deterministic MAP encoder of Appendix E (ridge penalties ``lambda_theta``,
``lambda_phi``, no variance head) is the same module with ``variational=False``.

Design decisions (the paper is silent on them):

* **Normalisation lives in the module.** Inputs are standardised with the training
  mean/std of ``x`` and ``u`` (std floored so that near-constant inputs such as ``q_w``
  are not blown up). The residual is divided per component by ``delta_scale`` (its
  training RMS, floored). The decoder ``theta0`` and the online Bayesian regression both
  work on this *normalised* residual ``delta / delta_scale``, so the paper's unit-free
  hyperparameters (``tau^2 = 0.1``, ``sigma_j^2 = 0.1``) mean the same for every state
  component — a position residual of 1e-4 m and a rate residual of 1 rad/s would
  otherwise need noise levels four orders of magnitude apart. ``predict_residual``
  scales back to physical units. RMS (not std) is used because the decoder has no bias:
  the residual is not centred, and its mean is part of what ``theta z`` must explain.
* **Per-sample averages.** Eq. 3 sums over the N transitions; training uses the
  minibatch mean instead (the same optimum, a step size that does not depend on N).
  Consequently ``lambda_theta``/``lambda_phi`` of the MAP variant are relative to the
  per-sample data term.
* **Features at deployment** are the posterior mean ``z_k = mu_phi(x_k, u_k)``
  (Sec. III-B, Algorithm 1); the latent variance ``sigma_z^2`` feeds ``sigma_tot``
  (Sec. IV).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import optax
from jax import Array
from jax.typing import ArrayLike

_ACTIVATIONS: dict[str, Callable[[Array], Array]] = {
    "elu": jax.nn.elu,
    "relu": jax.nn.relu,
    "tanh": jnp.tanh,
    "silu": jax.nn.silu,
    "gelu": jax.nn.gelu,
    "softplus": jax.nn.softplus,
}


class EncoderConfig(NamedTuple):
    """Architecture and training hyperparameters (Appendix D, Tables "Offline Training").

    ``variational=False`` selects the deterministic MAP encoder of Appendix E, trained with
    ridge weights ``lambda_theta`` (decoder) and ``lambda_phi`` (encoder weight matrices);
    ``kl_weight`` is then unused. ``d`` is the residual dimension (= ``x_dim``).
    """

    x_dim: int
    u_dim: int
    d: int
    hidden: tuple[int, ...]
    latent_dim: int
    activation: str = "elu"
    kl_weight: float = 0.1
    lr: float = 1e-3
    batch_size: int = 128
    epochs: int = 50
    variational: bool = True
    lambda_theta: float = 1e-4
    lambda_phi: float = 1e-4

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-compatible dict (``hidden`` as a list)."""
        out = self._asdict()
        out["hidden"] = list(self.hidden)
        return out

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> EncoderConfig:
        """Inverse of :meth:`to_dict`; rejects unknown or missing fields."""
        unknown = set(data) - set(cls._fields)
        if unknown:
            raise ValueError(f"unknown EncoderConfig fields: {sorted(unknown)}")
        missing = {"x_dim", "u_dim", "d", "hidden", "latent_dim"} - set(data)
        if missing:
            raise ValueError(f"missing EncoderConfig fields: {sorted(missing)}")
        kwargs = dict(data)
        kwargs["hidden"] = tuple(int(h) for h in kwargs["hidden"])
        for name in ("x_dim", "u_dim", "d", "latent_dim", "batch_size", "epochs"):
            if name in kwargs:
                kwargs[name] = int(kwargs[name])
        for name in ("kl_weight", "lr", "lambda_theta", "lambda_phi"):
            if name in kwargs:
                kwargs[name] = float(kwargs[name])
        if "variational" in kwargs:
            kwargs["variational"] = bool(kwargs["variational"])
        return validate_config(cls(**kwargs))


def validate_config(config: EncoderConfig) -> EncoderConfig:
    """Check dimensions and names; returns the config unchanged or raises ``ValueError``."""
    if min(config.x_dim, config.u_dim, config.d, config.latent_dim) < 1:
        raise ValueError(f"dimensions must be positive: {config}")
    if len(config.hidden) == 0 or min(config.hidden) < 1:
        raise ValueError(f"hidden must be a non-empty tuple of positive widths: {config.hidden}")
    if config.activation not in _ACTIVATIONS:
        raise ValueError(f"activation {config.activation!r} not in {sorted(_ACTIVATIONS)}")
    if config.batch_size < 1 or config.epochs < 0 or config.lr <= 0:
        raise ValueError(f"invalid training settings: {config}")
    return config


def cartpole_config(**overrides: Any) -> EncoderConfig:
    """Cartpole preset (Appendix D, cartpole table): MLP [8, 16, 8], ELU, l = 2, KL 0.1,
    Adam lr 1e-3, batch 128, 50 epochs. State (x, xdot, theta, thetadot), input force."""
    base = EncoderConfig(
        x_dim=4, u_dim=1, d=4, hidden=(8, 16, 8), latent_dim=2, activation="elu",
        kl_weight=0.1, lr=1e-3, batch_size=128, epochs=50,
    )  # fmt: skip
    return validate_config(base._replace(**overrides))


def quadrotor_config(**overrides: Any) -> EncoderConfig:
    """Quadrotor preset (Appendix D, quadrotor table): MLP [64, 128, 64], ELU, l = 8,
    KL 0.1, Adam lr 1e-3, batch 256, 100 epochs. 13-state, 4-input (Sec. 4 of the design)."""
    base = EncoderConfig(
        x_dim=13, u_dim=4, d=13, hidden=(64, 128, 64), latent_dim=8, activation="elu",
        kl_weight=0.1, lr=1e-3, batch_size=256, epochs=100,
    )  # fmt: skip
    return validate_config(base._replace(**overrides))


def preset(system: str, **overrides: Any) -> EncoderConfig:
    """The Appendix D preset for ``"cartpole"`` or ``"quadrotor"``."""
    if system == "cartpole":
        return cartpole_config(**overrides)
    if system == "quadrotor":
        return quadrotor_config(**overrides)
    raise ValueError(f"no encoder preset for system {system!r} (cartpole, quadrotor)")


class VLD(eqx.Module):
    """Encoder ``q_phi(z | x, u)`` and linear decoder prior ``theta0`` (Eq. 2).

    Single-sample methods (``x`` ``(nx,)``, ``u`` ``(nu,)``); ``jax.vmap`` them for
    batches. ``theta0`` is ``(d, l)`` in normalised residual units: row ``j`` is the prior
    mean ``mu_0^j`` of the decoder row ``theta^j`` in Algorithm 1. The normalisation
    constants are arrays of the module but are never trained (see the module docstring).
    """

    layers: tuple[eqx.nn.Linear, ...]
    mean_head: eqx.nn.Linear
    logvar_head: eqx.nn.Linear | None
    theta0: Array
    x_mean: Array
    x_std: Array
    u_mean: Array
    u_std: Array
    delta_scale: Array
    activation: str = eqx.field(static=True)

    def __init__(self, key: Array, config: EncoderConfig, dtype: Any = None):
        """Random weights and identity normalisation (use :meth:`create` for data-fitted
        normalisation; this form is the skeleton that weight files are loaded into)."""
        validate_config(config)
        dtype = jnp.zeros(()).dtype if dtype is None else dtype
        widths = (config.x_dim + config.u_dim, *config.hidden)
        keys = jax.random.split(key, len(config.hidden) + 3)
        self.layers = tuple(
            eqx.nn.Linear(widths[i], widths[i + 1], dtype=dtype, key=keys[i])
            for i in range(len(config.hidden))
        )
        self.mean_head = eqx.nn.Linear(widths[-1], config.latent_dim, dtype=dtype, key=keys[-3])
        self.logvar_head = (
            eqx.nn.Linear(widths[-1], config.latent_dim, dtype=dtype, key=keys[-2])
            if config.variational
            else None
        )
        # Scaled so that theta0 z has O(1) entries for z ~ N(0, I).
        self.theta0 = jax.random.normal(keys[-1], (config.d, config.latent_dim), dtype) / jnp.sqrt(
            config.latent_dim
        )
        self.x_mean = jnp.zeros(config.x_dim, dtype)
        self.x_std = jnp.ones(config.x_dim, dtype)
        self.u_mean = jnp.zeros(config.u_dim, dtype)
        self.u_std = jnp.ones(config.u_dim, dtype)
        self.delta_scale = jnp.ones(config.d, dtype)
        self.activation = config.activation

    @classmethod
    def create(
        cls,
        key: Array,
        config: EncoderConfig,
        x: Array,
        u: Array,
        delta: Array,
        *,
        min_std: float = 1e-3,
        min_scale: float = 1e-6,
    ) -> VLD:
        """Random weights with normalisation fitted to a training set ``x`` ``(N, nx)``,
        ``u`` ``(N, nu)``, ``delta`` ``(N, d)`` (physical units).

        ``x_std``/``u_std`` are floored at ``min_std`` and ``delta_scale`` (per-component
        RMS of the residual) at ``min_scale``, both in physical units.
        """
        x, u, delta = _as_float(x), _as_float(u), _as_float(delta)
        _check_data(config, x, u, delta)
        model = cls(key, config, dtype=x.dtype)
        stats = (
            jnp.mean(x, axis=0),
            jnp.maximum(jnp.std(x, axis=0), min_std),
            jnp.mean(u, axis=0),
            jnp.maximum(jnp.std(u, axis=0), min_std),
            jnp.maximum(jnp.sqrt(jnp.mean(delta**2, axis=0)), min_scale),
        )
        return eqx.tree_at(_normalisation_leaves, model, stats)

    @property
    def variational(self) -> bool:
        """False for the deterministic MAP encoder of Appendix E."""
        return self.logvar_head is not None

    @property
    def latent_dim(self) -> int:
        return self.theta0.shape[1]

    def _trunk(self, x: Array, u: Array) -> Array:
        act = _ACTIVATIONS[self.activation]
        h = jnp.concatenate([(x - self.x_mean) / self.x_std, (u - self.u_mean) / self.u_std])
        for layer in self.layers:
            h = act(layer(h))
        return h

    def encode(self, x: Array, u: Array) -> tuple[Array, Array]:
        """Posterior parameters ``(mu_phi, log sigma_phi^2)``, each ``(l,)``, of
        ``q_phi(z | x, u)`` (Eq. 2).

        The deterministic encoder returns ``log sigma^2 = -inf`` (a point mass).
        """
        h = self._trunk(x, u)
        mu = self.mean_head(h)
        if self.logvar_head is None:
            return mu, jnp.full_like(mu, -jnp.inf)
        return mu, self.logvar_head(h)

    def features(self, x: Array, u: Array) -> Array:
        """Deployment features ``z_k = mu_phi(x_k, u_k)``, ``(l,)`` (Sec. III-B, Algorithm 1)."""
        return self.mean_head(self._trunk(x, u))

    def latent_variance(self, x: Array, u: Array) -> Array:
        """Encoder variance ``sigma_z^2`` used in ``sigma_tot`` (Sec. IV); zero for MAP."""
        mu, logvar = self.encode(x, u)
        return jnp.exp(logvar) if self.variational else jnp.zeros_like(mu)

    def predict_residual(
        self,
        x: Array,
        u: Array,
        theta: Array | None = None,
    ) -> Array:
        """Residual ``f_Delta(x, u) = theta mu_phi(x, u)``, ``(d,)``, in physical units
        (Sec. III).

        ``theta`` (normalised units, as adapted online) defaults to the prior ``theta0``.
        """
        theta = self.theta0 if theta is None else theta
        return self.denormalise_residual(theta @ self.features(x, u))

    def normalise_residual(self, delta: Array) -> Array:
        """Physical residual -> the unit-free residual the decoder models."""
        return delta / self.delta_scale

    def denormalise_residual(self, delta_norm: Array) -> Array:
        """Inverse of :meth:`normalise_residual`."""
        return delta_norm * self.delta_scale


def _normalisation_leaves(m: VLD) -> tuple[Array, ...]:
    return (m.x_mean, m.x_std, m.u_mean, m.u_std, m.delta_scale)


def _as_float(a: Any) -> Array:
    a = jnp.asarray(a)
    return a if jnp.issubdtype(a.dtype, jnp.floating) else a.astype(float)


def _check_data(config: EncoderConfig, x: Array, u: Array, delta: Array) -> None:
    n = x.shape[0]
    expected = ((n, config.x_dim), (n, config.u_dim), (n, config.d))
    if (x.shape, u.shape, delta.shape) != expected:
        raise ValueError(
            f"expected x (N, {config.x_dim}), u (N, {config.u_dim}), delta (N, {config.d}); "
            f"got {x.shape}, {u.shape}, {delta.shape}"
        )
    if n == 0:
        raise ValueError("empty training set")


# --------------------------------------------------------------------------- objective


def kl_divergence(mu: Array, logvar: Array) -> Array:
    """Closed-form ``KL(N(mu, diag e^logvar) || N(0, I))``, the regulariser of Eq. 3."""
    return 0.5 * jnp.sum(jnp.exp(logvar) + mu**2 - 1.0 - logvar)


def reparameterise(key: Array, mu: Array, logvar: Array) -> Array:
    """Reparameterised sample ``z = mu + exp(logvar / 2) * eps``, ``eps ~ N(0, I)`` (Eq. 3)."""
    eps = jax.random.normal(key, jnp.shape(mu), jnp.result_type(mu))
    return mu + jnp.exp(0.5 * logvar) * eps


class LossTerms(NamedTuple):
    """Objective and its parts, each a minibatch mean (``penalty`` is the ridge term of
    the MAP variant, ``kl`` the unweighted KL of the variational one)."""

    total: Array
    recon: Array
    kl: Array
    penalty: Array


def vld_loss(
    model: VLD,
    key: Array,
    x: Array,
    u: Array,
    delta_norm: Array,
    kl_weight: float,
) -> LossTerms:
    """Eq. 3 (per-sample mean): ``E_q ||delta - theta0 z||^2 + beta_KL KL(q || N(0, I))``.

    One reparameterised sample per transition estimates the expectation; the residual is
    the normalised one.
    """
    mu, logvar = jax.vmap(model.encode)(x, u)
    z = reparameterise(key, mu, logvar)
    recon = jnp.mean(jnp.sum((delta_norm - z @ model.theta0.T) ** 2, axis=-1))
    kl = jnp.mean(jax.vmap(kl_divergence)(mu, logvar))
    zero = jnp.zeros((), recon.dtype)
    return LossTerms(recon + kl_weight * kl, recon, kl, zero)


def map_loss(
    model: VLD,
    x: Array,
    u: Array,
    delta_norm: Array,
    lambda_theta: float,
    lambda_phi: float,
) -> LossTerms:
    """Appendix E MAP objective (per-sample mean data term):
    ``||delta - theta0 phi(x, u)||^2 + lambda_theta ||theta0||^2 + lambda_phi ||phi||^2``,
    where ``||phi||^2`` sums the squared weight matrices of the encoder (not biases)."""
    z = jax.vmap(model.features)(x, u)
    recon = jnp.mean(jnp.sum((delta_norm - z @ model.theta0.T) ** 2, axis=-1))
    weights = [layer.weight for layer in model.layers] + [model.mean_head.weight]
    penalty = lambda_theta * jnp.sum(model.theta0**2) + lambda_phi * sum(
        jnp.sum(w**2) for w in weights
    )
    zero = jnp.zeros((), recon.dtype)
    return LossTerms(recon + penalty, recon, zero, penalty)


def objective(
    model: VLD,
    key: Array,
    x: Array,
    u: Array,
    delta_norm: Array,
    config: EncoderConfig,
) -> LossTerms:
    """Eq. 3 for a variational config, the Appendix E MAP objective otherwise."""
    if config.variational:
        return vld_loss(model, key, x, u, delta_norm, config.kl_weight)
    return map_loss(model, x, u, delta_norm, config.lambda_theta, config.lambda_phi)


# --------------------------------------------------------------------------- training


class TrainHistory(NamedTuple):
    """Per-epoch curves. ``train_loss``: mean minibatch objective over the epoch;
    ``val_loss``: objective on the validation set (fixed key); ``val_mse``: mean squared
    error per component of the normalised residual predicted with ``z = mu_phi`` (what
    deployment uses). Validation curves are NaN without a validation set."""

    train_loss: Array
    val_loss: Array
    val_mse: Array


def trainable_spec(model: VLD) -> VLD:
    """Filter spec: True for trained leaves (weights, ``theta0``), False for the
    normalisation constants, which stay as fitted on the data."""
    spec = jax.tree_util.tree_map(eqx.is_inexact_array, model)
    return eqx.tree_at(_normalisation_leaves, spec, (False,) * 5)


@eqx.filter_jit
def _epoch(
    params: VLD,
    static: VLD,
    opt_state: optax.OptState,
    key: Array,
    x: Array,
    u: Array,
    delta_norm: Array,
    config: EncoderConfig,
) -> tuple[VLD, optax.OptState, Array]:
    """One pass over shuffled minibatches as a ``lax.scan`` (last partial batch dropped)."""
    optimizer = optax.adam(config.lr)
    n = x.shape[0]
    bs = min(config.batch_size, n)
    nb = n // bs
    perm_key, step_key = jax.random.split(key)
    batches = jax.random.permutation(perm_key, n)[: nb * bs].reshape(nb, bs)
    step_keys = jax.random.split(step_key, nb)

    def loss(p: VLD, k: Array, idx: Array) -> Array:
        model = eqx.combine(p, static)
        return objective(model, k, x[idx], u[idx], delta_norm[idx], config).total

    def step(carry, inputs):
        p, s = carry
        idx, k = inputs
        value, grads = jax.value_and_grad(loss)(p, k, idx)
        updates, s = optimizer.update(grads, s, p)
        return (optax.apply_updates(p, updates), s), value

    (params, opt_state), losses = jax.lax.scan(step, (params, opt_state), (batches, step_keys))
    return params, opt_state, jnp.mean(losses)


@eqx.filter_jit
def _evaluate(
    model: VLD, key: Array, x: Array, u: Array, delta_norm: Array, config: EncoderConfig
) -> tuple[Array, Array]:
    terms = objective(model, key, x, u, delta_norm, config)
    pred = jax.vmap(model.features)(x, u) @ model.theta0.T
    return terms.total, jnp.mean((delta_norm - pred) ** 2)


def train(
    key: Array,
    config: EncoderConfig,
    x: Array,
    u: Array,
    delta: Array,
    *,
    callback: Callable[[int, float, float], None] | None = None,
    val: tuple[Array, Array, Array] | None = None,
    model: VLD | None = None,
) -> tuple[VLD, TrainHistory]:
    """Fit ``(phi, theta0)`` with Adam on minibatches (Eq. 3 / Appendix E, Appendix D).

    ``delta`` is in physical units; the normalisation is fitted here (unless an initial
    ``model`` is given, whose normalisation is kept). ``val = (x, u, delta)`` adds
    validation curves. ``callback(epoch, train_loss, val_loss)`` runs after each epoch
    (``epoch`` counts from 1, ``val_loss`` is NaN without ``val``) so a caller can show
    progress; training itself does no I/O. Deterministic given ``key``.
    """
    validate_config(config)
    x, u, delta = _as_float(x), _as_float(u), _as_float(delta)
    _check_data(config, x, u, delta)
    init_key, loop_key, val_key = jax.random.split(key, 3)
    if model is None:
        model = VLD.create(init_key, config, x, u, delta)
    params, static = eqx.partition(model, trainable_spec(model))
    opt_state = optax.adam(config.lr).init(params)
    delta_norm = model.normalise_residual(delta)
    if val is not None:
        xv, uv, dv = (_as_float(a) for a in val)
        _check_data(config, xv, uv, dv)
        dv_norm = model.normalise_residual(dv)

    nan = float("nan")
    train_curve, val_curve, mse_curve = [], [], []
    for epoch, epoch_key in enumerate(jax.random.split(loop_key, config.epochs), start=1):
        params, opt_state, train_loss = _epoch(
            params, static, opt_state, epoch_key, x, u, delta_norm, config
        )
        train_curve.append(float(train_loss))
        val_loss = val_mse = nan
        if val is not None:
            vl, vm = _evaluate(eqx.combine(params, static), val_key, xv, uv, dv_norm, config)
            val_loss, val_mse = float(vl), float(vm)
        val_curve.append(val_loss)
        mse_curve.append(val_mse)
        if callback is not None:
            callback(epoch, train_curve[-1], val_loss)

    history = TrainHistory(*(jnp.asarray(c, x.dtype) for c in (train_curve, val_curve, mse_curve)))
    return eqx.combine(params, static), history


# --------------------------------------------------------------------------- data


def residual_dataset(
    f_nom: Callable[[Array, Array], Array],
    X: Array,
    U: Array,
) -> tuple[Array, Array, Array]:
    """Transitions of one trajectory: ``(x_k, u_k, delta_k = x_{k+1} - f_nom(x_k, u_k))``
    (Sec. III, Eq. 1). ``f_nom(x, u) -> x_next`` is one nominal step; it is vmapped.
    Concatenate the outputs of several trajectories (never their states) to build a set.
    """
    X, U = _as_float(X), _as_float(U)
    if X.ndim != 2 or U.ndim != 2 or X.shape[0] != U.shape[0] + 1:
        raise ValueError(f"expected X (T+1, nx) and U (T, nu); got {X.shape} and {U.shape}")
    x, x_next = X[:-1], X[1:]
    return x, U, x_next - jax.vmap(f_nom)(x, U)


def calibrate_residual_scale(
    model: VLD,
    x: Array,
    u: Array,
    delta: Array,
    sigma2: ArrayLike = 0.1,
    *,
    min_scale: float = 1e-6,
) -> VLD:
    """Re-express the normalised residual so the offline one-step error variance is ``sigma2``.

    The online regression (Eq. 4) assumes observation noise ``sigma_j^2`` in the units the
    decoder works in. After training, the per-component error of the offline model,
    ``mse_j = mean((delta_j - f_Delta_j)^2)``, is what that noise is on the training
    distribution; choosing ``delta_scale_j = sqrt(mse_j / sigma_j^2)`` makes the paper's
    ``sigma_j^2`` (Appendix D) the actual noise level, and a prior variance ``tau^2`` a
    statement relative to it. ``theta0`` is rescaled with it, so predictions in physical
    units are unchanged. Components whose residual is identically zero keep ``min_scale``.
    """
    x, u, delta = _as_float(x), _as_float(u), _as_float(delta)
    pred = jax.vmap(model.predict_residual)(x, u)
    mse = jnp.mean((delta - pred) ** 2, axis=0)
    sigma2 = jnp.broadcast_to(jnp.asarray(sigma2, mse.dtype), mse.shape)
    scale = jnp.maximum(jnp.sqrt(mse / sigma2), min_scale).astype(model.delta_scale.dtype)
    theta0 = model.theta0 * (model.delta_scale / scale)[:, None]
    return eqx.tree_at(lambda m: (m.theta0, m.delta_scale), model, (theta0, scale))
