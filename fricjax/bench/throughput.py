"""Raw throughput of the seed cost (eq. 11) on this CPU: evaluations per second against the
batch (chain) size, float64 and float32, JAX against numpy, compile time, memory, one
against two host devices, the YNN fusion flag, and the fraction of the CPU's peak.

Variants, all over the same preprocessed recording and the same batch ``θ [C, d]`` drawn
uniformly in the box:

* ``fricjax f64``: ``jit(vmap(problem.cost_fn))`` — what the chains evaluate;
* ``jax f64`` / ``jax f32``: the hand transcription :class:`fricjax.bench.seed_cost.SeedCost`
  jitted and vmapped, data and θ cast to the dtype (``jax_enable_x64`` stays on). fricjax's
  own model cannot simply be cast: its drive term starts from float64 zeros, which promotes
  a float32 θ back to float64;
* ``numpy f64``: the same transcription in numpy, vectorised over the batch;
* ``numpy f64, one θ per call``: the same numpy cost called on one point at a time from a
  Python loop (``point_calls`` points), the way scipy's optimisers call a cost; a single
  rate, independent of C.

Device and flag experiments run in subprocesses (``XLA_FLAGS`` is read once, when JAX
starts): ``--xla_force_host_platform_device_count=2`` with the batch sharded over a 1-D mesh
(``NamedSharding``), and ``FRICJAX_XLA_DEFAULTS=0`` (fricjax then leaves out
``--xla_cpu_experimental_ynn_fusion_type=``).

FLOPs of one evaluation come from XLA's ``cost_analysis()`` of the compiled batch and from
a hand count per sample n (N harmonics): ``ωt`` 1, ``2cos`` 1, per harmonic 4 (two products
and two sums of eq. 4) + 4 (the two Chebyshev recurrences), Stribeck 8 (|v|/vs, δ·log, the
level, sgn·level, Fv·v, sum), residual 3, square and sum 2, i.e. ``(15 + 8N)·n`` FLOPs plus
``5·n`` transcendentals (sin, cos, log, exp, exp). On a uniform time grid ``[J, R]``
(:class:`fricjax.model.term.TimeGrid`, what fricjax's own cost uses) ``cos/sin ωt`` come
by angle addition from ``J + R`` pairs: ``ωt`` 1 becomes the complex product 6, i.e.
``(20 + 8N)·n + (J + R)`` FLOPs and ``3·n + 2·(J + R)`` transcendentals; with δ fixed
at 1 (the paper config: seed eq. 2) the Stribeck power ``exp(δ·log r)`` is skipped
(:func:`fricjax.model.friction.stribeck_curve`), ``(18 + 8N)·n + (J + R)`` FLOPs and
``n + 2·(J + R)`` transcendentals (the ``[J, R]`` layout of
:class:`fricjax.problem.GridCost` also evaluates its ``J·R − n`` padding samples, masked
out). XLA's count also holds the identity products that keep the
J + R sines (and, samples in order, the phasors) out of the per-sample loop
(:func:`fricjax.model.drive.phasor`), copies rather than arithmetic
(:func:`barrier_flops`). The fraction of peak divides the measured FLOP rate (hand count)
by :attr:`fricjax.bench.machine.Machine.peak_flops`.
"""

from __future__ import annotations

import json
import math
import os
import resource
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from fricjax.bench.machine import Machine, describe
from fricjax.bench.seed_cost import SeedCost
from fricjax.errors import FricjaxError, where
from fricjax.io.atomic import write_text_atomic
from fricjax.problem import GridCost, Problem
from fricjax.report.tables import fmt, format_table

CHAIN_COUNTS: tuple[int, ...] = (1, 4, 16, 64, 256, 1024, 4096)
VARIANTS: tuple[str, ...] = ("fricjax f64", "jax f64", "jax f32", "numpy f64")
#: The numpy cost called on one θ at a time (one rate, whatever the batch size).
POINT_VARIANT = "numpy f64, 1 θ/call"
_YNN = "--xla_cpu_experimental_ynn_fusion_type="


