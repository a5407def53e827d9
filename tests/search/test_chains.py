"""run_chains: reproducibility, forbidden (NaN) regions, stopping, interrupts, sharding."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fricjax.errors import FricjaxError
from fricjax.search.annealing import (
    AnnealSettings,
    improved,
    propose,
    step_with_cost,
    temperature,
)
from fricjax.search.chains import (
    METHODS,
    LevelInfo,
    relative_temperatures,
    run_chains,
    run_chains_fused,
)

CENTRE = np.array([0.9, -1.2, 2.5, 0.7, -0.4])
LOWER, UPPER = np.full(5, -3.0), np.full(5, 3.0)
SETTINGS = AnnealSettings(steps_per_level=30, max_levels=60, alpha=0.85)
METHOD = "csaa-gauss"
N_CHAINS = 3  # odd: two devices need a padding chain
TRACES: list[int] = []


def _cost(x):
    TRACES.append(1)  # runs at trace time only: counts compilations
    f = jnp.sum((x - CENTRE) ** 2)
    # Forbidden regions next to the minimum: NaN (e.g. an unstable simulation) and +inf.
    f = jnp.where(x[0] > 1.0, jnp.nan, f)
    return jnp.where(x[1] < -2.5, jnp.inf, f)


def _run(seed, settings=SETTINGS, **kwargs):
    return run_chains(
        jax.random.key(seed), _cost, LOWER, UPPER, METHOD, settings, N_CHAINS, **kwargs
    )


def _arrays(r):
    t = r.traces
    return {
        "best_x": r.best_x,
        "chain_x": r.chain_x,
        "chain_cost": r.chain_cost,
        "trace_best": t.best_cost,
        "trace_current": t.current_cost,
        "trace_acceptance": t.acceptance,
        "trace_temperature": t.temperature,
        "trace_evals": t.n_evals,
    }


@pytest.fixture(scope="module")
def reference():
    return _run(0)


def test_same_key_bit_identical_different_key_different(reference):
    again, other = _run(0), _run(1)
    for name, value in _arrays(reference).items():
        np.testing.assert_array_equal(value, _arrays(again)[name], err_msg=name)
    assert reference.t0 == again.t0
    assert not np.any(reference.chain_x == other.chain_x)
    # The chains of one run are independent too.
    assert len({tuple(row) for row in reference.chain_x}) == N_CHAINS


def test_second_call_does_not_recompile(reference):
    before = len(TRACES)
    # Another key and other schedule/stopping fields: the same compiled level function.
    changed = dataclasses.replace(SETTINGS, schedule="cauchy", patience=3, K=2.0)
    _run(5, changed)
    assert len(TRACES) == before


def test_nan_and_inf_regions_never_accepted(reference):
    t = reference.traces
    for trace in (t.best_cost, t.current_cost, t.acceptance):
        assert not np.any(np.isnan(trace))
    assert np.all(np.isfinite(t.current_cost[5:]))
    assert np.all(np.isfinite(reference.chain_cost))
    assert np.all(reference.chain_x[:, 0] <= 1.0) and np.all(reference.chain_x[:, 1] >= -2.5)
    # The minimum, 0.1 from the NaN region, is approached all the same (60 short levels).
    assert reference.best_cost < 0.1


def test_bounds_respected_and_traces_consistent(reference):
    assert np.all(reference.chain_x >= LOWER) and np.all(reference.chain_x <= UPPER)
    t = reference.traces
    L = reference.levels_run
    assert t.best_cost.shape == t.current_cost.shape == t.acceptance.shape == (L, N_CHAINS)
    assert np.all(np.diff(t.best_cost, axis=0) <= 0)  # a best cost never gets worse
    assert np.all(t.current_cost >= t.best_cost)
    assert np.all((t.acceptance >= 0) & (t.acceptance <= 1))
    np.testing.assert_array_equal(reference.chain_cost, t.best_cost[-1])
    assert reference.best_cost == reference.chain_cost.min()
    # Evaluations: the box sample (temperature + start candidates), one per start point,
    # one per step.
    steps = SETTINGS.steps_per_level * np.arange(1, L + 1)
    expected = SETTINGS.n_temperature_samples + N_CHAINS * (2 + steps)
    np.testing.assert_array_equal(t.n_evals, expected)
    assert np.all(np.diff(t.wall_time) >= 0)


def test_t0_is_K_times_sampled_range_and_first_temperature(reference):
    r = _run(0, dataclasses.replace(SETTINGS, K=2.5))
    assert r.t0 / 2.5 == pytest.approx(reference.t0 / 10.0, rel=1e-15)
    assert reference.traces.temperature[0] == reference.t0
    np.testing.assert_allclose(
        reference.traces.temperature, reference.t0 * 0.85 ** np.arange(60), rtol=1e-12
    )


def test_stops_when_cold_and_stale():
    s = dataclasses.replace(SETTINGS, max_levels=200, t_min_rel=1e-3, patience=5, rel_tol=1e-6)
    r = _run(3, s)
    assert r.levels_run < 200 and not r.interrupted
    t = r.traces
    # Replay the rule on the traces: the run ended at the first level that was both cold
    # (t ≤ 1e-3 t0) and without improvement for 5 levels.
    reference_cost, stale, first = math.inf, 0, None
    for level, best in enumerate(t.best_cost.min(axis=1)):
        if improved(float(best), reference_cost, s):
            reference_cost, stale = float(best), 0
        else:
            stale += 1
        if t.temperature[level] <= 1e-3 * r.t0 and stale >= 5:
            first = level
            break
    assert first == r.levels_run - 1
    never = _run(3, dataclasses.replace(s, max_levels=45, patience=10**6))
    assert never.levels_run == 45


def test_on_level_reports_progress_and_ctrl_c_returns_what_was_found():
    seen: list[LevelInfo] = []

    def on_level(info):
        seen.append(info)
        if info.level == 2:
            raise KeyboardInterrupt

    r = _run(0, on_level=on_level)
    assert r.interrupted and r.levels_run == 3
    assert [i.level for i in seen] == [0, 1, 2]
    np.testing.assert_array_equal([i.best_cost for i in seen], r.traces.best_cost.min(axis=1))
    np.testing.assert_array_equal([i.n_evals for i in seen], r.traces.n_evals)
    np.testing.assert_array_equal([i.temperature for i in seen], r.traces.temperature)
    assert r.best_cost == seen[-1].best_cost and np.isfinite(r.best_cost)


def test_chain_started_in_nan_region_escapes_it():
    # Gaussian steps widen while a chain's cost is not finite, instead of shrinking.
    x0 = np.tile([2.9, 0.0, 0.0, 0.0, 0.0], (N_CHAINS, 1))
    r = _run(8, x0=x0)
    assert np.isinf(r.traces.current_cost[0]).any()
    assert np.all(np.isfinite(r.traces.current_cost[-1]))
    assert np.all(r.chain_x[:, 0] <= 1.0)


def test_start_at_global_minimum_keeps_it():
    x0 = np.tile(CENTRE, (N_CHAINS, 1))
    r = _run(7, x0=x0)
    np.testing.assert_array_equal(r.chain_x, x0)
    assert r.best_cost == 0.0


@pytest.mark.parametrize(
    ("kwargs", "words"),
    [
        ({"method": "simplex"}, ["cfg.toml: method", "simplex", "csaa-gauss"]),
        ({"upper": np.full(5, -3.0)}, ["cfg.toml: upper", "exceed lower", "index 0"]),
        ({"lower": np.full(4, -3.0)}, ["cfg.toml: upper", "shape"]),
        ({"lower": np.array([0, 0, np.nan, 0, 0])}, ["cfg.toml: lower", "index 2"]),
        ({"x0": np.zeros((2, 5))}, ["cfg.toml: x0", "shape (3, 5)"]),
        ({"x0": np.full((3, 5), 4.0)}, ["cfg.toml: x0", "chain 0 parameter 0", "outside"]),
        ({"n_chains": 0}, ["cfg.toml: n_chains", "≥ 1"]),
        ({"cost_fn": lambda x: jnp.nan * x[0]}, ["cfg.toml: cost", "not finite"]),
    ],
)
def test_user_errors_name_the_field(kwargs, words):
    args = {
        "key": jax.random.key(0),
        "cost_fn": _cost,
        "lower": LOWER,
        "upper": UPPER,
        "method": METHOD,
        "settings": SETTINGS,
        "n_chains": N_CHAINS,
        **kwargs,
    }
    with pytest.raises(FricjaxError) as err:
        run_chains(**args, source="cfg.toml")
    assert "\n" not in str(err.value)
    for word in words:
        assert word in str(err.value)


_TWO_DEVICE_SCRIPT = textwrap.dedent(
    """
    import importlib.util, json, sys
    import jax
    import numpy as np
    spec = importlib.util.spec_from_file_location("chains_test", sys.argv[1])
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    r = mod._run(0)
    out = {k: np.asarray(v).tolist() for k, v in mod._arrays(r).items()}
    out["n_devices"] = r.n_devices
    out["visible"] = len(jax.devices())
    print(json.dumps(out))
    """
)


def test_two_host_devices_give_the_same_result(reference):
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2")
    env["JAX_PLATFORMS"] = "cpu"
    done = subprocess.run(
        [sys.executable, "-c", _TWO_DEVICE_SCRIPT, __file__],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    )
    out = json.loads(done.stdout.strip().splitlines()[-1])
    assert out["visible"] == 2 and out["n_devices"] == 2
    # Another process: equal to rounding. The chains' draws depend only on their keys, so a
    # chain split onto another device takes the same path (JSON round-trips float64).
    for name, value in _arrays(reference).items():
        np.testing.assert_allclose(np.asarray(out[name]), value, rtol=1e-12, err_msg=name)


# -- the whole search as one program (run_chains_fused) ---------------------------------


class _CostWithAux:
    """``x -> (cost, aux)``: the test cost with ``aux = [2x, cost]`` (a pytree leaf [d + 1])."""

    def __call__(self, x):
        c = _cost(x)
        return c, jnp.concatenate([2.0 * x, c[None]])


_WITH_AUX = _CostWithAux()


def _fused(seed, settings=SETTINGS, method=METHOD, **kwargs):
    return run_chains_fused(
        jax.random.key(seed), _cost, LOWER, UPPER, method, settings, N_CHAINS, **kwargs
    )


@pytest.fixture(scope="module")
def fused_reference():
    return _fused(0)[0]


def test_fused_runs_the_same_chains_as_run_chains(reference, fused_reference):
    # Same algorithm, same draws, same acceptance and stopping: on this cost the one
    # program reproduces the level-by-level host loop exactly (only the temperatures are
    # computed as t0·(t_k/t0) instead of t_k: equal to round-off).
    f = fused_reference
    assert f.levels_run == reference.levels_run and f.t0 == reference.t0
    for name, value in _arrays(reference).items():
        if name == "trace_temperature":
            np.testing.assert_allclose(_arrays(f)[name], value, rtol=1e-14)
        else:
            np.testing.assert_array_equal(_arrays(f)[name], value, err_msg=name)


def test_fused_same_key_bit_identical_and_no_recompile(fused_reference):
    before = len(TRACES)
    again = _fused(0)[0]
    for name, value in _arrays(fused_reference).items():
        np.testing.assert_array_equal(_arrays(again)[name], value, err_msg=name)
    # schedule and stopping fields are traced values of the program: no retrace
    changed = dataclasses.replace(SETTINGS, schedule="cauchy", patience=3, K=2.0, alpha=0.9)
    other = _fused(5, changed)[0]
    assert len(TRACES) == before
    assert not np.any(other.chain_x == fused_reference.chain_x)


def test_fused_stopping_rule_on_the_device_matches_the_host_loop():
    s = dataclasses.replace(SETTINGS, max_levels=200, t_min_rel=1e-3, patience=5, rel_tol=1e-6)
    host = _run(3, s)
    fused = _fused(3, s)[0]
    assert fused.levels_run == host.levels_run < 200
    np.testing.assert_array_equal(fused.traces.best_cost, host.traces.best_cost)
    np.testing.assert_array_equal(fused.traces.n_evals, host.traces.n_evals)


def test_fused_aux_is_the_cost_functions_output_at_each_chains_best_point():
    r, aux = run_chains_fused(
        jax.random.key(2), _WITH_AUX, LOWER, UPPER, METHOD, SETTINGS, N_CHAINS, has_aux=True
    )
    assert aux.shape == (N_CHAINS, 6)
    np.testing.assert_array_equal(aux[:, :5], 2.0 * r.chain_x)
    np.testing.assert_array_equal(aux[:, 5], r.chain_cost)
    assert _fused(2)[1] is None


def test_fused_on_level_replays_every_level_and_ctrl_c_marks_the_run():
    seen: list[LevelInfo] = []

    def on_level(info):
        seen.append(info)
        if info.level == 2:
            raise KeyboardInterrupt

    r = _fused(0, on_level=on_level)[0]
    # the levels ran on the device: the replay stops, the (complete) run is kept
    assert r.interrupted and r.levels_run == SETTINGS.max_levels
    assert [i.level for i in seen] == [0, 1, 2]
    np.testing.assert_array_equal([i.best_cost for i in seen], r.traces.best_cost[:3].min(axis=1))
    np.testing.assert_array_equal([i.n_evals for i in seen], r.traces.n_evals[:3])
    t = r.traces.wall_time
    assert np.all(np.diff(t) > 0) and t[0] > 0


def test_fused_cost_finite_nowhere_is_the_same_one_line_error():
    with pytest.raises(FricjaxError) as err:
        run_chains_fused(
            jax.random.key(0),
            lambda x: jnp.nan * x[0],
            LOWER,
            UPPER,
            METHOD,
            SETTINGS,
            3,
            source="cfg.toml",
        )
    assert str(err.value).startswith("cfg.toml: cost: not finite at any of the 512 points")


@pytest.mark.parametrize("schedule", ["geometric", "boltzmann", "cauchy", "reheat"])
def test_relative_temperatures_are_the_schedule_at_t0_1(schedule):
    s = dataclasses.replace(SETTINGS, schedule=schedule, max_levels=120, reheat_every=7)
    expected = np.asarray(temperature(schedule, 1.0, np.arange(120), s))
    np.testing.assert_allclose(relative_temperatures(s), expected, rtol=1e-14, atol=0)


def test_propose_and_step_with_cost_split_a_step_around_its_evaluation():
    algorithm = METHODS["csaa"]
    s = SETTINGS
    x0 = jnp.asarray(CENTRE + 0.5)
    state = algorithm.init(jax.random.key(4), x0, _cost(x0), LOWER, UPPER, s)
    whole = algorithm.step(state, _cost, 1.0, LOWER, UPPER, s)
    x_new = propose(algorithm, state, 1.0, LOWER, UPPER, s)
    split = step_with_cost(algorithm, state, _cost(x_new), 1.0, LOWER, UPPER, s)
    for a, b in zip(whole, split, strict=True):
        if jnp.issubdtype(a.dtype, jax.dtypes.prng_key):
            a, b = jax.random.key_data(a), jax.random.key_data(b)
        np.testing.assert_array_equal(a, b)
    assert int(whole.n_evals) == int(state.n_evals) + 1
