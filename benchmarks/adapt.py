"""Adaptation step latency vs beam size K (design §7; paper Appendix D ablation, ~7.6 ms).

One timed step is what the adaptation process does per control period: predict at ``z_k``
(Eq. 10, with the Sec. IV ``sigma_tot``), update every hypothesis under both branches
(Eqs. 5-9), prune to the top K, via :func:`arcade_core.adaptation.make_packed_step`
(float32, the packed beam donated, ``block_until_ready`` on every result). Quadrotor
sizes: d = 13 outputs, l = 8 latent features, the Appendix D quadrotor preset
(scalar sigma^2, so one covariance per hypothesis is shared by the outputs), measured
side by side with the preset's prior-precision floor at changepoints (``prior_floor = 1``,
one small Cholesky factorisation per hypothesis and step) and with Eq. 5 as written
(``prior_floor = 0``).

Inputs are synthetic but realistic: z ~ N(0, I) (the VLD latent prior) and residuals of
a 20 Hz quadrotor model (mm/s-scale position, cm/s-scale velocity errors) from a decoder
that switches halfway, as when a payload is dropped.

The measurement runs in a fresh interpreter so that it does not depend on what the calling
process did with JAX before, and with JAX's CPU client executing inline
(``jax_cpu_enable_async_dispatch=False``): for a kernel of a few tens of microseconds,
handing it to a worker thread costs more than it saves. The adaptation service should
run the same way; ``sync_dispatch=False`` measures the default instead.

    python -m benchmarks.adapt [--quick] [--async-dispatch]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

import numpy as np

from arcade_io import jsonout
from benchmarks.common import machine, percentiles

# One-step residual scales for the 13 quadrotor states (p, v, q, omega) at 20 Hz.
_RESIDUAL_SCALE = np.array([1e-3] * 3 + [2e-2] * 3 + [2e-3] * 4 + [5e-2] * 3)


def _inputs(steps: int, d: int, l: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    scale = np.resize(_RESIDUAL_SCALE, d)[:, None]
    theta_a = scale * rng.normal(size=(d, l)) / np.sqrt(l)
    theta_b = theta_a + 0.5 * scale * rng.normal(size=(d, l)) / np.sqrt(l)
    z = rng.normal(size=(steps, l))
    theta = np.where(np.arange(steps)[:, None, None] < steps // 2, theta_a, theta_b)
    delta = np.einsum("tdi,ti->td", theta, z) + 0.1 * scale[:, 0] * rng.normal(size=(steps, d))
    sigma_z2 = np.full((steps, l), 0.05)
    return np.concatenate([z, delta, sigma_z2], axis=1).astype(np.float32)


def _measure(Ks, d: int, l: int, steps: int, warmup: int, seed: int, floors=(1.0, 0.0)) -> dict:
    """Timing loop; runs in the worker process."""
    import jax

    from arcade_core import adaptation as A

    inputs = _inputs(warmup + steps, d, l, seed)
    results = []
    for floor, K in ((f, K) for f in floors for K in Ks):
        cfg = A.quadrotor_config()._replace(K=int(K), prior_floor=float(floor))
        packed = A.pack(A.init(np.zeros((d, l), np.float32), cfg), cfg)
        fn = A.make_packed_step()
        samples = []
        for i, x in enumerate(inputs):
            t0 = time.perf_counter()
            packed, out = fn(packed, x)
            jax.block_until_ready((packed, out))
            if i >= warmup:
                samples.append(time.perf_counter() - t0)
        assert np.isfinite(np.asarray(out)).all(), "non-finite adaptation output"
        med, p99 = percentiles(samples, 1e6)
        results.append(
            {
                "K": int(K),
                "prior_floor": float(floor),
                "median_us": round(med, 2),
                "p99_us": round(p99, 2),
            }
        )
    return {"machine": machine(), "d": d, "l": l, "results": results}


def run(
    Ks=(5, 10, 15, 20, 30),
    d: int = 13,
    l: int = 8,
    steps: int = 3000,
    warmup: int = 300,
    seed: int = 0,
    quick: bool = False,
    sync_dispatch: bool = True,
) -> dict:
    """Median and p99 latency (µs) of one adaptation step for each beam size in ``Ks``.

    Returns ``{"machine", "d", "l", "results": [{"K", "prior_floor", "median_us", "p99_us"},
    ...]}``.
    """
    if quick:
        steps, warmup = 400, 100
    job = dict(Ks=list(Ks), d=d, l=l, steps=steps, warmup=warmup, seed=seed, sync=sync_dispatch)
    proc = subprocess.run(
        [sys.executable, "-m", "benchmarks.adapt", "--worker", json.dumps(job)],
        capture_output=True,
        text=True,
        check=False,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"adaptation benchmark worker failed:\n{proc.stderr[-4000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _worker(job: dict) -> None:
    import jax

    # Must precede the first JAX computation: it configures the CPU client.
    jax.config.update("jax_cpu_enable_async_dispatch", not job.pop("sync"))
    from arcade_io import jaxsetup

    jaxsetup.configure(x64=False)
    print(json.dumps(_measure(**job)))


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true", help="fewer steps (smoke run)")
    p.add_argument("--async-dispatch", action="store_true", help="JAX's default CPU dispatch")
    p.add_argument("--steps", type=int, default=3000)
    p.add_argument("--worker", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        _worker(json.loads(args.worker))
        return
    result = run(steps=args.steps, quick=args.quick, sync_dispatch=not args.async_dispatch)
    print(jsonout.dumps(result, indent=2))


if __name__ == "__main__":
    main()