@dataclass(frozen=True)
class ThroughputSettings:
    """``chains``: batch sizes; ``min_time`` [s]: timing per measurement (fastest of
    ``repeats`` slots); ``sub_chains``: batch sizes of the subprocess experiments; ``subprocess``:
    run them at all; ``point_calls``: points of the one-θ-per-call numpy loop."""

    chains: tuple[int, ...] = CHAIN_COUNTS
    min_time: float = 2.0
    repeats: int = 10
    sub_chains: tuple[int, ...] = (64, 1024, 4096)
    subprocess: bool = True
    point_calls: int = 200

    def validate(self) -> ThroughputSettings:
        src = "bench throughput"
        if not self.chains or min(self.chains) < 1:
            raise FricjaxError(f"{where(src, 'chains')}: need batch sizes ≥ 1")
        if self.repeats < 1 or not self.min_time > 0:
            raise FricjaxError(f"{where(src, 'repeats')}: need repeats ≥ 1 and min_time > 0")
        if self.point_calls < 1:
            raise FricjaxError(f"{where(src, 'point_calls')}: need at least 1 call")
        return self


def per_call_seconds(fn: Callable[[Any], Any], x: Any, *, min_time: float, repeats: int) -> float:
    """Fastest over ``repeats`` slots of the mean time of one call [s], each slot at least
    ``min_time / repeats`` long; ``fn`` runs once first (warm). The minimum, because other
    processes on the machine can only ever slow a slot down."""
    jax.block_until_ready(fn(x))
    slot = min_time / repeats
    samples = []
    for _ in range(repeats):
        n, start = 0, time.perf_counter()
        while True:
            jax.block_until_ready(fn(x))
            n += 1
            elapsed = time.perf_counter() - start
            if elapsed >= slot:
                break
        samples.append(elapsed / n)
    return float(np.min(samples))


def hand_flops(
    n_samples: int,
    harmonics: int,
    grid: tuple[int, int] | None = None,
    delta_one: bool = False,
) -> tuple[int, int]:
    """(FLOPs, transcendentals) of one evaluation by the count of the module docstring;
    ``grid`` = (J, R) of the time grid when the drive uses angle addition (None: plain);
    ``delta_one``: δ fixed at 1, the Stribeck power skipped (grid path only: the hand
    transcription always evaluates it)."""
    if grid is None:
        return (15 + 8 * harmonics) * n_samples, 5 * n_samples
    j, r = grid
    if delta_one:
        return (18 + 8 * harmonics) * n_samples + j + r, n_samples + 2 * (j + r)
    return (20 + 8 * harmonics) * n_samples + j + r, 3 * n_samples + 2 * (j + r)


def delta_fixed_at_one(problem: Problem) -> bool:
    """Whether the Stribeck exponent δ is a fixed 1 (then the cost skips its power)."""
    spec = problem.spec
    return "delta" in spec and not spec["delta"].free and float(spec["delta"].init) == 1.0


def barrier_flops(grid: tuple[int, int] | None, in_order: bool) -> int:
    """FLOPs XLA counts for the identity products of :func:`fricjax.model.drive.phasor`,
    per evaluation: ``[J + R, 2] @ I₂`` always, and ``[2J, R] @ I_R`` when the samples stay
    in order (``in_order``: a :class:`fricjax.problem.Cost`, not a ``GridCost``); 0 without
    a grid."""
    if grid is None:
        return 0
    j, r = grid
    return 8 * (j + r) + (4 * r * j * r if in_order else 0)


def grid_shape(problem: Problem) -> tuple[int, int] | None:
    """(J, R) of the problem's time grid, or None when its cost evaluates sin/cos per sample."""
    grid = problem.grid
    return None if grid is None else (int(grid.outer.shape[0]), int(grid.inner.shape[0]))


