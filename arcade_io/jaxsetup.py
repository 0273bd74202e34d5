"""One place that configures JAX for every entry point (CLI, services, tests).

JAX on CPU compiles slowly, so the persistent compilation cache is always on. The cache
lives in ``$ARCADE_JAX_CACHE`` (default ``~/.cache/arcade/jax``).
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator
from pathlib import Path


def cache_dir() -> Path:
    return Path(os.environ.get("ARCADE_JAX_CACHE", Path.home() / ".cache" / "arcade" / "jax"))


def configure(*, x64: bool = False) -> None:
    """Enable the persistent compilation cache (and optionally float64).

    Call before the first jitted function runs. Safe to call more than once.
    """
    import jax

    path = cache_dir()
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", str(path))
    # Cache everything: even "fast" compiles cost tens of ms each and services compile many.
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    if x64:
        jax.config.update("jax_enable_x64", True)


@contextlib.contextmanager
def x64(enabled: bool = True) -> Iterator[None]:
    """Float64 on (or off) inside the block, the previous setting restored after it: a
    benchmark that needs float64 must not change the dtype of the ones run after it in
    the same process."""
    import jax

    previous = bool(jax.config.jax_enable_x64)
    jax.config.update("jax_enable_x64", enabled)
    try:
        yield
    finally:
        jax.config.update("jax_enable_x64", previous)
