"""Stored programs (fricjax.programs): a new process loads the traced program instead of
tracing, gets the same numbers, and nothing unreproducible is ever stored."""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fricjax import programs
from fricjax.programs import Stored, signature

TRACED: list[str] = []


class Settings(NamedTuple):
    scale: float = 2.0
    order: int = 3


class Residual(eqx.Module):
    data: jax.Array
    settings: Settings = eqx.field(static=True)


def _program(res: Residual, theta: jax.Array, shift: float) -> tuple[jax.Array, Settings]:
    TRACED.append("traced")  # runs at trace time only
    powers = jnp.stack([theta**k for k in range(res.settings.order)])
    out = res.settings.scale * jnp.sum(powers, 0) @ res.data + shift
    # a non-array output comes back too, as filter_jit returns it
    return jnp.linalg.solve(res.data.T @ res.data + jnp.eye(4), out), res.settings


@pytest.fixture
def store(tmp_path: Path) -> Path:
    folder = programs.set_store(tmp_path / "programs")
    assert folder is not None
    yield folder
    programs.set_store(None)


def _args() -> tuple[Residual, jax.Array]:
    data = jnp.asarray(np.random.default_rng(0).normal(size=(3, 4)))
    return Residual(data, Settings()), jnp.asarray([0.5, -1.0, 2.0])


def test_a_new_process_loads_the_program_and_gets_the_same_numbers(store: Path) -> None:
    res, theta = _args()
    reference, static = eqx.filter_jit(_program)(res, theta, 0.25)
    TRACED.clear()
    first, _ = Stored(_program)(res, theta, 0.25)  # exports: one trace
    assert TRACED == ["traced"] and len(list(store.iterdir())) == 1
    again = Stored(_program)  # a new process: nothing in memory
    out, settings = again(res, theta, 0.25)
    assert TRACED == ["traced"]  # loaded, not traced
    assert settings == static
    np.testing.assert_array_equal(np.asarray(out), np.asarray(reference))
    np.testing.assert_array_equal(np.asarray(first), np.asarray(reference))
    # new data of the same shape reuse it; the result follows the data
    out2, _ = again(Residual(2 * res.data, res.settings), theta, 0.25)
    assert TRACED == ["traced"]
    ref2, _ = eqx.filter_jit(_program)(Residual(2 * res.data, res.settings), theta, 0.25)
    np.testing.assert_allclose(np.asarray(out2), np.asarray(ref2), rtol=1e-14)


def test_every_static_input_and_shape_is_in_the_key() -> None:
    res, theta = _args()
    base = signature(_program, None, ((res, theta, 0.25), {}))
    assert base is not None
    assert base == signature(_program, None, ((res, 3 * theta, 0.25), {}))  # values traced
    changed = [
        ((res, theta, 0.5), {}),  # a static float
        ((Residual(res.data, Settings(order=4)), theta, 0.25), {}),  # a static field
        ((res, theta[:2], 0.25), {}),  # a shape
        ((res, theta.astype(jnp.float32), 0.25), {}),  # a dtype
    ]
    keys = {signature(_program, None, args) for args in changed}
    assert base not in keys and len(keys) == len(changed)
    assert (
        signature(_program, {"xla_backend_optimization_level": 0}, ((res, theta, 0.25), {})) != base
    )


def _apply(fn: object, x: jax.Array) -> jax.Array:
    return fn(x)  # type: ignore[operator]


def test_a_closure_is_never_stored(store: Path) -> None:
    k = 3.0
    x = jnp.arange(4.0)
    assert signature(_apply, None, ((lambda v: v * k, x), {})) is None
    out = Stored(_apply)(lambda v: v * k, x)
    np.testing.assert_array_equal(np.asarray(out), 3.0 * np.arange(4.0))
    assert list(store.iterdir()) == []


def test_inside_a_trace_it_is_traced_with_the_caller(store: Path) -> None:
    res, theta = _args()
    fn = Stored(_program)
    batched = jax.vmap(lambda th: fn(res, th, 0.25)[0])(jnp.stack([theta, 2 * theta]))
    single = eqx.filter_jit(_program)(res, 2 * theta, 0.25)[0]
    np.testing.assert_allclose(np.asarray(batched[1]), np.asarray(single), rtol=1e-14)
    assert list(store.iterdir()) == []


def test_a_damaged_file_is_traced_again_and_replaced(store: Path) -> None:
    res, theta = _args()
    Stored(_program)(res, theta, 0.25)
    (path,) = store.iterdir()
    path.write_bytes(b"not a program")
    TRACED.clear()
    out, _ = Stored(_program)(res, theta, 0.25)
    assert TRACED == ["traced"]
    assert path.read_bytes() != b"not a program"
    ref, _ = eqx.filter_jit(_program)(res, theta, 0.25)
    np.testing.assert_array_equal(np.asarray(out), np.asarray(ref))


def test_without_a_store_it_is_filter_jit() -> None:
    programs.set_store(None)
    res, theta = _args()
    TRACED.clear()
    fn = Stored(_program)
    fn(res, theta, 0.75)  # a signature no other test compiled
    fn(res, 5 * theta, 0.75)
    assert TRACED == ["traced"]