def describe_layout(problem: Problem) -> str:
    """One phrase: how ``problem.cost_fn`` evaluates the drive's sin/cos."""
    grid = grid_shape(problem)
    if grid is None:
        return "sin/cos per sample (t is not a uniform grid)"
    where = (
        "samples in the [J, R] layout (`GridCost`)"
        if isinstance(problem.cost_fn, GridCost)
        else "samples in order"
    )
    return (
        f"time grid J × R = {grid[0]} × {grid[1]}: sin/cos by angle addition from "
        f"{grid[0] + grid[1]} pairs, {where}"
    )


def numpy_point_rate(sc: SeedCost, points: np.ndarray, *, repeats: int) -> float:
    """Evaluations/s of the numpy cost called on one θ at a time from a Python loop over
    ``points [P, d]`` (how scipy's optimisers call a cost): the fastest of ``repeats`` loops,
    after one warm call."""
    sc.numpy(points[0])
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        for theta in points:
            sc.numpy(theta)
        best = min(best, time.perf_counter() - start)
    return points.shape[0] / best


def _batch(problem: Problem, c: int, seed: int = 0) -> np.ndarray:
    lo, hi = problem.spec.lower, problem.spec.upper
    return lo + np.random.default_rng(seed).random((c, lo.size)) * (hi - lo)


def _functions(problem: Problem, sc: SeedCost) -> dict[str, Callable[[Any], Any]]:
    return {
        "fricjax f64": jax.jit(jax.vmap(problem.cost_fn)),
        "jax f64": jax.jit(jax.vmap(sc.jax_fn(jnp.float64))),
        "jax f32": jax.jit(jax.vmap(sc.jax_fn(jnp.float32))),
        "numpy f64": sc.numpy,
    }


def _cost_analysis(compiled: Any) -> dict[str, float]:
    ca = compiled.cost_analysis()
    if isinstance(ca, list | tuple):
        ca = ca[0] if ca else {}
    return {k: float(v) for k, v in (ca or {}).items() if k in ("flops", "transcendentals")}


@dataclass
class ThroughputResult:
    """Measured numbers: ``rate[variant][C]`` evaluations/s, ``numpy_point`` evaluations/s
    of the numpy cost one θ per call, ``compile[variant][C]`` [s], ``f32_error`` (largest
    relative error of the float32 cost), ``flops`` (XLA's cost analysis per evaluation),
    ``hand`` (hand count per evaluation), ``grid`` ((J, R) of fricjax's time grid or None),
    ``barrier`` (XLA FLOPs of its identity products), ``layout`` (how fricjax's cost
    evaluates sin/cos), ``maxrss_mib``, ``device_memory`` (JAX's memory stats or None),
    ``sub`` (subprocess experiments)."""

    settings: ThroughputSettings
    n_samples: int
    d: int
    harmonics: int
    rate: dict[str, dict[int, float]]
    compile: dict[str, dict[int, float]]
    f32_error: float
    flops: dict[str, float]
    hand: tuple[int, int]
    maxrss_mib: float
    device_memory: dict[str, Any] | None
    numpy_point: float = math.nan
    grid: tuple[int, int] | None = None
    barrier: int = 0
    layout: str = ""
    sub: dict[str, dict[int, float]] = field(default_factory=dict)
    sub_notes: list[str] = field(default_factory=list)


