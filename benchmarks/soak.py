"""Numerics soak of the packed adaptation step (Algorithm 1) under changepoints and outliers.

``arcade bench soak`` runs 10^6 steps of :func:`arcade_core.adaptation.packed_step` (the
real-time fast path, quadrotor sizes d = 13, l = 8, Appendix D quadrotor preset) on a
synthetic regression stream built to be hostile:

- the true decoder jumps often (probability 1/300 per step, scale log-uniform over three
  decades) and in bursts (a jump at half of the steps of a 200-step burst every 50 000);
- observation noise is Student-t with 1.5 degrees of freedom (infinite variance), plus 1 %
  outliers of 10^3 in one output;
- the features alternate between a nearly constant vector (hover, first, as at take-off),
  full excitation (``z ~ N(0, I)``) and a rank-2 subspace, every 7 919 steps, always with
  ``|z| <= R = 4``.

Checks, for every step and every hypothesis ``h`` of the beam (per-step checks inside the
``lax.scan``, chunk checks every ``chunk`` steps):

- finite: beam, scores and every output of every step;
- SPD: the eigenvalues of every covariance ``Sigma_h = W_h W_h^T`` (chunk ends) are
  positive, and the square roots finite;
- Lemma 2 as stated (the paper's bounded-variance lemma): ``z_k^T Sigma_{k,h} z_k <=
  min{tau^2 R^2, R^2 sigma^2 / (alpha t(k))}``. The lemma assumes ``lambda_min(sum_{t in
  S} z_t z_t^T) >= alpha t`` for the samples ``S`` of every segment seen so far; with
  ``l > 1`` features a segment's first sample has rank one, so ``alpha = 0`` and the
  stated envelope is ``tau^2 R^2``. The proof assumes the tempered prior after a
  changepoint is no more diffuse than ``tau^2 I``; Eq. 5 as written divides the covariance
  by ``beta^2 < 1``, so directions the segment has not excited grow by ``1 / beta^2`` per
  changepoint on the path and the envelope can fail (violations are counted). With the
  learner's full prior-precision floor (``prior_floor = 1``, the quadrotor preset) the
  assumption holds and a violation fails the run (both are run if the preset has a floor);
- the envelopes that do follow from Eq. 6 with tempering (must hold, up to rounding):
  ``Sigma_h <= tau^2 / (rho + (1 - rho) beta^{2 m_h}) I`` (``m_h`` changepoints on the
  path, ``rho`` the learner's prior-precision floor at changepoints; ``tau^2 beta^{-2 m_h}``
  for Eq. 5 as written, ``tau^2`` with the full floor; per step, along ``z_k``) and
  ``Sigma_h <= sigma^2 (sum_{t in S_h} z_t z_t^T)^{-1}`` for the samples ``S_h`` of the
  hypothesis' current segment (chunk ends, as ``lambda_max(W^T G W) <= sigma^2`` over the
  part of the segment inside the chunk, which is implied by it).

    python -m benchmarks.soak [--quick] [--steps N] [--dtype float32|float64] [--json]
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable
from typing import Any, NamedTuple

from arcade_io import jsonout
from benchmarks.common import machine

D, L = 13, 8
R = 4.0  # feature norm bound
JUMP_P = 1.0 / 300
BURST_EVERY, BURST_LEN = 50_000, 200
REGIME_LEN = 7919
OUTLIER_P, OUTLIER = 0.01, 1e3
TAIL_DF = 1.5
NOISE = 0.3


class Stats(NamedTuple):
    """Running per-step statistics carried through the scan."""

    nonfinite: Any  # steps with any non-finite value
    stated_max: Any  # max over steps and hypotheses of q_h / (tau^2 R^2)
    stated_viol: Any  # (step, hypothesis) pairs above the stated envelope
    stated_steps: Any  # steps with at least one violation
    worst_t: Any  # segment length t(k) of the worst stated violation
    worst_m: Any  # changepoints on that hypothesis' path
    worst_step: Any
    prior_max: Any  # max of q_h / (tau^2 |z|^2 beta^{-2 m_h}) (<= 1)
    prior_viol: Any
    param_max: Any  # max beam-marginal parameter variance (Sec. IV), any output
    total_max: Any  # max sigma_tot^2 = param + between (no encoder term here)
    detected: Any  # steps flagged as changepoints (UpdateInfo.changepoint)
    jumps: Any  # true decoder jumps


def _init_stats(dtype) -> Stats:
    import jax.numpy as jnp

    z = jnp.zeros((), dtype)
    i = jnp.zeros((), jnp.int32)
    return Stats(i, z, i, i, i, i, i, z, i, z, z, i, i)


def _stream_step(key, k, theta, dtype):
    """One sample of the stream: ``(z, delta, new theta, jumped)``."""
    import jax
    import jax.numpy as jnp

    ks = jax.random.split(jax.random.fold_in(key, k), 8)
    in_burst = (k % BURST_EVERY) < BURST_LEN
    jump = jax.random.uniform(ks[0]) < jnp.where(in_burst, 0.5, JUMP_P)
    scale = 10.0 ** jax.random.uniform(ks[1], (), dtype, minval=-2.0, maxval=1.0)
    theta = jnp.where(jump, scale * jax.random.normal(ks[2], (D, L), dtype), theta)
    regime = (k // REGIME_LEN + 2) % 3  # hover first, as at take-off
    full = jax.random.normal(ks[3], (L,), dtype)
    low_rank = full * (jnp.arange(L) < 2)
    hover = jnp.ones((L,), dtype) * 0.5 + 1e-3 * full
    z = jnp.select([regime == 0, regime == 1], [full, low_rank], hover)
    z = z / jnp.maximum(1.0, jnp.linalg.norm(z) / R)
    noise = NOISE * jax.random.t(ks[4], TAIL_DF, (D,), dtype)
    outlier = (
        (jax.random.uniform(ks[5]) < OUTLIER_P)
        * OUTLIER
        * jax.nn.one_hot(jax.random.randint(ks[6], (), 0, D), D, dtype=dtype)
        * jnp.sign(jax.random.normal(ks[7], (), dtype))
    )
    delta = theta @ z + noise + outlier
    return z, delta, theta, jump


def make_chunk(config, chunk: int, dtype):
    """Jitted ``(packed, theta, stats, key, k0) -> (packed, theta, stats, z (chunk, l))``:
    ``chunk`` stream samples and packed steps with the per-step checks."""
    import jax
    import jax.numpy as jnp

    from arcade_core import adaptation as A

    K = int(config.K)
    tau2 = jnp.asarray(config.tau2, dtype)
    log_beta2 = 2.0 * jnp.log(jnp.asarray(config.beta, dtype))
    rho = jnp.asarray(_floor(config), dtype)
    eps = jnp.finfo(dtype).eps
    tol = 1e4 * eps  # rounding of a few hundred flops on values of order one
    stated = tau2 * R * R

    def body(carry, k):
        packed, theta, st, key = carry
        z, delta, theta, jumped = _stream_step(key, k, theta, dtype)
        # Pre-step projections of every hypothesis (what the step predicts with).
        w = packed.sqrt_covariances[:, 0]  # (K, l, l): one covariance shared by outputs
        a = jnp.einsum("kji,j->ki", w, z)
        q = jnp.sum(a * a, axis=-1)  # z^T Sigma_h z
        used = jnp.isfinite(packed.floats[:K])
        m = packed.ints[:K]
        last = packed.ints[K : 2 * K]
        step = packed.ints[3 * K]
        t_seg = jnp.where(last >= 1, step - last + 1, step)  # samples in h's segment
        ratio = jnp.where(used, q / stated, 0.0)
        viol = used & (ratio > 1.0 + tol)
        zz = jnp.sum(z * z)
        # Sigma_h <= tau^2 / (rho + (1 - rho) beta^{2 m_h}) I (m_h changepoints on the path).
        shrink = rho + (1.0 - rho) * jnp.exp(m.astype(dtype) * log_beta2)
        log_env = jnp.log(tau2 * zz) - jnp.log(shrink)
        prior_ratio = jnp.where(used & (zz > 0), jnp.exp(jnp.log(q + 1e-300) - log_env), 0.0)

        inputs = jnp.concatenate([z, delta, jnp.zeros((L,), dtype)])
        packed, out = A.packed_step(packed, inputs)
        pred, info = A.unpack_outputs(out, D, K)
        finite = (
            jnp.all(jnp.isfinite(out))
            & jnp.all(jnp.isfinite(packed.means))
            & jnp.all(jnp.isfinite(packed.sqrt_covariances))
            & jnp.all(jnp.isfinite(packed.floats[K:]))
            & jnp.all(jnp.isfinite(packed.floats[:K]) | (packed.floats[:K] == -jnp.inf))
        )
        h = jnp.argmax(ratio)
        worse = ratio[h] > st.stated_max
        st = Stats(
            nonfinite=st.nonfinite + (~finite),
            stated_max=jnp.maximum(st.stated_max, ratio[h]),
            stated_viol=st.stated_viol + jnp.sum(viol, dtype=jnp.int32),
            stated_steps=st.stated_steps + jnp.any(viol),
            worst_t=jnp.where(worse, t_seg[h], st.worst_t),
            worst_m=jnp.where(worse, m[h], st.worst_m),
            worst_step=jnp.where(worse, step + 1, st.worst_step),
            prior_max=jnp.maximum(st.prior_max, jnp.max(prior_ratio)),
            prior_viol=st.prior_viol + jnp.sum(prior_ratio > 1.0 + tol, dtype=jnp.int32),
            param_max=jnp.maximum(st.param_max, jnp.max(pred.param)),
            total_max=jnp.maximum(st.total_max, jnp.max(pred.param + pred.between)),
            detected=st.detected + info.changepoint.astype(jnp.int32),
            jumps=st.jumps + jumped.astype(jnp.int32),
        )
        return (packed, theta, st, key), z

    def run(packed, theta, st, key, k0):
        ks = k0 + jnp.arange(chunk, dtype=jnp.int32)
        (packed, theta, st, _), zs = jax.lax.scan(body, (packed, theta, st, key), ks)
        return packed, theta, st, zs

    return jax.jit(run)


def make_chunk_check(config, chunk: int, dtype):
    """Jitted chunk-end checks: ``(packed, zs, k0) -> (min eigenvalue, max condition
    number, max lambda_max(W^T G W) / sigma^2 over the used hypotheses)``."""
    import jax
    import jax.numpy as jnp

    K = int(config.K)
    sigma2 = jnp.asarray(config.sigma2, dtype)

    def check(packed, zs, k0):
        w = packed.sqrt_covariances[:, 0]
        cov = jnp.einsum("kij,klj->kil", w, w)
        eig = jnp.linalg.eigvalsh(0.5 * (cov + jnp.swapaxes(cov, 1, 2)))
        used = jnp.isfinite(packed.floats[:K])
        min_eig = jnp.min(jnp.where(used[:, None], eig, jnp.inf))
        cond = jnp.max(jnp.where(used, eig[:, -1] / eig[:, 0], 0.0))
        # Samples of each hypothesis' current segment inside this chunk (steps k0+1..).
        last = packed.ints[K : 2 * K]
        start = jnp.maximum(jnp.where(last >= 1, last, 1), k0 + 1)
        steps = k0 + 1 + jnp.arange(chunk)
        mask = (steps[None, :] >= start[:, None]).astype(dtype)
        G = jnp.einsum("kc,ci,cj->kij", mask, zs, zs)
        M = jnp.einsum("kji,kjl,klm->kim", w, G, w)  # W^T G W
        lam = jnp.linalg.eigvalsh(0.5 * (M + jnp.swapaxes(M, 1, 2)))[:, -1]
        data = jnp.max(jnp.where(used, lam / sigma2, 0.0))
        return min_eig, cond, data

    return jax.jit(check)


def _floor(config: Any) -> float:
    """The learner's prior-precision floor at changepoints (0: Eq. 5 as written)."""
    return float(getattr(config, "prior_floor", 0.0))


