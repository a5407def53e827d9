"""CSAA: eq. 12 redraw and the adaptive Gaussian move, alone and inside run_chains."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

from fricjax.search import csaa
from fricjax.search.annealing import AnnealSettings
from fricjax.search.chains import run_chains

CENTRE = np.array([0.3, -1.2, 2.5, 0.7, -0.4])
LOWER, UPPER = np.full(5, -3.0), np.full(5, 3.0)
SETTINGS = AnnealSettings(steps_per_level=40, max_levels=150, alpha=0.88)


def _quad(x):
    return jnp.sum((x - CENTRE) ** 2)


def _rastrigin(x):
    # Global minimum 0 at the origin, local minima near every integer point.
    return 10.0 * x.shape[0] + jnp.sum(x**2 - 10.0 * jnp.cos(2.0 * jnp.pi * x))


@pytest.fixture(scope="module")
def quad_runs():
    return {
        m: run_chains(jax.random.key(11), _quad, LOWER, UPPER, m, SETTINGS, n_chains=8)
        for m in ("csaa", "csaa-gauss")
    }


def test_redraw_quadratic_5d_minimum(quad_runs):
    r = quad_runs["csaa"]
    err = np.abs(r.chain_x - CENTRE).max(axis=1)
    # Eq. 12 is a random redraw: accuracy grows only like 1/(redraws per parameter).
    assert np.all(err < 0.1)  # 1/60 of each range
    assert np.abs(r.best_x - CENTRE).max() < 0.03
    assert r.best_cost == pytest.approx(float(_quad(r.best_x)), rel=1e-12)


def test_gauss_quadratic_5d_minimum(quad_runs):
    r = quad_runs["csaa-gauss"]
    err = np.abs(r.chain_x - CENTRE).max(axis=1)
    assert np.all(err < 0.02)


def test_final_points_inside_box(quad_runs):
    for r in quad_runs.values():
        assert np.all(r.chain_x >= LOWER) and np.all(r.chain_x <= UPPER)


def test_gauss_acceptance_driven_towards_target(quad_runs):
    # The scale adapts level by level: mid-run acceptance sits near the 0.4 target.
    acc = quad_runs["csaa-gauss"].traces.acceptance
    assert 0.25 < float(np.mean(acc[40:100])) < 0.55
    # Eq. 12 redraws are rejected almost always once the chains are cold.
    assert float(np.mean(quad_runs["csaa"].traces.acceptance[-20:])) < 0.05


def test_redraw_rastrigin_2d_global_minimum_on_most_chains():
    box = np.full(2, 5.12)
    r = run_chains(jax.random.key(4), _rastrigin, -box, box, "csaa", SETTINGS, n_chains=8)
    in_global_well = np.all(np.abs(r.chain_x) < 0.5, axis=1)
    assert in_global_well.sum() >= 6
    assert r.best_cost < 0.01


_redraw = jax.jit(jax.vmap(csaa.redraw, in_axes=(0, None, None, None, None)), static_argnums=4)


def test_redraw_changes_exactly_k_parameters_uniformly_in_bounds():
    x = jnp.asarray(CENTRE)
    u = np.random.default_rng(0).uniform(size=(20_000, 5 + 2))
    new = np.asarray(_redraw(u, x, LOWER, UPPER, 2))
    changed = new != CENTRE
    assert np.all(changed.sum(axis=1) == 2)
    assert np.all(new >= LOWER) and np.all(new <= UPPER)
    # Each parameter is picked with probability k/d = 2/5 ...
    np.testing.assert_allclose(changed.mean(axis=0), 0.4, atol=5 * math.sqrt(0.24 / 20_000))
    # ... and redrawn uniformly over its range (eq. 12).
    values = (new[changed] - LOWER[0]) / (UPPER[0] - LOWER[0])
    assert stats.kstest(values, "uniform").pvalue > 1e-4


_gauss = jax.jit(
    jax.vmap(csaa.gauss_proposal, in_axes=(0, None, None, None, None, None)), static_argnums=5
)


def test_gauss_proposal_reflects_into_box_and_has_range_scaled_spread():
    rng = np.random.default_rng(1)
    corner = jnp.asarray(UPPER - 1e-3)
    u = rng.uniform(size=(20_000, 5))
    big = np.asarray(_gauss(u, corner, LOWER, UPPER, 1.0, 0))
    assert np.all(big >= LOWER) and np.all(big <= UPPER)
    small = np.asarray(_gauss(u, jnp.zeros(5), LOWER, UPPER, 0.01, 0))
    # Away from the bounds the step is N(0, (s·(b − a))²) on every parameter.
    np.testing.assert_allclose(small.std(axis=0), 0.06, rtol=0.03)
    assert np.all(small != 0.0)


def test_adapt_scale_follows_acceptance():
    s = AnnealSettings(gauss_target=0.4, gauss_gamma=2.0, gauss_scale0=0.1)
    state = csaa.init(jax.random.key(0), jnp.zeros(3), 1.0, -jnp.ones(3), jnp.ones(3), s)
    up = csaa.adapt_scale(state, 0.9, s)
    down = csaa.adapt_scale(state, 0.0, s)
    assert float(up.adapt) == pytest.approx(0.1 * math.exp(2.0 * 0.5), rel=1e-12)
    assert float(down.adapt) == pytest.approx(0.1 * math.exp(-2.0 * 0.4), rel=1e-12)
    huge = csaa.adapt_scale(state._replace(adapt=jnp.asarray(0.9)), 1.0, s)
    assert float(huge.adapt) == csaa.SCALE_MAX