def run_throughput(
    problem: Problem,
    settings: ThroughputSettings | None = None,
    *,
    recording: str | Path | None = None,
    config: str | Path | None = None,
    on_line: Callable[[str], None] | None = None,
) -> ThroughputResult:
    """Measure everything of the module docstring; the subprocess experiments need the
    ``recording`` and ``config`` paths (they rebuild the problem in a fresh process)."""
    ts = (settings or ThroughputSettings()).validate()
    sc = SeedCost.from_problem(problem)
    fns = _functions(problem, sc)
    rate: dict[str, dict[int, float]] = {v: {} for v in VARIANTS}
    comp: dict[str, dict[int, float]] = {v: {} for v in VARIANTS if v != "numpy f64"}
    flops: dict[str, float] = {}
    for c in ts.chains:
        x64 = jnp.asarray(_batch(problem, c))
        for name in VARIANTS:
            x = x64.astype(jnp.float32) if name.endswith("f32") else x64
            fn = fns[name]
            if name != "numpy f64":
                start = time.perf_counter()
                compiled = jax.jit(jax.vmap(_unwrap(name, problem, sc))).lower(x).compile()
                comp[name][c] = time.perf_counter() - start
                if name == "fricjax f64" and c == max(ts.chains):
                    flops = {k: v / c for k, v in _cost_analysis(compiled).items()}
                fn = compiled
            else:
                x = np.asarray(x)
            dt = per_call_seconds(fn, x, min_time=ts.min_time, repeats=ts.repeats)
            rate[name][c] = c / dt
        if on_line is not None:
            on_line(
                f"C={c:5d}: " + ", ".join(f"{name} {rate[name][c]:9.0f}/s" for name in VARIANTS)
            )
    points = _batch(problem, ts.point_calls, seed=2)
    numpy_point = numpy_point_rate(sc, points, repeats=max(1, min(ts.repeats, 5)))
    if on_line is not None:
        on_line(f"numpy f64, one θ per call ({ts.point_calls} calls): {numpy_point:9.0f}/s")
    x = _batch(problem, 256, seed=1)
    ref = np.asarray(fns["fricjax f64"](jnp.asarray(x)))
    f32 = np.asarray(fns["jax f32"](jnp.asarray(x, dtype=jnp.float32)), dtype=np.float64)
    f32_error = float(np.max(np.abs(f32 / ref - 1.0)))
    try:
        stats = jax.devices()[0].memory_stats()
    except Exception:  # backends without memory stats raise instead of returning None
        stats = None
    result = ThroughputResult(
        settings=ts,
        n_samples=problem.n,
        d=problem.spec.n_free,
        harmonics=sc.harmonics,
        rate=rate,
        compile=comp,
        f32_error=f32_error,
        flops=flops,
        hand=hand_flops(problem.n, sc.harmonics, grid_shape(problem), delta_fixed_at_one(problem)),
        maxrss_mib=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        device_memory=dict(stats) if stats else None,
        numpy_point=numpy_point,
        grid=grid_shape(problem),
        barrier=barrier_flops(grid_shape(problem), not isinstance(problem.cost_fn, GridCost)),
        layout=describe_layout(problem),
    )
    if ts.subprocess and recording is not None and config is not None:
        _subprocess_experiments(result, recording, config, on_line)
    return result


def _unwrap(name: str, problem: Problem, sc: SeedCost) -> Callable[[Any], Any]:
    if name == "fricjax f64":
        return problem.cost_fn
    return sc.jax_fn(jnp.float32 if name.endswith("f32") else jnp.float64)


# ----------------------------------------------------------------------------------------
# Subprocess experiments
# ----------------------------------------------------------------------------------------

_EXPERIMENTS: dict[str, dict[str, str]] = {
    "1 device (fricjax defaults, YNN fusion off)": {"devices": "1", "defaults": "1"},
    "2 host devices, batch sharded": {"devices": "2", "defaults": "1"},
    "1 device, FRICJAX_XLA_DEFAULTS=0 (XLA's YNN fusion on)": {"devices": "1", "defaults": "0"},
}


