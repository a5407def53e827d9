"""RDSA (eq. 6): greedy random-direction steps with step-factor adaptation."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fricjax.search import rdsa
from fricjax.search.annealing import AnnealSettings
from fricjax.search.chains import run_chains

CENTRE = np.array([0.3, -1.2, 2.5, 0.7, -0.4])
LOWER, UPPER = np.full(5, -3.0), np.full(5, 3.0)
SETTINGS = AnnealSettings(steps_per_level=40, max_levels=60)


def _quad(x):
    return jnp.sum((x - CENTRE) ** 2)


@pytest.fixture(scope="module")
def quad_run():
    return run_chains(jax.random.key(2), _quad, LOWER, UPPER, "rdsa", SETTINGS, n_chains=6)


def test_quadratic_5d_minimum_on_every_chain(quad_run):
    np.testing.assert_allclose(quad_run.chain_x, np.tile(CENTRE, (6, 1)), rtol=0, atol=1e-6)
    assert np.all(quad_run.chain_x >= LOWER) and np.all(quad_run.chain_x <= UPPER)


def test_greedy_current_cost_never_increases(quad_run):
    current = quad_run.traces.current_cost
    assert np.all(np.diff(current, axis=0) <= 0)
    # Greedy: the current point is always the chain's best point.
    np.testing.assert_array_equal(current, quad_run.traces.best_cost)


def _flat(x):
    return jnp.asarray(1.0)


_step = jax.jit(rdsa.step, static_argnums=(1, 5))


def test_alpha_shrinks_after_patience_failures_and_grows_after_success():
    s = AnnealSettings(rdsa_alpha0=0.2, rdsa_grow=1.5, rdsa_shrink=0.5, rdsa_patience=3)
    lo, hi = jnp.zeros(4), jnp.ones(4)
    state = rdsa.init(jax.random.key(0), jnp.full(4, 0.5), jnp.nan, lo, hi, s)
    # Cost NaN at the start counts as +inf: the first finite candidate is a success.
    state = _step(state, _flat, 1.0, lo, hi, s)
    assert float(state.adapt.alpha) == pytest.approx(0.3, rel=1e-12) and int(state.n_accepted) == 1
    alphas = []
    for _ in range(7):  # equal cost is not better: failures
        state = _step(state, _flat, 1.0, lo, hi, s)
        alphas.append(float(state.adapt.alpha))
    np.testing.assert_allclose(alphas, [0.3, 0.3, 0.15, 0.15, 0.15, 0.075, 0.075], rtol=1e-12)
    assert int(state.n_evals) == 9 and int(state.n_proposed) == 8


def test_step_ignores_temperature_and_stays_in_box():
    s = AnnealSettings(rdsa_alpha0=1.0)
    lo, hi = jnp.zeros(3), jnp.array([1.0, 2.0, 5.0])
    state = rdsa.init(jax.random.key(4), jnp.asarray([0.99, 0.01, 4.9]), 9.0, lo, hi, s)
    hot = _step(state, _flat, 1e9, lo, hi, s)
    cold = _step(state, _flat, 0.0, lo, hi, s)
    for field in ("x", "cost", "adapt", "n_accepted"):
        for a, b in zip(
            jax.tree.leaves(getattr(hot, field)),
            jax.tree.leaves(getattr(cold, field)),
            strict=True,
        ):
            np.testing.assert_array_equal(a, b)
    # The flat cost 1 beats the start cost 9: the reflected step of a full range was taken.
    assert int(hot.n_accepted) == 1
    assert np.all(np.asarray(hot.x) >= np.asarray(lo))
    assert np.all(np.asarray(hot.x) <= np.asarray(hi))


def test_direction_is_a_unit_vector():
    u = np.random.default_rng(0).uniform(size=(100, 26))
    s = np.asarray(jax.jit(jax.vmap(rdsa.direction))(u))
    np.testing.assert_allclose(np.linalg.norm(s, axis=1), 1.0, rtol=1e-12)
