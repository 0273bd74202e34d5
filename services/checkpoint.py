"""The adapter's posterior checkpoint: a beam (``BeamState`` fields) in one ``.npz`` file.

Written atomically at the adapter's checkpoint period and at shutdown, restored at start
only when the stored beam has the layout and the metadata (weights, method, knobs) of the
one it would replace.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from arcade_io import atomicfile


def save_checkpoint(path: Path, beam: Any, meta: dict[str, Any]) -> None:
    """Atomically write a beam (``BeamState`` fields) and ``meta`` strings to ``path``."""
    arrays = {f: np.asarray(getattr(beam, f)) for f in beam._fields}
    arrays.update({f"meta_{k}": np.asarray(str(v)) for k, v in meta.items()})
    # Against a crash of the process, not of the machine: no fsync in the adapter's loop.
    with atomicfile.atomic_open(path, "wb", fsync=False) as f:
        np.savez(f, **arrays)


def load_checkpoint(path: Path, template: Any, meta: dict[str, Any]) -> Any | None:
    """The beam stored at ``path`` if it matches ``template``'s shapes and ``meta``."""
    path = Path(path)
    if not path.is_file():
        return None
    with np.load(path) as data:
        for k, v in meta.items():
            if f"meta_{k}" not in data or str(data[f"meta_{k}"]) != str(v):
                return None
        fields = {}
        for f in template._fields:
            ref = np.asarray(getattr(template, f))
            if f not in data:  # written by a version whose beam had other fields
                return None
            a = data[f]
            if a.shape != ref.shape:
                return None
            fields[f] = a.astype(ref.dtype)
    import jax.numpy as jnp

    return type(template)(**{k: jnp.asarray(v) for k, v in fields.items()})