def _subprocess_experiments(
    result: ThroughputResult,
    recording: str | Path,
    config: str | Path,
    on_line: Callable[[str], None] | None,
) -> None:
    ts = result.settings
    for label, exp in _EXPERIMENTS.items():
        env = dict(os.environ)
        flags = [f for f in env.get("XLA_FLAGS", "").split() if "ynn_fusion" not in f]
        flags = [f for f in flags if "force_host_platform_device_count" not in f]
        flags.append(f"--xla_force_host_platform_device_count={exp['devices']}")
        env["XLA_FLAGS"] = " ".join(flags)
        env["FRICJAX_XLA_DEFAULTS"] = exp["defaults"]
        request = {
            "recording": str(recording),
            "config": str(config),
            "chains": list(ts.sub_chains),
            "min_time": ts.min_time,
            "repeats": ts.repeats,
        }
        code = "from fricjax.bench.throughput import worker; worker()"
        proc = subprocess.run(
            [sys.executable, "-c", code, json.dumps(request)],
            env=env,
            capture_output=True,
            text=True,
            check=False,
        )
        if proc.returncode != 0:
            tail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
            result.sub_notes.append(f"{label}: failed ({tail})")
            continue
        reply = json.loads(proc.stdout.strip().splitlines()[-1])
        result.sub[label] = {int(k): float(v) for k, v in reply["rate"].items()}
        result.sub_notes.append(
            f"{label}: {reply['n_devices']} device(s), XLA_FLAGS=`{reply['xla_flags']}`"
        )
        if on_line is not None:
            on_line(
                f"{label}: " + ", ".join(f"C={c} {r:.0f}/s" for c, r in result.sub[label].items())
            )


