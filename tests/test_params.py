from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fricjax.errors import FricjaxError
from fricjax.params import Param, ParamSpec

SPEC = ParamSpec(
    (
        Param("a", "N", 0.0, 2.0, 1.0),
        Param("b", "1", 1.0, 1.0, 1.0, free=False),
        Param("c", "m/s", -1.0, 1.0, 0.5),
    )
)


def test_flat_named_round_trip() -> None:
    theta = np.array([1.5, -0.25])
    named = SPEC.unflatten(jnp.asarray(theta))
    assert {k: float(v) for k, v in named.items()} == {"a": 1.5, "b": 1.0, "c": -0.25}
    np.testing.assert_array_equal(SPEC.flatten({k: float(v) for k, v in named.items()}), theta)
    np.testing.assert_array_equal(SPEC.lower, [0.0, -1.0])
    np.testing.assert_array_equal(SPEC.upper, [2.0, 1.0])


def test_unflatten_vmaps() -> None:
    thetas = jnp.array([[0.1, 0.2], [0.3, 0.4]])
    out = jax.vmap(lambda th: SPEC.unflatten(th)["c"] * 2)(thetas)
    np.testing.assert_allclose(np.asarray(out), [0.4, 0.8])


def test_rejects_bad_specs() -> None:
    with pytest.raises(FricjaxError, match="lower bound 3 > upper bound 2"):
        ParamSpec((Param("a", "N", 3.0, 2.0, 2.5),), source="x.toml")
    with pytest.raises(FricjaxError, match="fixed value 5 outside"):
        ParamSpec((Param("a", "N", 0.0, 2.0, 5.0, free=False),), source="x.toml")
    with pytest.raises(FricjaxError, match="unknown parameter 'zz'"):
        SPEC.flatten({"zz": 1.0})
