"""Sparse system identification of the residual: the SysID baseline (Sec. V).

After Brunton et al. (2016, SINDy) and Kaiser et al. (2018, SINDy with control): the
residual ``delta = x_{k+1} - f_nom(x_k, u_k)`` is regressed on a library of candidate
functions of ``z = [x, u]``

- all monomials of total degree 0..``degree`` (2 or 3) in the entries of z;
- ``sin`` and ``cos`` of the angle-like entries (``angle_indices``), each also multiplied
  by every monomial of degree 1..``trig_cross_degree`` (e.g. ``u0*cos(x2)``);

and the coefficients are found by sequentially thresholded least squares (STLSQ) with a
ridge penalty. Regression happens on normalised columns (library columns divided by
their RMS, targets by theirs): a term survives when its *typical contribution* is at
least ``threshold`` times the RMS of that residual component, which makes one threshold
meaningful for outputs of very different scales. A final ridge fit on the surviving terms
gives the reported coefficients, in original units.

The library is data (index arrays plus a names tuple), evaluated without powers, so
predictions are differentiable everywhere (for use inside the MPC).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import Array


class Library(eqx.Module):
    """Candidate terms ``theta_t(z) = trig_t(z) * prod_i z[monomials[t, i]]``.

    ``monomials`` indexes ``[z, 1]`` (the pad index ``n_in`` stands for the factor 1);
    ``trig`` indexes ``[1, sin(z_a) for a in angles, cos(z_a) for a in angles]``.
    """

    monomials: Array  # (T, max(degree, 1)) int
    trig: Array  # (T,) int
    angle_indices: tuple[int, ...] = eqx.field(static=True)
    names: tuple[str, ...] = eqx.field(static=True)

    def __call__(self, z: Array) -> Array:
        """Library row for one input ``z`` (n_in,), shape (T,)."""
        z_ext = jnp.concatenate([z, jnp.ones((1,), z.dtype)])
        angles = z[jnp.asarray(self.angle_indices, jnp.int32)]
        trig_ext = jnp.concatenate([jnp.ones((1,), z.dtype), jnp.sin(angles), jnp.cos(angles)])
        return jnp.prod(z_ext[self.monomials], axis=1) * trig_ext[self.trig]

    @property
    def size(self) -> int:
        return len(self.names)


def _monomial_name(idx: tuple[int, ...], var: Sequence[str]) -> str:
    parts = []
    for i in sorted(set(idx)):
        p = idx.count(i)
        parts.append(var[i] if p == 1 else f"{var[i]}^{p}")
    return "*".join(parts)


def make_library(
    nx: int,
    nu: int,
    *,
    degree: int = 2,
    angle_indices: Sequence[int] = (),
    trig_cross_degree: int = 1,
    state_names: Sequence[str] | None = None,
    input_names: Sequence[str] | None = None,
) -> Library:
    """Polynomial + trigonometric candidate library over ``z = [x, u]`` (Brunton et al.).

    Term order: ``1``, monomials by degree, then per angle ``sin``, ``cos`` and their
    products with monomials of degree 1..``trig_cross_degree``. ``angle_indices`` index
    the state (angles are states).
    """
    n_in = nx + nu
    var = list(state_names or [f"x{i}" for i in range(nx)])
    var += list(input_names or [f"u{i}" for i in range(nu)])
    if len(var) != n_in:
        raise ValueError("state_names/input_names do not match nx/nu")
    angles = tuple(int(a) for a in angle_indices)
    if any(not 0 <= a < nx for a in angles):
        raise ValueError("angle_indices must index the state")
    width = max(degree, trig_cross_degree, 1)

    def monos(lo: int, hi: int) -> list[tuple[int, ...]]:
        out: list[tuple[int, ...]] = []
        for k in range(lo, hi + 1):
            out += list(itertools.combinations_with_replacement(range(n_in), k))
        return out

    rows: list[tuple[tuple[int, ...], int]] = [(m, 0) for m in monos(0, degree)]
    names = [_monomial_name(m, var) or "1" for m, _ in rows]
    for j, a in enumerate(angles):
        for kind, t in (("sin", 1 + j), ("cos", 1 + len(angles) + j)):
            for m in monos(0, trig_cross_degree):
                rows.append((m, t))
                trig_name = f"{kind}({var[a]})"
                names.append(f"{_monomial_name(m, var)}*{trig_name}" if m else trig_name)
    mono = np.full((len(rows), width), n_in, dtype=np.int32)
    for r, (m, _) in enumerate(rows):
        mono[r, : len(m)] = m
    trig = np.array([t for _, t in rows], dtype=np.int32)
    return Library(jnp.asarray(mono), jnp.asarray(trig), angles, tuple(names))


class SysIDModel(eqx.Module):
    """Identified sparse residual model ``delta = Theta(z) @ coef``."""

    terms: Library  # the candidate library the coefficients refer to
    coef: Array  # (T, d), zero where inactive
    active: Array  # (T, d) bool


def _masked_ridge(r: Array, b: Array, mask: Array, ridge: Array) -> Array:
    """Ridge least squares on the columns in ``mask``; inactive coefficients are 0.

    Works on the triangular factor ``r`` of the library (``Theta = Q r``), so the
    conditioning is that of the library, not of its Gram matrix (which matters in single
    precision, where trigonometric and polynomial columns are nearly collinear).
    """
    m = mask.astype(r.dtype)
    a = jnp.concatenate([r * m[None, :], jnp.sqrt(ridge) * jnp.diag(m)])
    rhs = jnp.concatenate([b, jnp.zeros_like(b)])
    return jnp.linalg.lstsq(a, rhs)[0] * m


def _stlsq(r: Array, rhs: Array, alive: Array, threshold: Array, ridge: Array, iters: int):
    """STLSQ (Brunton et al. 2016, "sequentially thresholded least squares") with ridge.

    ``r`` (T, T) is the triangular factor of the normalised library, ``rhs`` (T, d) the
    projected normalised targets; returns normalised coefficients and the active mask,
    both (T, d).
    """

    def per_output(b: Array, alive_j: Array):
        def body(_, active):
            xi = _masked_ridge(r, b, active, ridge)
            return active & (jnp.abs(xi) >= threshold)

        active = jax.lax.fori_loop(0, iters, body, alive_j)
        return _masked_ridge(r, b, active, ridge), active

    xi, active = jax.vmap(per_output, in_axes=1, out_axes=1)(rhs, alive)
    return xi, active


@eqx.filter_jit
def _fit(library: Library, z: Array, delta: Array, threshold: Array, ridge: Array, iters: int):
    theta = jax.vmap(library)(z)  # (N, T)
    n = theta.shape[0]
    col = jnp.sqrt(jnp.mean(theta**2, axis=0))
    alive = col > 1e-12  # identically-zero columns can never be selected
    col = jnp.where(alive, col, 1.0)
    out = jnp.sqrt(jnp.mean(delta**2, axis=0))
    out = jnp.where(out > 1e-12, out, 1.0)
    # Scaled so that r^T r is the normalised Gram matrix (columns of unit mean square).
    q, r = jnp.linalg.qr(theta / col / jnp.sqrt(n))
    rhs = q.T @ (delta / out / jnp.sqrt(n))
    alive = jnp.broadcast_to(alive[:, None], rhs.shape)
    xi, active = _stlsq(r, rhs, alive, threshold, ridge, iters)
    return SysIDModel(terms=library, coef=xi * out[None, :] / col[:, None], active=active)


def fit(
    x: Array,
    u: Array,
    delta: Array,
    *,
    library: Library | None = None,
    degree: int = 2,
    angle_indices: Sequence[int] = (),
    threshold: float = 0.02,
    ridge: float = 1e-8,
    iterations: int = 10,
) -> SysIDModel:
    """Identify a sparse residual model by STLSQ with ridge (Brunton et al.; Kaiser et al.).

    Args:
        x: (N, nx), u: (N, nu), delta: (N, d) offline residual data.
        library: candidate terms; default ``make_library(nx, nu, degree, angle_indices)``.
        threshold: minimum normalised contribution ``|coef| * rms(term) / rms(delta_j)``.
        ridge: ridge weight on normalised coefficients (columns have unit RMS).
        iterations: thresholding rounds (a fixed count; STLSQ converges in a few).
    """
    x, u, delta = jnp.atleast_2d(x), jnp.atleast_2d(u), jnp.atleast_2d(delta)
    if library is None:
        library = make_library(x.shape[1], u.shape[1], degree=degree, angle_indices=angle_indices)
    z = jnp.concatenate([x, u], axis=1)
    thr = jnp.asarray(threshold, z.dtype)
    return _fit(library, z, delta, thr, jnp.asarray(ridge, z.dtype), int(iterations))


def predict(model: SysIDModel, x: Array, u: Array) -> Array:
    """Residual at one (x, u), shape (d,)."""
    return model.terms(jnp.concatenate([x, u])) @ model.coef


def active_terms(
    model: SysIDModel, output_names: Sequence[str] | None = None
) -> dict[str, list[tuple[str, float]]]:
    """Readable listing: for each residual component, its (term name, coefficient) pairs."""
    coef = np.asarray(model.coef)
    active = np.asarray(model.active)
    d = coef.shape[1]
    outs = list(output_names or [f"delta{j}" for j in range(d)])
    if len(outs) != d:
        raise ValueError("output_names must have one name per residual component")
    return {
        outs[j]: [(model.terms.names[t], float(coef[t, j])) for t in np.flatnonzero(active[:, j])]
        for j in range(d)
    }
