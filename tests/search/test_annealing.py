"""Annealing control: Metropolis rule, eq. 15 initial temperature, schedules, settings."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fricjax.errors import FricjaxError
from fricjax.search.annealing import (
    AnnealSettings,
    improved,
    initial_temperature,
    metropolis_accept,
    normal_from_uniform,
    random_mask,
    random_subset,
    reflect,
    should_stop,
    temperature,
)

N_KEYS = 40_000


@jax.jit
def _acceptance_rate(key, cost, cost_new, t):
    keys = jax.random.split(key, N_KEYS)
    accepted = jax.vmap(lambda k: metropolis_accept(k, cost, cost_new, t))(keys)
    return jnp.mean(accepted)


@pytest.mark.parametrize(("delta", "t"), [(1.0, 1.0), (0.3, 2.0), (5.0, 2.5), (0.05, 0.01)])
def test_metropolis_uphill_acceptance_matches_boltzmann_factor(delta, t):
    p = math.exp(-delta / t)
    rate = float(_acceptance_rate(jax.random.key(7), 3.0, 3.0 + delta, t))
    # 4.5 binomial standard deviations: a false failure once in ~1.5e5 runs.
    sigma = math.sqrt(p * (1 - p) / N_KEYS)
    assert abs(rate - p) <= 4.5 * sigma + 1.0 / N_KEYS


def test_metropolis_downhill_always_and_nonfinite_never_accepted():
    key = jax.random.key(1)
    assert float(_acceptance_rate(key, 3.0, 2.0, 1.0)) == 1.0
    assert float(_acceptance_rate(key, 3.0, 3.0, 0.0)) == 1.0  # Δ = 0 counts as downhill
    assert float(_acceptance_rate(key, 3.0, 3.5, 0.0)) == 0.0  # t = 0: greedy
    for bad in (jnp.nan, jnp.inf, -jnp.inf):
        assert float(_acceptance_rate(key, 3.0, bad, 1e9)) == 0.0
    # A chain sitting on a non-finite cost takes any finite candidate.
    assert float(_acceptance_rate(key, jnp.nan, 1e30, 1e-9)) == 1.0


def _step_cost(x):
    # Takes exactly the values 2 and 7 on halves of the box, NaN on a corner band.
    value = jnp.where(x[0] < 0.5, 2.0, 7.0)
    return jnp.where(x[1] > 0.9, jnp.nan, value)


def _linear_cost(x):
    return x[0]


def _nan_cost(x):
    return jnp.nan * x[0]


_t0 = jax.jit(initial_temperature, static_argnums=(1, 4, 5))


def test_initial_temperature_is_K_times_cost_range():
    lower, upper = jnp.zeros(3), jnp.ones(3)
    t0 = _t0(jax.random.key(0), _step_cost, lower, upper, 10.0, 256)
    assert float(t0) == 10.0 * (7.0 - 2.0)  # NaN samples ignored, range exact
    t0 = _t0(jax.random.key(0), _linear_cost, lower, upper, 10.0, 256)
    # Sample range of 256 uniforms: below 1, above 0.97 except with probability ~1e-9.
    assert 10.0 * 0.97 < float(t0) < 10.0


def test_initial_temperature_nan_when_no_finite_cost():
    t0 = _t0(jax.random.key(0), _nan_cost, jnp.zeros(3), jnp.ones(3), 10.0, 256)
    assert math.isnan(float(t0))


LEVELS = np.arange(400)


def test_geometric_schedule_is_eq16_and_decreasing():
    s = AnnealSettings(alpha=0.95)
    t = np.asarray(temperature("geometric", 123.0, LEVELS, s))
    np.testing.assert_allclose(t, 123.0 * 0.95**LEVELS, rtol=1e-12)
    np.testing.assert_allclose(t[1:] / t[:-1], 0.95, rtol=1e-12)  # t_{k+1} = α t_k
    assert t[0] == 123.0


def test_boltzmann_and_cauchy_schedules_match_formulas_and_decrease():
    s = AnnealSettings()
    log_t = np.asarray(temperature("boltzmann", 5.0, LEVELS, s))
    np.testing.assert_allclose(log_t, 5.0 * math.log(2) / np.log(LEVELS + 2.0), rtol=1e-12)
    fast_t = np.asarray(temperature("cauchy", 5.0, LEVELS, s))
    np.testing.assert_allclose(fast_t, 5.0 / (LEVELS + 1.0), rtol=1e-12)
    for t in (log_t, fast_t):
        assert t[0] == pytest.approx(5.0, rel=1e-15)
        assert np.all(np.diff(t) < 0)


def test_reheat_schedule_restarts_at_a_fraction_of_the_last_restart():
    s = AnnealSettings(alpha=0.9, reheat_every=30, reheat_fraction=0.4)
    t = np.asarray(temperature("reheat", 2.0, LEVELS, s))
    expected = 2.0 * 0.4 ** (LEVELS // 30) * 0.9 ** (LEVELS % 30)
    np.testing.assert_allclose(t, expected, rtol=1e-12)
    starts = t[::30]
    np.testing.assert_allclose(starts[1:] / starts[:-1], 0.4, rtol=1e-12)
    cycles = t[:390].reshape(13, 30)
    assert np.all(np.diff(cycles, axis=1) < 0)  # geometric cooling inside every cycle
    assert np.all(cycles[1:, 0] > cycles[:-1, -1])  # and a reheat at each restart


def test_settings_from_dict_accepts_toml_values():
    s = AnnealSettings.from_dict(
        {"K": 5, "alpha": 0.9, "schedule": "cauchy", "steps_per_level": 10}, "run.toml"
    )
    assert (s.K, s.alpha, s.schedule, s.steps_per_level) == (5.0, 0.9, "cauchy", 10)
    assert s.n_bits == 10 and s.csaa_k == 1 and s.dsaa_k == 2


@pytest.mark.parametrize(
    ("entry", "words"),
    [
        ({"alpah": 0.9}, ["run.toml: alpah", "unknown setting", "alpha"]),
        ({"alpha": 1.5}, ["run.toml: alpha", "(0, 1)", "1.5"]),
        ({"steps_per_level": 2.5}, ["run.toml: steps_per_level", "integer"]),
        ({"patience": True}, ["run.toml: patience", "number"]),
        ({"schedule": "linear"}, ["run.toml: schedule", "geometric"]),
        ({"n_bits": 64}, ["run.toml: n_bits", "1..52"]),
        ({"K": "ten"}, ["run.toml: K", "number"]),
    ],
)
def test_settings_errors_name_file_and_field(entry, words):
    with pytest.raises(FricjaxError) as err:
        AnnealSettings.from_dict(entry, "run.toml")
    message = str(err.value)
    assert "\n" not in message
    for word in words:
        assert word in message


def test_reflect_mirrors_at_bounds_and_never_leaves_box():
    lo, hi = jnp.array([0.0, -2.0]), jnp.array([1.0, 3.0])
    x = reflect(jnp.array([1.25, -2.5]), lo, hi)
    np.testing.assert_allclose(np.asarray(x), [0.75, -1.5], rtol=0, atol=1e-15)
    far = np.random.default_rng(3).normal(size=(5000, 2)) * 100.0
    y = np.asarray(jax.jit(jax.vmap(lambda v: reflect(v, lo, hi)))(far))
    assert np.all(y >= np.asarray(lo)) and np.all(y <= np.asarray(hi))


def test_random_subset_is_uniform_over_pairs():
    # Floyd's algorithm: every 2-subset of 6 items equally likely (15 pairs).
    u = np.random.default_rng(5).uniform(size=(30_000, 2))
    idx = np.asarray(jax.jit(jax.vmap(lambda v: random_subset(v, 6, 2)))(u))
    assert np.all(idx[:, 0] != idx[:, 1])
    _, counts = np.unique(np.sort(idx, axis=1) @ np.array([6, 1]), return_counts=True)
    assert counts.size == 15
    expected = 30_000 / 15
    assert np.all(np.abs(counts - expected) < 5 * math.sqrt(expected))


def test_random_mask_has_exactly_k_entries():
    u = np.random.default_rng(2).uniform(size=(1000, 3))
    masks = np.asarray(jax.jit(jax.vmap(lambda v: random_mask(v, 26, 3)))(u))
    assert np.all(masks.sum(axis=1) == 3)
    assert bool(np.all(random_mask(jnp.zeros(0), 4, 9)))  # k ≥ n: all


def test_normal_from_uniform_is_finite_even_at_zero():
    z = np.asarray(normal_from_uniform(np.array([0.0, 0.5 - 2**-53, 1 - 2**-52])))
    assert np.all(np.isfinite(z))
    assert z[0] == pytest.approx(-z[2], rel=1e-12)  # grid symmetric about 1/2


def test_stopping_rule_needs_cold_and_stale():
    s = AnnealSettings(t_min_rel=1e-3, patience=3, rel_tol=1e-6, abs_tol=0.0)
    assert not should_stop(0.5e-3, 1.0, 2, s)  # cold but improved recently
    assert not should_stop(2e-3, 1.0, 10, s)  # stale but still warm
    assert should_stop(1e-3, 1.0, 3, s)
    assert improved(1.0, math.inf, s) and not improved(math.inf, 1.0, s)
    assert not improved(1.0 - 1e-7, 1.0, s) and improved(1.0 - 1e-5, 1.0, s)
