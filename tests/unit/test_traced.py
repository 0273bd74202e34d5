"""Traced functions kept on disk (arcade_io.traced): loaded only under their own key,
bit-identical to ``jax.jit``, and a bad file is traced afresh."""

from __future__ import annotations

import warnings
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from arcade_io import traced


class Pair(NamedTuple):
    a: jax.Array
    b: jax.Array


class Net(eqx.Module):
    w: jax.Array
    scale: float = eqx.field(static=True)


def _solve(pair: Pair, net: Net, k):
    """A Cholesky solve (a LAPACK kernel on CPU) and a loop, like the MPC step."""
    m = pair.a @ pair.a.T + net.scale * jnp.eye(pair.a.shape[0])
    x = jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(m), pair.b)
    y = jax.lax.fori_loop(0, 5, lambda i, v: jnp.tanh(v + net.w * k), x)
    return Pair(x, y), {"norm": jnp.linalg.norm(y)}


def _args(n: int = 3, k: int = 2):
    rng = np.random.default_rng(0)
    return Pair(rng.normal(size=(n, n)), rng.normal(size=n)), Net(jnp.ones(n), 0.5), k


@pytest.fixture
def store(tmp_path, monkeypatch):
    monkeypatch.setenv("ARCADE_JAX_CACHE", str(tmp_path))
    monkeypatch.delenv("ARCADE_TRACED", raising=False)
    return tmp_path / "traced"


def test_a_stored_function_is_loaded_and_matches_jit_bit_for_bit(store):
    args = _args()
    first = traced.load_or_trace("solve", _solve, args)
    again = traced.load_or_trace("solve", _solve, args)
    assert not first.loaded and again.loaded
    assert len(list(store.iterdir())) == 1
    want = jax.jit(_solve)(*args)
    for f in (first, again):
        got = f(*args)
        assert jax.tree.structure(got) == jax.tree.structure(want)
        for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
            np.testing.assert_array_equal(np.asarray(g), np.asarray(w))
    # Other values of the same signature are inputs, not constants.
    other = (Pair(args[0].a * 2.0, args[0].b), Net(jnp.full(3, 0.3), 0.5), 3)
    for g, w in zip(jax.tree.leaves(again(*other)), jax.tree.leaves(jax.jit(_solve)(*other))):
        np.testing.assert_array_equal(np.asarray(g), np.asarray(w))


def test_what_the_function_depends_on_is_in_its_key(store):
    args = _args()
    traced.load_or_trace("solve", _solve, args)
    different = [
        ("solve", _args(), "delay=0.02"),  # the caller's key (what the function closes over)
        ("solve", _args(n=4), ""),  # shapes
        ("solve", (_args()[0], Net(jnp.ones(3), 0.7), 2), ""),  # a static field
        ("solve", (*_args()[:2], 2.0), ""),  # a dtype
        ("other", _args(), ""),  # the name
    ]
    for name, a, key in different:
        assert not traced.load_or_trace(name, _solve, a, key).loaded, (name, key)
    assert len(list(store.iterdir())) == 1 + len(different)
    # The same arguments in the other precision (float64 arrays become float32 ones).
    with jax.enable_x64(not jax.config.jax_enable_x64), warnings.catch_warnings():
        warnings.filterwarnings("ignore", "Explicitly requested dtype", UserWarning)
        assert not traced.load_or_trace("solve", _solve, args).loaded


def test_a_damaged_file_is_traced_afresh_and_replaced(store):
    args = _args()
    traced.load_or_trace("solve", _solve, args)
    (path,) = store.iterdir()
    path.write_bytes(path.read_bytes()[:100])
    again = traced.load_or_trace("solve", _solve, args)
    assert not again.loaded
    np.testing.assert_array_equal(
        np.asarray(again(*args)[0].a), np.asarray(jax.jit(_solve)(*args)[0].a)
    )
    assert traced.load_or_trace("solve", _solve, args).loaded


def test_the_store_can_be_turned_off(store, monkeypatch):
    monkeypatch.setenv("ARCADE_TRACED", "0")
    assert not traced.load_or_trace("solve", _solve, _args()).loaded
    assert not traced.load_or_trace("solve", _solve, _args()).loaded
    assert not store.exists()


def test_arguments_of_another_structure_are_refused(store):
    f = traced.load_or_trace("solve", _solve, _args())
    with pytest.raises(TypeError, match="traced for arguments"):
        f(_args()[0], _args()[1])


def test_a_result_that_cannot_be_stored_is_a_clear_error(store):
    with pytest.raises(TypeError, match="tree of tuples"):
        traced.load_or_trace("net", lambda w: Net(w, lambda v: v), (jnp.ones(2),))
