"""Traced JAX functions kept on disk, so that a process starts without tracing them.

The persistent compilation cache (:mod:`arcade_io.jaxsetup`) keeps XLA's compilation, not
the Python tracing and lowering before it, which JAX redoes in every process: for the
controller's MPC step (an Optimistix solve inside a while loop) that is about 3 s per
function at each start of the service. :func:`load_or_trace` keeps the lowered function
(``jax.export``: StableHLO, serialized with ``flatbuffers``) and loads it on the next start;
its compilation is then a hit of the persistent cache.

**The key** names everything the lowered function depends on, so that a stale file is never
loaded: the function's name and the caller's ``key`` (whatever the function closes over
besides code: options, delays); the content of every source and data file of the packages
that define what is traced (:data:`SOURCES`: the library, the file layer, the services and
the vehicle presets); the JAX version; the ``jax_enable_x64`` setting; and the abstract
signature of the arguments (their tree structure with the static fields of modules,
shapes, dtypes, weak types). The arguments themselves (weights, learned state, references)
are inputs of the function, never baked into it. Anything else a function closes over must
be in ``key``: the caller's responsibility, stated where it calls.

A hit deserializes the function (milliseconds); a miss, or a file that cannot be read (a
truncated write, another format), traces as ``jax.jit`` would and stores the result
atomically. ``ARCADE_TRACED=0`` turns the store off (always trace). The files live beside
the compilation cache (``<cache>/traced``); deleting them is always safe.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import pickle
import re
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from arcade_io.atomicfile import write_bytes
from arcade_io.jaxsetup import cache_dir

ROOT = Path(__file__).resolve().parent.parent
#: What a traced function of the stack can depend on besides its arguments.
SOURCES = ("arcade_core", "arcade_control", "arcade_io", "services", "deploy/vehicles")
#: File format of a stored function (bump when the layout below changes).
FORMAT = 1


@functools.cache
def source_digest(tops: tuple[str, ...] = SOURCES, suffixes=(".py", ".toml", ".json")) -> str:
    """SHA-256 of the names and contents of the files with ``suffixes`` under the
    folders ``tops`` of the source tree (a key for what was computed from them)."""
    h = hashlib.sha256()
    for top in tops:
        for path in sorted((ROOT / top).rglob("*")):
            if path.suffix in suffixes and "__pycache__" not in path.parts:
                h.update(str(path.relative_to(ROOT)).encode())
                h.update(path.read_bytes())
    return h.hexdigest()


_ADDRESS = re.compile(r" at 0x[0-9a-fA-F]+")


def _signature(leaves: Sequence[Any], treedef: Any) -> str:
    import jax

    avals = [jax.typeof(x) for x in leaves]
    weak = [a.weak_type for a in avals]
    # Function-valued static fields print with their address, which differs per process.
    return _ADDRESS.sub("", f"{treedef}|{[str(a) for a in avals]}|{weak}")


def _key(name: str, key: str, leaves: Sequence[Any], treedef: Any) -> str:
    import jax

    parts = [
        f"format {FORMAT}",
        name,
        key,
        source_digest(),
        f"jax {jax.__version__}",
        f"x64 {bool(jax.config.jax_enable_x64)}",
        _signature(leaves, treedef),
    ]
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()


def enabled() -> bool:
    return os.environ.get("ARCADE_TRACED", "1") != "0"


class Traced:
    """A function lowered and compiled for the arguments it was first given; called with
    arguments of the same structure, shapes and dtypes. ``loaded``: it came from disk."""

    def __init__(
        self, exported: Any, leaves: Sequence[Any], treedef: Any, result_tree: Any, loaded: bool
    ):
        import jax

        # Compiled once for these arguments: a later call with arrays that differ only in
        # how JAX holds them (committed to the device or not, e.g. a previous result) does
        # not compile again, as a jitted function would on its first such call.
        self._call = jax.jit(exported.call).lower(*leaves).compile()
        self._treedef = treedef
        self._result_tree = result_tree
        self.loaded = loaded

    def __call__(self, *args: Any) -> Any:
        import jax

        leaves, treedef = jax.tree.flatten(args)
        if treedef != self._treedef:
            raise TypeError(f"traced for arguments {self._treedef}, called with {treedef}")
        return jax.tree.unflatten(self._result_tree, self._call(*leaves))


def load_or_trace(name: str, fn: Callable[..., Any], args: tuple, key: str = "") -> Traced:
    """``fn`` lowered for ``args``, from the store when a function for this ``name``,
    ``key``, code and signature is there, else traced and stored.

    ``fn`` must return a tree of tuples, lists, dicts and named tuples of arrays, or of
    modules whose static fields pickle (its structure is stored with the function); its
    arguments may be any tree.
    """
    import jax
    from jax import export

    leaves, treedef = jax.tree.flatten(args)
    digest = _key(name, key, leaves, treedef)
    path = cache_dir() / "traced" / f"{name}-{digest[:32]}.bin"
    if enabled() and path.is_file():
        try:
            blob = pickle.loads(path.read_bytes())
            if blob["key"] == digest:
                exported = export.deserialize(blob["exported"])
                return Traced(exported, leaves, treedef, blob["result_tree"], loaded=True)
        except Exception:  # unreadable or another format: trace afresh below
            pass
    result_trees = []

    def flat(*flat_args):
        out, result_tree = jax.tree.flatten(fn(*jax.tree.unflatten(treedef, flat_args)))
        result_trees.append(result_tree)
        return out

    exported = export.export(jax.jit(flat))(*leaves)
    result_tree = result_trees[0]
    if enabled():
        blob = {"key": digest, "exported": exported.serialize(), "result_tree": result_tree}
        try:
            data = pickle.dumps(blob)
            stored = pickle.loads(data)["result_tree"]  # its structure must round-trip
            stored.unflatten([None] * stored.num_leaves)
        except Exception as err:
            raise TypeError(
                f"{name}: its result must be a tree of tuples, lists, dicts and named "
                f"tuples of arrays to be stored ({err})"
            ) from err
        path.parent.mkdir(parents=True, exist_ok=True)
        with contextlib.suppress(OSError):  # a read-only cache: the next start traces again
            write_bytes(path, data)
    return Traced(exported, leaves, treedef, result_tree, loaded=False)