def soak(
    steps: int = 1_000_000,
    dtype: str = "float32",
    chunk: int = 10_000,
    seed: int = 0,
    config: Any = None,
    prior_floor: float | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Run the soak in this process; returns the statistics (see the module docstring).

    ``config``: the adaptation hyperparameters (default: the quadrotor preset);
    ``prior_floor`` overrides its precision floor at changepoints (``0``: Eq. 5 as written);
    ``progress`` gets a line at the start and after every tenth of the chunks.
    """
    import jax
    import jax.numpy as jnp

    from arcade_core import adaptation as A

    dt = jnp.dtype(dtype)
    cfg = config if config is not None else A.quadrotor_config()
    if prior_floor is not None:
        if not hasattr(cfg, "prior_floor"):
            raise ValueError("this learner has no prior_floor setting")
        cfg = cfg._replace(prior_floor=prior_floor)
    chunk = min(chunk, steps)
    n_chunks = math.ceil(steps / chunk)
    key = jax.random.PRNGKey(seed)
    theta0 = jnp.zeros((D, L), dt)
    packed = A.pack(A.init(theta0, cfg), cfg)
    theta = 0.1 * jax.random.normal(jax.random.PRNGKey(seed + 1), (D, L), dt)
    st = _init_stats(dt)
    run, check = make_chunk(cfg, chunk, dt), make_chunk_check(cfg, chunk, dt)
    t0 = time.perf_counter()
    run(packed, theta, st, key, jnp.int32(0))[2].nonfinite.block_until_ready()  # compile
    check(packed, jnp.zeros((chunk, L), dt), jnp.int32(0))[0].block_until_ready()
    compile_s = time.perf_counter() - t0
    min_eig, max_cond, data_max = math.inf, 0.0, 0.0
    label = f"[soak] {dtype}, prior floor {_floor(cfg):g}"
    if progress is not None:
        progress(f"{label}: {n_chunks * chunk} steps (compiled in {compile_s:.1f} s)")
    every = max(1, n_chunks // 10)
    t0 = time.perf_counter()
    for c in range(n_chunks):
        k0 = jnp.int32(c * chunk)
        packed, theta, st, zs = run(packed, theta, st, key, k0)
        e, cond, data = (float(v) for v in check(packed, zs, k0))
        min_eig, max_cond, data_max = min(min_eig, e), max(max_cond, cond), max(data_max, data)
        if progress is not None and ((c + 1) % every == 0 or c + 1 == n_chunks):
            done = (c + 1) * chunk
            progress(f"{label}: {done} steps, {time.perf_counter() - t0:.0f} s")
    jax.block_until_ready(packed)
    wall = time.perf_counter() - t0
    s = {k: v.item() for k, v in st._asdict().items()}
    tol = 1e4 * float(jnp.finfo(dt).eps)
    n = n_chunks * chunk
    result = {
        "dtype": dtype,
        "steps": n,
        "K": int(cfg.K),
        "d": D,
        "l": L,
        "beta": float(cfg.beta),
        "tau2": float(cfg.tau2),
        "sigma2": float(cfg.sigma2),
        "prior_floor": _floor(cfg),
        "R": R,
        "compile_s": compile_s,
        "wall_s": wall,
        "us_per_step": 1e6 * wall / n,
        "true_jumps": s["jumps"],
        "detected_changepoints": s["detected"],
        "nonfinite_steps": s["nonfinite"],
        "min_eigenvalue": min_eig,
        "max_condition": max_cond,
        "prior_envelope_max_ratio": s["prior_max"],
        "prior_envelope_violations": s["prior_viol"],
        "data_envelope_max_ratio": data_max,
        "max_param_variance": s["param_max"],
        "max_sigma_tot2": s["total_max"],
        "lemma2_stated": {
            "bound": float(cfg.tau2) * R * R,
            "max_ratio": s["stated_max"],
            "violations": s["stated_viol"],
            "steps_with_violation": s["stated_steps"],
            "fraction_of_steps": s["stated_steps"] / n,
            "worst": {
                "step": s["worst_step"],
                "segment_samples": s["worst_t"],
                "changepoints_on_path": s["worst_m"],
            },
        },
    }
    result["ok"] = bool(
        result["nonfinite_steps"] == 0
        and min_eig > 0
        and result["prior_envelope_violations"] == 0
        and data_max <= 1.0 + tol
        # With the full floor the tempered prior is never wider than tau^2 I: Lemma 2 holds.
        and (_floor(cfg) < 1.0 or s["stated_viol"] == 0)
    )
    return result


def run(
    quick: bool = False,
    steps: int | None = None,
    dtypes: tuple[str, ...] = ("float32", "float64"),
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """``arcade bench soak``: 10^6 steps per dtype (``quick``: 2 x 10^4) with the quadrotor
    preset, and with Eq. 5 as written (no prior floor) if the preset has a floor;
    ``progress``: see :func:`soak`."""
    from arcade_core import adaptation as A
    from arcade_io import jaxsetup

    jaxsetup.configure()
    n = steps if steps is not None else (20_000 if quick else 1_000_000)
    chunk = 2_000 if n <= 50_000 else 10_000
    floors: list[float | None] = [None]
    if _floor(A.quadrotor_config()) > 0:
        floors.append(0.0)
    with jaxsetup.x64():  # float64 runs need it; float32 arrays stay float32
        results = [
            soak(n, dt, chunk=chunk, prior_floor=f, progress=progress)
            for f in floors
            for dt in dtypes
        ]
    return {
        "machine": machine(),
        "steps": n,
        "results": results,
        "ok": all(r["ok"] for r in results),
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--steps", type=int, default=None)
    p.add_argument("--dtype", choices=["float32", "float64"], action="append")
    p.add_argument("--json", action="store_true")
    a = p.parse_args(argv)
    r = run(quick=a.quick, steps=a.steps, dtypes=tuple(a.dtype or ("float32", "float64")))
    print(jsonout.dumps(r) if a.json else jsonout.dumps(r, indent=2))
    return 0 if r["ok"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