def worker() -> None:
    """Subprocess entry: rate of ``jit(vmap(cost))`` with the batch sharded over all
    devices (1-D mesh); prints one JSON line ``{"rate": {C: evals/s}, ...}``."""
    request = json.loads(sys.argv[-1])
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    from fricjax.api import load

    _, _, problem = load(request["recording"], request["config"])
    devices = jax.devices()
    mesh = Mesh(np.asarray(devices), ("chains",))
    sharded = NamedSharding(mesh, PartitionSpec("chains"))
    fn = jax.jit(jax.vmap(problem.cost_fn), in_shardings=sharded, out_shardings=sharded)
    rate = {}
    for c in request["chains"]:
        pad = -(-c // len(devices)) * len(devices)
        x = jax.device_put(jnp.asarray(_batch(problem, pad)), sharded)
        dt = per_call_seconds(fn, x, min_time=request["min_time"], repeats=request["repeats"])
        rate[c] = pad / dt
    print(
        json.dumps(
            {"rate": rate, "n_devices": len(devices), "xla_flags": os.environ.get("XLA_FLAGS")}
        )
    )


# ----------------------------------------------------------------------------------------
# Report
# ----------------------------------------------------------------------------------------


def peak_ratios(result: ThroughputResult) -> tuple[float, float, float]:
    """(fricjax f64 peak rate, its ratio to numpy one θ per call, its ratio to the
    vectorised numpy peak rate) — peaks over the measured batch sizes."""
    best = max(result.rate["fricjax f64"].values())
    numpy_peak = max(result.rate["numpy f64"].values())
    return best, best / result.numpy_point, best / numpy_peak


def throughput_table(result: ThroughputResult) -> str:
    """Plain-text table of evaluations/s and the ratios against numpy and float64, then the
    numpy one-θ-per-call rate and the peak ratios."""
    rows = []
    for c in result.settings.chains:
        r = {v: result.rate[v][c] for v in VARIANTS}
        rows.append(
            (
                str(c),
                *(f"{r[v]:.0f}" for v in VARIANTS),
                f"{result.numpy_point:.0f}",
                fmt(r["fricjax f64"] / r["numpy f64"], 3),
                fmt(r["jax f32"] / r["jax f64"], 3),
            )
        )
    best, per_point, vectorised = peak_ratios(result)
    table = format_table(
        rows, ("chains", *VARIANTS, POINT_VARIANT, "fricjax/numpy", "f32/f64 (jax)")
    )
    return (
        f"{table}\nfricjax f64 peak {best:.0f}/s = {fmt(per_point, 3)}x numpy one θ per call, "
        f"{fmt(vectorised, 3)}x vectorised numpy (peak)"
    )


def throughput_markdown(result: ThroughputResult, machine: Machine) -> str:
    ts = result.settings
    best_c = max(ts.chains, key=lambda c: result.rate["fricjax f64"][c])
    best = result.rate["fricjax f64"][best_c]
    hand_f, hand_t = result.hand
    peak = machine.peak_flops
    lines = [
        "# Cost throughput on this CPU",
        "",
        "Generated by `fricjax bench throughput` (`benchmarks/throughput.py`); every number "
        "is measured in this run. Ratios are within this run.",
        "",
        "## Machine",
        "",
        machine.markdown(),
        "",
        f"Problem: the paper twin, {result.n_samples} samples, {result.d} free parameters, "
        f"N = {result.harmonics} harmonics. Batch θ [C, d] uniform in the box. Evaluations/s "
        f"= C / (time of one call, the fastest of {ts.repeats} slots of "
        f"{ts.min_time / ts.repeats:g} s each), after one warm call.",
        "",
        "## Evaluations per second against the number of chains",
        "",
        "| chains | "
        + " | ".join(VARIANTS)
        + f" | {POINT_VARIANT} | fricjax / numpy | f32 / f64 (jax) |",
        "|---" * (len(VARIANTS) + 4) + "|",
    ]
    for c in ts.chains:
        r = {v: result.rate[v][c] for v in VARIANTS}
        lines.append(
            f"| {c} | "
            + " | ".join(f"{r[v]:.0f}" for v in VARIANTS)
            + f" | {result.numpy_point:.0f}"
            + f" | {fmt(r['fricjax f64'] / r['numpy f64'], 3)}"
            + f" | {fmt(r['jax f32'] / r['jax f64'], 3)} |"
        )
    _, per_point, vectorised = peak_ratios(result)
    numpy_peak = max(result.rate["numpy f64"].values())
    grid = f"fricjax's cost: {result.layout}" if result.layout else "fricjax's cost"
    lines += [
        "",
        f"**fricjax f64 at its peak ({best:.0f}/s, C = {best_c}) is {fmt(per_point, 3)}× the "
        f"numpy cost called one θ per call ({result.numpy_point:.0f}/s) and "
        f"{fmt(vectorised, 3)}× the vectorised numpy cost at its peak ({numpy_peak:.0f}/s).**",
        "",
        "`fricjax f64` = `jit(vmap(problem.cost_fn))`; " + grid + "; `jax f64/f32` = the "
        "hand transcription (`fricjax.bench.seed_cost`) at that dtype; `numpy f64` = the same "
        "transcription in numpy, vectorised over the batch; "
        f"`{POINT_VARIANT}` = that numpy cost called on one θ at a time from a Python loop "
        f"over {ts.point_calls} points (how scipy's optimisers call a cost; the same for "
        "every C). float32 accuracy: largest relative error of the float32 "
        f"cost at 256 random points {result.f32_error:.2g}: cost differences below that "
        "fraction are invisible in float32 (annealing compares costs of nearby points, LM "
        "their derivatives), which is why fricjax runs in float64.",
        "",
        "## JIT compile time [s] (lower + compile, per batch size)",
        "",
        "| chains | " + " | ".join(result.compile) + " |",
        "|---" * (len(result.compile) + 1) + "|",
    ]
    for c in ts.chains:
        lines.append(
            f"| {c} | " + " | ".join(f"{result.compile[v][c]:.2f}" for v in result.compile) + " |"
        )
    dm = (
        ", ".join(f"{k} {v}" for k, v in result.device_memory.items())
        if result.device_memory
        else "not available (the CPU client reports no memory stats)"
    )
    lines += [
        "",
        "## Memory",
        "",
        f"- peak resident set of this process (ru_maxrss): {result.maxrss_mib:.0f} MiB",
        f"- JAX device memory stats: {dm}",
        f"- data: {result.n_samples} samples × 5 float64 arrays = "
        f"{result.n_samples * 5 * 8 / 1024:.1f} KiB; a batch of 4096 θ = "
        f"{4096 * result.d * 8 / 2**20:.2f} MiB",
        "",
    ]
    if result.sub:
        labels = list(result.sub)
        lines += [
            "## Host devices and the YNN fusion flag (subprocesses, `fricjax f64`)",
            "",
            "| chains | " + " | ".join(labels) + " |",
            "|---" * (len(labels) + 1) + "|",
        ]
        for c in ts.sub_chains:
            lines.append(
                f"| {c} | "
                + " | ".join(f"{result.sub[lb].get(c, float('nan')):.0f}" for lb in labels)
                + " |"
            )
        base = labels[0]
        lines += [""]
        for lb in labels[1:]:
            ratios = ", ".join(
                f"C={c}: {fmt(result.sub[lb][c] / result.sub[base][c], 3)}"
                for c in ts.sub_chains
                if c in result.sub[lb] and c in result.sub[base]
            )
            lines.append(f"- {lb} / {base}: {ratios}")
    if result.sub_notes:
        lines += ["", *[f"- {n}" for n in result.sub_notes]]
    xla = result.flops
    lines += [
        "",
        "## FLOPs and the fraction of peak",
        "",
        f"- XLA cost analysis of the compiled batch (C = {max(ts.chains)}), per evaluation: "
        + (
            f"{xla.get('flops', float('nan')):.0f} FLOPs, "
            f"{xla.get('transcendentals', float('nan')):.0f} transcendentals"
            if xla
            else "not available"
        ),
        f"- hand count per evaluation: {_hand_formula(result)} = "
        f"{hand_f} FLOPs + {hand_t} transcendentals (module docstring of "
        "`fricjax.bench.throughput`)"
        + (
            f"; XLA's count adds {result.barrier} FLOPs of identity products "
            "(copies that keep the grid's sines out of the per-sample loop)"
            if result.grid
            else ""
        ),
        f"- best measured rate: {best:.0f} evaluations/s at C = {best_c} → "
        f"{best * hand_f / 1e9:.2f} GFLOP/s by the hand count"
        + (
            f" ({best * xla['flops'] / 1e9:.2f} GFLOP/s by XLA's count)" if xla.get("flops") else ""
        ),
        f"- nominal float64 peak {peak / 1e9:.1f} GFLOP/s → "
        + (
            f"**{100 * best * hand_f / peak:.2f} %** of peak counting a transcendental as one "
            f"FLOP, {100 * best * (hand_f + 20 * hand_t) / peak:.2f} % counting each as ~20 "
            "(a vectorised polynomial evaluation)"
            if peak > 0
            else "unknown (no clock rate in /proc/cpuinfo)"
        ),
        "",
        f"The FMA units are not what limits the cost: one evaluation is a chain of "
        f"~{round(hand_f / result.n_samples)} elementwise operations and "
        f"{round(hand_t / result.n_samples)} transcendentals per sample over "
        f"{result.n_samples} samples, then a sum. The rate peaks at C = {best_c}; "
        f"at C = {max(ts.chains)} it is {fmt(result.rate['fricjax f64'][max(ts.chains)] / best, 3)}"
        "× the peak rate, each intermediate [C, n] array being "
        f"{max(ts.chains) * result.n_samples * 8 / 2**20:.1f} MiB (beyond the per-core "
        "caches).",
        "",
    ]
    return "\n".join(lines)


def _hand_formula(result: ThroughputResult) -> str:
    n, h = result.n_samples, result.harmonics
    if result.grid is None:
        return f"(15 + 8·{h})·{n}"
    j, r = result.grid
    return f"(20 + 8·{h})·{n} + ({j} + {r})"


def throughput_benchmark(
    recording: str | Path,
    config: str | Path,
    *,
    out_dir: str | Path = "benchmarks/results",
    settings: ThroughputSettings | None = None,
    on_line: Callable[[str], None] | None = None,
) -> tuple[ThroughputResult, Path]:
    """:func:`run_throughput` on a recording + config; writes ``throughput.md`` atomically."""
    from fricjax.api import load

    machine = describe()
    _, _, problem = load(recording, config)
    result = run_throughput(problem, settings, recording=recording, config=config, on_line=on_line)
    path = write_text_atomic(Path(out_dir) / "throughput.md", throughput_markdown(result, machine))
    return result, path
