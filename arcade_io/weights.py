"""VLD weight files: one self-describing file per trained encoder/decoder.

Layout (all in one file)::

    b"ARCADE-VLD\\n"                 magic
    8 bytes, little-endian uint64     length of the header
    header                            UTF-8 JSON (see below)
    payload                           ``equinox.tree_serialise_leaves`` of the module

The header holds the format version, the package version that wrote it, the
:class:`~arcade_core.encoder.EncoderConfig` (enough to rebuild the module skeleton), the
floating dtype, the SHA-256 and length of the payload, and a caller-supplied ``extra``
dict (system name, description of the training data, metrics, ...). Loading rebuilds the
skeleton from the stored config and reads the leaves into it, so a round trip is exact
(bit for bit, at the same JAX precision setting). Any inconsistency raises
:class:`WeightFileError` with the reason. ``extra["system"]`` names the system the VLD was
trained for; a loader that needs one system (``load_model(..., system=...)``) refuses the
others' files, and those whose state/input dimensions are not the system's
(:data:`SYSTEM_DIMS`). :func:`weight_file_problem` is the one-line check of the command line.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import struct
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from arcade_core.encoder import VLD, EncoderConfig
from arcade_io import __version__, atomicfile

MAGIC = b"ARCADE-VLD\n"
FORMAT_VERSION = 1
_LEN = struct.Struct("<Q")
_MAX_HEADER = 1 << 24  # a header is a few kB; anything larger is a corrupt length field
#: State and input dimensions of each system's VLD.
SYSTEM_DIMS = {"cartpole": (4, 1), "quadrotor": (13, 4)}


class WeightFileError(ValueError):
    """A weight file is corrupt, of an unknown format, or does not match expectations."""


def save_model(
    path: str | os.PathLike[str],
    model: VLD,
    config: EncoderConfig,
    extra: dict[str, Any] | None = None,
) -> Path:
    """Write ``model`` (built from ``config``) and JSON-serialisable ``extra`` to ``path``.

    The write is atomic (temporary file + rename), so a reader never sees half a file.
    Returns the path written.
    """
    path = Path(path)
    _check_model_matches(model, config)
    buf = io.BytesIO()
    eqx.tree_serialise_leaves(buf, model)
    payload = buf.getvalue()
    header = {
        "format": "arcade-vld",
        "format_version": FORMAT_VERSION,
        "arcade_version": __version__,
        "config": config.to_dict(),
        "dtype": str(model.theta0.dtype),
        "payload_bytes": len(payload),
        "payload_sha256": hashlib.sha256(payload).hexdigest(),
        "extra": dict(extra or {}),
    }
    try:
        header_bytes = json.dumps(header, sort_keys=True, allow_nan=False).encode()
    except (TypeError, ValueError) as err:
        raise ValueError(f"extra must be JSON-serialisable (finite numbers): {err}") from err

    return atomicfile.write_bytes(
        path, MAGIC + _LEN.pack(len(header_bytes)) + header_bytes + payload
    )


def read_header(path: str | os.PathLike[str]) -> dict[str, Any]:
    """The parsed, validated header of a weight file (payload checksum included)."""
    return _read(Path(path))[0]


def load_model(
    path: str | os.PathLike[str],
    *,
    expected_config: EncoderConfig | None = None,
    system: str | None = None,
) -> tuple[VLD, EncoderConfig, dict[str, Any]]:
    """Read a weight file written by :func:`save_model`: ``(model, config, extra)``.

    ``expected_config``, when given, must equal the stored config (e.g. a caller that
    needs the Appendix D architecture); otherwise :class:`WeightFileError` is raised.
    ``system`` (e.g. ``"quadrotor"``), when given, must be the system the file records
    and match its dimensions (:data:`SYSTEM_DIMS`); otherwise :class:`WeightFileError`.
    A missing file raises ``FileNotFoundError``. Loading is exact when the JAX precision
    setting matches the one the file was written with; a float64 file read with
    ``jax_enable_x64`` off is rounded to float32.
    """
    path = Path(path)
    header, payload = _read(path)
    try:
        config = EncoderConfig.from_dict(header["config"])
    except (TypeError, ValueError) as err:
        raise WeightFileError(f"{path}: invalid encoder config in header: {err}") from err
    if expected_config is not None and config != expected_config:
        diff = {
            k: (v, getattr(config, k))
            for k, v in expected_config._asdict().items()
            if getattr(config, k) != v
        }
        raise WeightFileError(f"{path}: config mismatch (field: (expected, stored)): {diff}")
    if system is not None:
        _check_system(path, config, header["extra"], system)

    # A float64 file read with x64 disabled is loaded as float32 (the only loss-y case).
    dtype = jax.dtypes.canonicalize_dtype(jnp.dtype(header["dtype"]))
    # Shapes and dtypes only: initialising the weights that the file replaces costs about
    # half a second of eager operations in every process that loads a model.
    # The key is abstract too: a concrete one would run two eager operations.
    key = jax.ShapeDtypeStruct((2,), jnp.uint32)
    skeleton = eqx.filter_eval_shape(VLD, key, config, dtype=dtype)
    stream = io.BytesIO(payload)
    try:
        model = eqx.tree_deserialise_leaves(stream, skeleton, filter_spec=_host_cast_leaf)
    except Exception as err:  # numpy/equinox raise several types for malformed data
        raise WeightFileError(f"{path}: payload does not match the stored config: {err}") from err
    if stream.tell() != len(payload):
        raise WeightFileError(f"{path}: payload has {len(payload) - stream.tell()} extra bytes")
    return model, config, header["extra"]


def _host_cast_leaf(f: Any, x: Any) -> Any:
    """equinox's default leaf reader, except that an array is cast to JAX's precision
    (float64 to float32 with x64 off) on the host: ``jnp.load`` casts on the device, which
    lowers and compiles one conversion per leaf shape in every process that loads a model.
    The same rounding (IEEE round to nearest) either way. ``device_put``, not
    ``jnp.asarray``, which compiles a copy per leaf shape too (about 10 ms each)."""
    if isinstance(x, (jax.Array, jax.ShapeDtypeStruct)):
        a = np.load(f)
        return jax.device_put(a.astype(jax.dtypes.canonicalize_dtype(a.dtype), copy=False))
    return eqx.default_deserialise_filter_spec(f, x)


def weight_file_problem(path: str | os.PathLike[str], system: str | None = None) -> str | None:
    """Why ``path`` cannot be loaded (as ``system``'s VLD when given), in one line that
    starts with the path; None when it loads."""
    path = Path(path)
    if not path.exists():
        return f"{path}: no such file"
    if not path.is_file():
        return f"{path}: not a file"
    try:
        load_model(path, system=system)
    except WeightFileError as err:
        return str(err).splitlines()[0]
    except OSError as err:
        return f"{path}: {err.strerror or err}"
    return None


def _check_system(path: Path, config: EncoderConfig, extra: Any, system: str) -> None:
    stored = extra.get("system") if isinstance(extra, dict) else None
    if stored is not None and stored != system:
        raise WeightFileError(f"{path}: weights of the {stored}, not of the {system}")
    want = SYSTEM_DIMS.get(system)
    if want is not None and (config.x_dim, config.u_dim) != want:
        raise WeightFileError(
            f"{path}: a VLD for {config.x_dim} states and {config.u_dim} inputs; the "
            f"{system} has {want[0]} and {want[1]}"
        )


def _read(path: Path) -> tuple[dict[str, Any], bytes]:
    if not path.is_file():
        raise FileNotFoundError(f"weight file not found: {path}")
    data = path.read_bytes()
    if not data.startswith(MAGIC):
        raise WeightFileError(f"{path}: not an ARCADE VLD weight file (bad magic)")
    start = len(MAGIC) + _LEN.size
    if len(data) < start:
        raise WeightFileError(f"{path}: truncated header")
    (n,) = _LEN.unpack_from(data, len(MAGIC))
    if n > _MAX_HEADER or start + n > len(data):
        raise WeightFileError(f"{path}: corrupt or truncated header (length {n})")
    try:
        header = json.loads(data[start : start + n].decode())
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise WeightFileError(f"{path}: header is not valid JSON: {err}") from err
    required = {"format", "format_version", "config", "dtype", "payload_bytes", "payload_sha256"}
    if not isinstance(header, dict) or not required <= set(header):
        raise WeightFileError(f"{path}: header lacks fields {sorted(required - set(header))}")
    if header["format"] != "arcade-vld" or header["format_version"] != FORMAT_VERSION:
        raise WeightFileError(
            f"{path}: unsupported format {header['format']!r} v{header['format_version']} "
            f"(this version reads arcade-vld v{FORMAT_VERSION})"
        )
    payload = data[start + n :]
    if len(payload) != header["payload_bytes"]:
        raise WeightFileError(
            f"{path}: payload is {len(payload)} bytes, header says {header['payload_bytes']}"
        )
    if hashlib.sha256(payload).hexdigest() != header["payload_sha256"]:
        raise WeightFileError(f"{path}: payload checksum mismatch (file corrupt)")
    header.setdefault("extra", {})
    return header, payload


def _check_model_matches(model: VLD, config: EncoderConfig) -> None:
    """Refuse to write a file whose config could not rebuild ``model``."""
    skeleton = VLD(jax.random.PRNGKey(0), config, dtype=model.theta0.dtype)
    a, b = (eqx.filter(m, eqx.is_array) for m in (model, skeleton))
    same = jax.tree_util.tree_structure(a) == jax.tree_util.tree_structure(b) and [
        x.shape for x in jax.tree_util.tree_leaves(a)
    ] == [x.shape for x in jax.tree_util.tree_leaves(b)]
    if not same or model.activation != config.activation:
        raise ValueError("model does not match config (architecture or activation differ)")
