from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from fricjax.model.friction import CoulombViscous, StribeckFriction, stribeck_curve
from fricjax.model.term import Signals

P = {
    k: jnp.asarray(v)
    for k, v in {"Fc": 30.0, "Fs": 189.99, "vs": 0.121, "delta": 1.0, "Fv": 3749.9}.items()
}


def sig(v: np.ndarray) -> Signals:
    v = jnp.asarray(v, dtype=jnp.float64)
    return Signals(jnp.zeros_like(v), jnp.zeros_like(v), v, jnp.zeros_like(v))


def test_stribeck_values_at_known_points() -> None:
    f = StribeckFriction()
    v = np.array([0.121, 1.0, -0.121, 1e-12])
    got = np.asarray(f.force(P, sig(v)))
    expect = [
        30 + 159.99 * np.exp(-1) + 3749.9 * 0.121,
        30 + 159.99 * np.exp(-1 / 0.121) + 3749.9,
        -(30 + 159.99 * np.exp(-1) + 3749.9 * 0.121),
        189.99,  # v -> 0+: the static level Fs
    ]
    np.testing.assert_allclose(got, expect, rtol=1e-9)
    assert float(f.force(P, sig(np.array([0.0])))[0]) == 0.0  # sgn(0) = 0


def test_stribeck_equals_seed_eq1_for_positive_speed() -> None:
    v = np.linspace(1e-4, 2.0, 50)
    p = dict(P, delta=jnp.asarray(1.7))
    seed_eq1 = 30 * 1 + (189.99 - 30) * np.exp(-((v / 0.121) ** 1.7)) + 3749.9 * v
    np.testing.assert_allclose(
        np.asarray(StribeckFriction().force(p, sig(v))), seed_eq1, rtol=1e-12
    )


@settings(max_examples=50, deadline=None)
@given(
    st.floats(min_value=-5.0, max_value=5.0, allow_nan=False),
    st.floats(min_value=0.3, max_value=4.0),
)
def test_friction_is_odd(v: float, delta: float) -> None:
    p = dict(P, delta=jnp.asarray(delta))
    for term in (StribeckFriction(), CoulombViscous()):
        fwd = float(term.force(p, sig(np.array([v])))[0])
        bwd = float(term.force(p, sig(np.array([-v])))[0])
        assert fwd == -bwd


def test_gradient_finite_at_rest_for_any_delta() -> None:
    for delta in (0.5, 1.0, 2.0):
        g = jax.grad(lambda d: stribeck_curve(jnp.asarray(0.0), 30.0, 190.0, 0.1, d))(
            jnp.asarray(delta)
        )
        assert np.isfinite(float(g))


def test_static_limit_is_fs() -> None:
    s = sig(np.array([0.0]))
    assert float(StribeckFriction().static(P, s, jnp.asarray(-1.0))[0]) == -189.99
    assert float(CoulombViscous().static(P, s, jnp.asarray(1.0))[0]) == 30.0
