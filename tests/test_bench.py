"""Benchmarks (fricjax.bench): the convergence study on a tiny budget, the hand-written
seed cost against fricjax's, peak-FLOP arithmetic and the peer tracker."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fricjax.bench.convergence import (
    ConvergenceResult,
    ConvergenceSettings,
    convergence_markdown,
    convergence_table,
    first_reach,
    parameter_errors,
    plot_convergence,
    run_convergence,
    summarise,
)
from fricjax.bench.machine import describe, peak_flops, simd_width
from fricjax.bench.peers import Tracker, _Stop
from fricjax.bench.seed_cost import SeedCost
from fricjax.bench.throughput import (
    VARIANTS,
    ThroughputResult,
    ThroughputSettings,
    barrier_flops,
    delta_fixed_at_one,
    grid_shape,
    hand_flops,
    numpy_point_rate,
    peak_ratios,
    throughput_markdown,
    throughput_table,
)
from fricjax.data.twin import read_truth
from fricjax.errors import FricjaxError
from fricjax.problem import Cost, GridCost
from fricjax.search import dsaa
from fricjax.search.annealing import AnnealSettings

TINY = ConvergenceSettings(
    methods=("csaa", "dsaa"),
    seeds=2,
    chains=4,
    steps_per_level=5,
    levels=6,
    refine=False,
    separable=False,
)


@pytest.fixture(scope="module")
def tiny(twin_problem, paper_config, twin_path: Path) -> ConvergenceResult:
    return run_convergence(
        twin_problem,
        paper_config.tables,
        TINY,
        source=paper_config.source,
        truth=read_truth(twin_path),
    )


def test_every_method_gets_the_same_evaluation_budget(tiny: ConvergenceResult, paper_config):
    samples = AnnealSettings.from_dict(paper_config.table("anneal")).n_temperature_samples
    # Metropolis steps + the eq. 15 box sample (samples + start candidates) + start costs
    expected = TINY.chains * TINY.steps_per_level * TINY.levels + samples + 2 * TINY.chains
    budgets = {label: [int(r.n_evals[-1]) for r in mr.runs] for label, mr in tiny.methods.items()}
    assert set(budgets) == set(TINY.methods)
    assert all(b == [expected] * TINY.seeds for b in budgets.values())


def test_best_cost_traces_are_monotone_and_end_at_the_raw_result(tiny: ConvergenceResult):
    for mr in tiny.methods.values():
        for r in mr.runs:
            assert r.best.shape == (TINY.levels,)
            assert np.all(np.diff(r.best) <= 0.0)
            assert np.all(np.diff(r.n_evals) == TINY.chains * TINY.steps_per_level)
            assert np.all(np.diff(r.wall_time) >= 0.0)
            assert r.best[-1] == r.raw_cost
            # without the refiner the reported point is the raw one
            assert r.cost == r.raw_cost


def test_success_rates_and_reference_cost(tiny: ConvergenceResult):
    assert tiny.best_cost == min(r.cost for mr in tiny.methods.values() for r in mr.runs)
    assert tiny.truth_cost is not None and tiny.truth_cost > 0
    for row in summarise(tiny).values():
        rates = [v for k, v in row.items() if k.startswith("success_")]
        assert len(rates) == 4
        assert all(0.0 <= v <= 1.0 for v in rates)
        q = row["raw_q"]
        assert q[0] <= q[1] <= q[2]
    # the run that defines c* succeeds against c* by construction
    best = summarise(tiny)[tiny.best_label]
    assert best["success_best_raw"] >= 1.0 / TINY.seeds


def test_dsaa_points_lie_on_the_grid_and_the_floor_is_consistent(tiny: ConvergenceResult):
    lo, hi = jnp.asarray(tiny.lower), jnp.asarray(tiny.upper)
    bits = int(tiny.floor["n_bits"])
    for r in tiny.methods["dsaa"].runs:
        grid = dsaa.from_index(dsaa.to_index(jnp.asarray(r.raw_x), lo, hi, bits), lo, hi, bits)
        np.testing.assert_allclose(np.asarray(grid), r.raw_x, rtol=1e-14)
    # greedy descent starts at the snapped point and only moves downhill
    assert tiny.floor["grid_descent"] <= tiny.floor["snapped"]
    assert tiny.floor["dsaa_best"] <= tiny.floor["dsaa_median"]


def test_report_has_the_seed_tables_and_plots_are_written(tiny: ConvergenceResult, tmp_path):
    text = convergence_markdown(tiny, describe(), images={"evals": "e.png", "time": "t.png"})
    for published in ("59209", "58322", "58335", "3749.9", "1118.9", "0.499"):
        assert published in text
    assert "Table 4. Error mean square" in text
    summary = convergence_table(tiny).splitlines()
    assert [line.split()[0] for line in summary[2:]] == list(TINY.methods)
    for key in ("n_evals", "wall_time"):
        path = plot_convergence(tiny, x_key=key, path=tmp_path / f"{key}.png")
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["n_evals.png", "wall_time.png"]


def test_parameter_errors_are_zero_at_the_truth_and_phases_wrap():
    truth = {
        "F0": 400.0,
        "Fc": 30.0,
        "Fv": 3000.0,
        "Fs": 190.0,
        "vs": 0.1,
        "omega": 31.4,
        "Fp_1": 600.0,
        "phi_1": 0.5,
    }
    names = list(truth)
    x = np.array([truth[n] for n in names])
    assert parameter_errors(names, x, truth) == {
        "table1": 0.0,
        "amplitudes": 0.0,
        "phases": 0.0,
        "omega": 0.0,
    }
    x[names.index("phi_1")] += 2 * math.pi
    x[names.index("Fp_1")] *= 1.1
    err = parameter_errors(names, x, truth)
    assert err["phases"] < 1e-12
    assert err["amplitudes"] == pytest.approx(0.1)


def test_first_reach_returns_the_first_level_at_or_below_the_threshold():
    best = np.array([5.0, 3.0, 2.0, 2.0, 1.0])
    xs = np.array([10, 20, 30, 40, 50])
    assert first_reach(best, xs, 2.0) == 30.0
    assert first_reach(best, xs, 0.5) is None


def test_unknown_method_is_a_one_line_error():
    with pytest.raises(FricjaxError, match=r"bench convergence: methods: unknown method 'sa'"):
        ConvergenceSettings(methods=("sa",)).validate()


def test_seed_cost_equals_fricjax_cost(twin_problem):
    sc = SeedCost.from_problem(twin_problem)
    lo, hi = twin_problem.spec.lower, twin_problem.spec.upper
    x = lo + np.random.default_rng(3).random((16, lo.size)) * (hi - lo)
    ref = np.asarray(jax.jit(jax.vmap(twin_problem.cost_fn))(jnp.asarray(x)))
    np.testing.assert_allclose(sc.numpy(x), ref, rtol=1e-9)
    np.testing.assert_allclose(sc.numpy(x[0]), ref[0], rtol=1e-9)
    f64 = jax.jit(jax.vmap(sc.jax_fn(jnp.float64)))(jnp.asarray(x))
    np.testing.assert_allclose(np.asarray(f64), ref, rtol=1e-9)
    f32 = jax.jit(jax.vmap(sc.jax_fn(jnp.float32)))(jnp.asarray(x))
    assert f32.dtype == jnp.float32
    # float32 keeps ~7 digits of a sum of 232 squares, no more
    np.testing.assert_allclose(np.asarray(f32, dtype=np.float64), ref, rtol=1e-4)


def test_peak_flops_follows_the_vector_width():
    assert simd_width({"sse2"}) == 2
    assert simd_width({"avx", "avx2", "fma"}) == 4
    assert simd_width({"avx2", "fma", "avx512f"}) == 8
    assert peak_flops(2, 2.5e9, {"avx512f", "fma"}) == 2 * 2.5e9 * 2 * 8 * 2
    assert peak_flops(1, 1e9, {"avx"}) == 1e9 * 2 * 4


def test_tracker_logs_improvements_and_stops_at_the_target():
    tr = Tracker(lambda x: np.sum(x**2, axis=1), target=1.0, time_cap=60.0, max_evals=100, d=2)
    tr.batch(np.array([[3.0, 0.0], [2.0, 0.0]]))
    with pytest.raises(_Stop):
        tr.batch(np.array([[5.0, 0.0], [0.5, 0.0], [0.1, 0.0]]))
    run = tr.result(seed=0)
    assert run.evals == 5
    assert [h[1] for h in run.history] == [2, 5]
    assert [h[2] for h in run.history] == pytest.approx([4.0, 0.01])
    assert run.first_hit(1.0)[1] == 5
    assert run.first_hit(0.001) is None
    np.testing.assert_array_equal(run.x, [0.1, 0.0])
    assert run.note == "reached the provisional target"


def _xla_counts(fn, d: int, theta0) -> tuple[float, float]:
    x = jnp.asarray(np.tile(theta0, (4, 1)))
    analysis = jax.jit(jax.vmap(fn)).lower(x).compile().cost_analysis()
    analysis = analysis[0] if isinstance(analysis, list | tuple) else analysis
    return analysis["flops"] / 4, analysis["transcendentals"] / 4


def test_hand_flop_count_agrees_with_xla_cost_analysis(twin_problem):
    pb = twin_problem
    sc = SeedCost.from_problem(pb)
    grid = grid_shape(pb)
    assert grid == (15, 16)
    # fricjax's cost: angle addition on the [J, R] grid layout
    assert isinstance(pb.cost_fn, GridCost)
    # configs/paper.toml fixes δ = 1: the Stribeck power is skipped
    assert delta_fixed_at_one(pb)
    flops, transcendentals = hand_flops(pb.n, sc.harmonics, grid, delta_one=True)
    assert flops == (18 + 8 * 10) * pb.n + 15 + 16
    assert transcendentals == pb.n + 2 * (15 + 16)
    xla_f, xla_t = _xla_counts(pb.cost_fn, pb.spec.n_free, pb.spec.init)
    assert xla_f == pytest.approx(flops + barrier_flops(grid, in_order=False), rel=0.1)
    assert xla_t == pytest.approx(transcendentals, rel=0.1)
    # samples in order (what a stateful model gets): one more identity product per sample
    xla_f, xla_t = _xla_counts(Cost(pb.residual_fn), pb.spec.n_free, pb.spec.init)
    assert xla_f == pytest.approx(flops + barrier_flops(grid, in_order=True), rel=0.1)
    assert xla_t == pytest.approx(transcendentals, rel=0.1)
    # the hand transcription keeps one sine and one cosine per sample
    plain_f, plain_t = hand_flops(pb.n, sc.harmonics)
    assert plain_f == (15 + 8 * 10) * pb.n and plain_t == 5 * pb.n
    xla_f, xla_t = _xla_counts(sc.jax_fn(jnp.float64), pb.spec.n_free, pb.spec.init)
    assert xla_f == pytest.approx(plain_f, rel=0.1)
    assert xla_t == pytest.approx(plain_t, rel=0.1)


def test_numpy_one_point_per_call_rate_and_the_report_ratios(twin_problem):
    sc = SeedCost.from_problem(twin_problem)
    lo, hi = twin_problem.spec.lower, twin_problem.spec.upper
    points = lo + np.random.default_rng(4).random((5, lo.size)) * (hi - lo)
    assert 0 < numpy_point_rate(sc, points, repeats=1) < math.inf
    ts = ThroughputSettings(chains=(1, 64), subprocess=False, point_calls=200)
    rate = {
        "fricjax f64": {1: 2.0e4, 64: 3.0e5},
        "jax f64": {1: 1.0e4, 64: 2.0e5},
        "jax f32": {1: 2.0e4, 64: 4.0e5},
        "numpy f64": {1: 5.0e3, 64: 6.0e4},
    }
    result = ThroughputResult(
        settings=ts,
        n_samples=232,
        d=26,
        harmonics=10,
        rate=rate,
        compile={v: {1: 0.5, 64: 0.6} for v in VARIANTS if v != "numpy f64"},
        f32_error=1e-6,
        flops={},
        hand=hand_flops(232, 10, (15, 16)),
        maxrss_mib=100.0,
        device_memory=None,
        numpy_point=1.0e4,
        grid=(15, 16),
        barrier=barrier_flops((15, 16), in_order=False),
        layout="time grid J × R = 15 × 16",
    )
    assert peak_ratios(result) == (3.0e5, 30.0, 5.0)
    md = throughput_markdown(result, describe())
    assert "| numpy f64, 1 θ/call |" in md
    assert "| 64 | 300000 | 200000 | 400000 | 60000 | 10000 | 5 | 2 |" in md
    assert "is 30× the numpy cost called one θ per call (10000/s)" in md
    assert "5× the vectorised numpy cost at its peak (60000/s)" in md
    text = throughput_table(result)
    assert text.splitlines()[-1] == (
        "fricjax f64 peak 300000/s = 30x numpy one θ per call, 5x vectorised numpy (peak)"
    )


def test_cli_rejects_an_unknown_method_in_one_line():
    out = subprocess.run(
        [sys.executable, "-m", "fricjax.cli", "bench", "convergence", "--methods", "csaa,sa"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 2
    assert out.stderr.strip() == (
        "error: bench convergence: methods: unknown method 'sa' (known: csaa, csaa-gauss, "
        "dsaa, dsaa-gray, rdsa)"
    )
