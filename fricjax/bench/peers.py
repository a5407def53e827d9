"""fricjax against peer optimisers on the same problem, in the same process.

Peers minimise the same cost (seed eq. 11 over the preprocessed paper twin, [N²]) over the
same box, from :class:`fricjax.bench.seed_cost.SeedCost` — a vectorised numpy transcription
checked equal to fricjax's cost to 1e-9 relative at random points:

* scipy ``differential_evolution`` (vectorised, ``updating="deferred"``, popsize 15 ×
  d members): ``polish=False`` with ``tol=0`` (runs until the target or a cap, so its
  own convergence test cannot stop it short of the target), on the numpy cost and on the
  jitted, vmapped JAX cost; and scipy's default path, ``tol=0.01`` then ``polish=True``
  (L-BFGS-B from the best member), on the numpy cost;
* scipy ``dual_annealing`` (single-point numpy cost; its local search is L-BFGS-B);
* pycma's IPOP-CMA-ES (``cma.fmin2``, 9 restarts with doubling population), on the box
  scaled to the unit cube, σ0 = 0.3, numpy cost over each population (optional: the
  ``bench`` extra);
* fricjax: ``identify`` with the config's settings, once with the 26-D CSAA search and
  once with the separable (variable-projection) search when present, each with and
  without the Levenberg–Marquardt refiner.

Target: cost ≤ (1 + ``success_rel``)·c*, c* the best cost any run found, every run's end
point refined by fricjax's LM. A provisional c* (fricjax CSAA + LM, seed 0) lets peers stop
once they reach it; success and time to target are recomputed against the final c* from
each run's history of improvements. Every peer run stops at ``time_cap`` seconds or
``max_evals`` evaluations. Times are warm: each jitted function runs once before timing.
Reported: success rates, median time and evaluations to target (failures count as ∞, so
a median is finite only when at least half the seeds succeeded) and fricjax/peer ratios of
median time to target.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import jax.numpy as jnp
import numpy as np

from fricjax.bench.convergence import separable_available
from fricjax.bench.machine import Machine, describe
from fricjax.bench.seed_cost import SeedCost, batch_fn
from fricjax.errors import FricjaxError, where
from fricjax.identify import IdentifySettings, identify
from fricjax.io.atomic import write_text_atomic
from fricjax.problem import Problem
from fricjax.refine import refine_many
from fricjax.report.tables import fmt, format_table

#: fricjax paths whose median time to target is divided by each method's.
REFERENCES: tuple[str, ...] = ("fricjax csaa + LM", "fricjax separable + LM")


@dataclass(frozen=True)
class PeerSettings:
    """Seeds and caps of the peer benchmark.

    ``seeds``: seeds of the fricjax runs and the fast peers (DE without polish);
    ``slow_seeds``: seeds of the slow peers (DE with polish, dual annealing, CMA-ES);
    ``time_cap`` [s] and ``max_evals``: per peer run; ``success_rel``: target tolerance;
    ``de_popsize``: scipy's popsize multiplier; ``separable``: include fricjax's separable
    path (None = when available); ``peers``: which peers to run (names as in the report).
    """

    seeds: int = 10
    slow_seeds: int = 3
    time_cap: float = 60.0
    max_evals: int = 2_000_000
    success_rel: float = 0.01
    de_popsize: int = 15
    separable: bool | None = None
    peers: tuple[str, ...] = (
        "DE numpy",
        "DE jax",
        "DE numpy + polish",
        "dual_annealing numpy",
        "CMA-ES numpy",
    )

    def validate(self) -> PeerSettings:
        src = "bench peers"
        for name in ("seeds", "slow_seeds", "max_evals", "de_popsize"):
            if getattr(self, name) < 1:
                raise FricjaxError(f"{where(src, name)}: must be ≥ 1, got {getattr(self, name)}")
        if not self.time_cap > 0:
            raise FricjaxError(f"{where(src, 'time_cap')}: must be > 0, got {self.time_cap}")
        unknown = sorted(set(self.peers) - set(PeerSettings().peers))
        if unknown:
            raise FricjaxError(f"{where(src, 'peers')}: unknown peer {unknown[0]!r}")
        return self


@dataclass
class Run:
    """One run: ``history`` of improvements ``(seconds, evaluations, best cost)``, the
    final best point ``x [d]``/``cost``, ``evals``, ``seconds``; ``refined``: the cost
    after fricjax's LM from ``x`` (filled in later); ``note``: why it stopped."""

    seed: int
    history: list[tuple[float, int, float]]
    x: np.ndarray
    cost: float
    evals: int
    seconds: float
    note: str = ""
    refined: float = math.nan

    def first_hit(self, threshold: float) -> tuple[float, int] | None:
        for t, n, c in self.history:
            if c <= threshold:
                return t, n
        return None


@dataclass
class Method:
    """All runs of one method; ``per_eval``: what one evaluation is (for the report)."""

    name: str
    runs: list[Run]
    per_eval: str = "full cost"
    compile_time: float = 0.0


class _Stop(Exception):
    """Raised inside an objective to end a peer run (target, time cap or evaluation cap)."""


class Tracker:
    """Wraps a batched cost ``f(X [P, d]) -> [P]``: counts evaluations, keeps the best
    point, logs improvements and raises :class:`_Stop` at the target or a cap."""

    def __init__(
        self,
        fn: Callable[[np.ndarray], np.ndarray],
        *,
        target: float | None,
        time_cap: float,
        max_evals: int,
        d: int,
    ) -> None:
        self.fn, self.target, self.time_cap, self.max_evals = fn, target, time_cap, max_evals
        self.evals, self.best, self.best_x = 0, math.inf, np.full(d, np.nan)
        self.history: list[tuple[float, int, float]] = []
        self.note = "optimiser finished"
        self.start = time.perf_counter()

    def batch(self, x: np.ndarray) -> np.ndarray:
        """``X [P, d] -> costs [P]``."""
        self._check()
        x = np.asarray(x, dtype=np.float64).reshape(-1, self.best_x.size)
        costs = np.asarray(self.fn(x), dtype=np.float64)
        self.evals += x.shape[0]
        finite = np.where(np.isfinite(costs), costs, np.inf)
        k = int(np.argmin(finite))
        if finite[k] < self.best:
            self.best, self.best_x = float(finite[k]), x[k].copy()
            self.history.append((time.perf_counter() - self.start, self.evals, self.best))
        if self.target is not None and self.best <= self.target:
            self.note = "reached the provisional target"
            raise _Stop
        return costs

    def single(self, x: np.ndarray) -> float:
        return float(self.batch(np.asarray(x)[None, :])[0])

    def _check(self) -> None:
        if time.perf_counter() - self.start > self.time_cap:
            self.note = f"time cap {self.time_cap:g} s"
            raise _Stop
        if self.evals >= self.max_evals:
            self.note = f"evaluation cap {self.max_evals}"
            raise _Stop

    def result(self, seed: int) -> Run:
        return Run(
            seed=seed,
            history=list(self.history),
            x=self.best_x.copy(),
            cost=self.best,
            evals=self.evals,
            seconds=time.perf_counter() - self.start,
            note=self.note,
        )


def check_seed_cost(problem: Problem, sc: SeedCost, n: int = 64, seed: int = 0) -> float:
    """Largest relative difference between the numpy cost and fricjax's at ``n`` points
    uniform in the box; raises :class:`FricjaxError` above 1e-9."""
    import jax

    lo, hi = problem.spec.lower, problem.spec.upper
    x = lo + np.random.default_rng(seed).random((n, lo.size)) * (hi - lo)
    ref = np.asarray(jax.jit(jax.vmap(problem.cost_fn))(jnp.asarray(x)))
    worst = float(np.max(np.abs(sc.numpy(x) / ref - 1.0)))
    if not worst <= 1e-9:
        raise FricjaxError(
            f"{where('bench', 'seed_cost')}: numpy cost differs from fricjax's by {worst:.3g}"
        )
    return worst


# ----------------------------------------------------------------------------------------
# Peers
# ----------------------------------------------------------------------------------------


def _de(
    fn: Callable[[np.ndarray], np.ndarray],
    lo: np.ndarray,
    hi: np.ndarray,
    seed: int,
    ps: PeerSettings,
    target: float | None,
    polish: bool,
) -> Run:
    from scipy.optimize import differential_evolution

    tr = Tracker(fn, target=target, time_cap=ps.time_cap, max_evals=ps.max_evals, d=lo.size)

    def objective(x: np.ndarray) -> np.ndarray | float:
        x = np.asarray(x)
        # vectorised calls pass [d, S]; the polish passes one point [d]
        return tr.single(x) if x.ndim == 1 else tr.batch(x.T)

    pop = ps.de_popsize * lo.size
    try:
        differential_evolution(
            objective,
            list(zip(lo, hi, strict=True)),
            popsize=ps.de_popsize,
            maxiter=max(ps.max_evals // pop, 1),
            tol=0.01 if polish else 0.0,
            vectorized=True,
            updating="deferred",
            polish=polish,
            seed=seed,
        )
    except _Stop:
        pass
    return tr.result(seed)


def _dual_annealing(
    fn: Callable[[np.ndarray], np.ndarray],
    lo: np.ndarray,
    hi: np.ndarray,
    seed: int,
    ps: PeerSettings,
    target: float | None,
) -> Run:
    from scipy.optimize import dual_annealing

    tr = Tracker(fn, target=target, time_cap=ps.time_cap, max_evals=ps.max_evals, d=lo.size)
    try:
        dual_annealing(tr.single, list(zip(lo, hi, strict=True)), maxfun=ps.max_evals, seed=seed)
    except _Stop:
        pass
    return tr.result(seed)


def _cma(
    fn: Callable[[np.ndarray], np.ndarray],
    lo: np.ndarray,
    hi: np.ndarray,
    seed: int,
    ps: PeerSettings,
    target: float | None,
) -> Run:
    import cma

    span = hi - lo
    tr = Tracker(
        lambda z: fn(lo + np.clip(z, 0.0, 1.0) * span),
        target=target,
        time_cap=ps.time_cap,
        max_evals=ps.max_evals,
        d=lo.size,
    )
    x0 = np.random.default_rng(seed).random(lo.size)
    options = {"bounds": [0.0, 1.0], "seed": seed + 1, "verbose": -9, "maxfevals": ps.max_evals}
    try:
        cma.fmin2(
            None,
            x0,
            0.3,
            options,
            restarts=9,
            incpopsize=2,
            parallel_objective=lambda zs: list(tr.batch(np.asarray(zs))),
        )
    except _Stop:
        pass
    run = tr.result(seed)
    run.x = lo + np.clip(run.x, 0.0, 1.0) * span
    return run


def _fricjax_runs(
    problem: Problem,
    tables: Mapping[str, Any],
    source: str,
    seeds: Sequence[int],
    separable: bool,
) -> tuple[Method, Method, float]:
    """``identify`` with the config's settings, the search space forced (26-D or
    separable): (without LM, from the traces; with LM), and the warm-up time."""
    overrides: dict[str, Any] = {"separable": separable} if separable_available() else {}
    overrides["objective"] = "equation"  # the seed's procedure, as its peers run it

    def settings(seed: int) -> IdentifySettings:
        return IdentifySettings.from_tables(
            tables, source=source, overrides={**overrides, "seed": seed}
        )

    t0 = time.perf_counter()
    identify(problem, settings(seeds[0]))
    warm = time.perf_counter() - t0
    raw, refined = [], []
    for seed in seeds:
        run = identify(problem, settings(seed))
        tr = run.traces
        best = np.minimum.accumulate(np.min(np.asarray(tr["best_cost"]), axis=1))
        hist = [
            (float(t), int(n), float(c))
            for t, n, c in zip(tr["wall_time"], tr["n_evals"], best, strict=True)
        ]
        k = int(np.argmin(run.chain_cost))
        evals = int(tr["n_evals"][-1]) if len(tr["n_evals"]) else 0
        search_time = float(tr["wall_time"][-1]) if len(tr["wall_time"]) else 0.0
        raw.append(
            Run(
                seed,
                hist,
                np.asarray(run.chain_x[k]),
                float(run.chain_cost[k]),
                evals,
                search_time,
                f"{run.attrs['levels']} levels",
            )
        )
        total = float(run.attrs["wall_time"])
        refined.append(
            Run(
                seed,
                [*hist, (total, evals, float(run.cost))],
                np.asarray(run.value),
                float(run.cost),
                evals,
                total,
                "search + LM",
            )
        )
    name = "fricjax separable" if separable else "fricjax csaa"
    per = (
        "projected cost (chains over the nonlinear parameters, linear ones solved exactly)"
        if separable
        else "full cost, jitted and vmapped over the chains; 26-D search with the config's "
        "[search]/[anneal] settings (early stop included)"
    )
    return (
        Method(name, raw, per, warm),
        Method(f"{name} + LM", refined, per + "; LM evaluations not counted", warm),
        warm,
    )


@dataclass
class PeerResult:
    settings: PeerSettings
    methods: dict[str, Method]
    best_cost: float
    provisional: float
    seed_cost_error: float
    n_samples: int
    d: int
    skipped: dict[str, str] = field(default_factory=dict)
    wall: float = 0.0
    default_path: str = "26-D"


def run_peers(
    problem: Problem,
    tables: Mapping[str, Any],
    settings: PeerSettings | None = None,
    *,
    source: str = "config",
    on_run: Callable[[str, Run], None] | None = None,
) -> PeerResult:
    """Run fricjax and every peer (module docstring); refine every end point with LM."""
    ps = (settings or PeerSettings()).validate()
    start = time.perf_counter()
    sc = SeedCost.from_problem(problem)
    err = check_seed_cost(problem, sc)
    lo, hi = problem.spec.lower, problem.spec.upper
    seeds = list(range(ps.seeds))
    slow = list(range(ps.slow_seeds))
    methods: dict[str, Method] = {}
    skipped: dict[str, str] = {}

    def report(name: str, runs: list[Run]) -> None:
        if on_run is not None:
            for r in runs:
                on_run(name, r)

    raw, refined, _ = _fricjax_runs(problem, tables, source, seeds, separable=False)
    methods[raw.name], methods[refined.name] = raw, refined
    report(refined.name, refined.runs)
    use_sep = separable_available() if ps.separable is None else ps.separable
    if use_sep:
        sraw, sref, _ = _fricjax_runs(problem, tables, source, seeds, separable=True)
        methods[sraw.name], methods[sref.name] = sraw, sref
        report(sref.name, sref.runs)
    provisional = min(r.cost for m in methods.values() for r in m.runs)
    target = (1 + ps.success_rel) * provisional

    jax_batch = batch_fn(sc)
    t0 = time.perf_counter()
    jax_batch(np.tile(lo, (ps.de_popsize * lo.size, 1))).block_until_ready()
    jax_compile = time.perf_counter() - t0

    def numpy_batch(x: np.ndarray) -> np.ndarray:
        return sc.numpy(x)

    def jax_eval(x: np.ndarray) -> np.ndarray:
        return np.asarray(jax_batch(jnp.asarray(x)))

    pop = ps.de_popsize * lo.size
    plan: list[tuple[str, list[int], Callable[[int], Run], str, float]] = [
        (
            "DE numpy",
            seeds,
            lambda s: _de(numpy_batch, lo, hi, s, ps, target, False),
            f"numpy cost over the population ({pop} points a call); tol = 0, no polish",
            0.0,
        ),
        (
            "DE jax",
            seeds,
            lambda s: _de(jax_eval, lo, hi, s, ps, target, False),
            f"jitted vmapped JAX cost over the population ({pop} points a call); tol = 0, "
            f"no polish; compile {jax_compile:.2f} s excluded",
            jax_compile,
        ),
        (
            "DE numpy + polish",
            slow,
            lambda s: _de(numpy_batch, lo, hi, s, ps, None, True),
            "numpy cost; scipy's defaults (tol = 0.01) then L-BFGS-B polish (one point a "
            "call, finite-difference gradient); runs to its own end, not stopped at the target",
            0.0,
        ),
        (
            "dual_annealing numpy",
            slow,
            lambda s: _dual_annealing(numpy_batch, lo, hi, s, ps, target),
            "numpy cost, one point a call (dual annealing is sequential; its local search "
            "is L-BFGS-B with finite differences)",
            0.0,
        ),
        (
            "CMA-ES numpy",
            slow,
            lambda s: _cma(numpy_batch, lo, hi, s, ps, target),
            "numpy cost over each population; IPOP restarts (9, population ×2 each), unit "
            "cube, σ0 = 0.3",
            0.0,
        ),
    ]
    for name, which, fn, what, compile_time in plan:
        if name not in ps.peers:
            continue
        if name.startswith("CMA"):
            try:
                import cma  # noqa: F401
            except ImportError:
                skipped[name] = "pycma not installed (pip install 'fricjax[bench]')"
                continue
        runs = []
        for s in which:
            runs.append(fn(s))
            report(name, runs[-1:])
        methods[name] = Method(name, runs, what, compile_time)

    # every end point polished by fricjax's LM: c* is the best cost any method led to
    ends = [(m, r) for m in methods.values() for r in m.runs if np.all(np.isfinite(r.x))]
    starts = jnp.asarray(np.stack([np.clip(r.x, lo, hi) for _, r in ends]))
    polished = np.asarray(refine_many(problem.residual_fn, starts, lo, hi).cost_after)
    for (_, r), c in zip(ends, polished, strict=True):
        r.refined = float(min(c, r.cost)) if np.isfinite(c) else r.cost
    best = min(min(r.refined, r.cost) for _, r in ends)
    default = IdentifySettings.from_tables(tables, source=source)
    return PeerResult(
        default_path="separable" if getattr(default, "separable", False) else "26-D CSAA",
        settings=ps,
        methods=methods,
        best_cost=best,
        provisional=provisional,
        seed_cost_error=err,
        n_samples=problem.n,
        d=lo.size,
        skipped=skipped,
        wall=time.perf_counter() - start,
    )


# ----------------------------------------------------------------------------------------
# Statistics and report
# ----------------------------------------------------------------------------------------


def _median_inf(values: Sequence[float]) -> float:
    """Median with failures as +∞ (finite only if at least half are finite)."""
    return float(np.median(np.asarray(values, dtype=float))) if values else math.inf


def summarise_peers(result: PeerResult) -> dict[str, dict[str, Any]]:
    """Per method: seeds, success rate, median time/evaluations to target (∞ = failed),
    median final cost / c*, evaluations per second, and the fricjax/peer time ratio."""
    target = (1 + result.settings.success_rel) * result.best_cost
    out: dict[str, dict[str, Any]] = {}
    for name, m in result.methods.items():
        hits = [r.first_hit(target) for r in m.runs]
        times = [h[0] if h else math.inf for h in hits]
        evals = [float(h[1]) if h else math.inf for h in hits]
        out[name] = {
            "seeds": len(m.runs),
            "success": float(np.mean([h is not None for h in hits])),
            "time": _median_inf(times),
            "evals": _median_inf(evals),
            "final": float(np.median([r.cost for r in m.runs])) / result.best_cost,
            "final_lm": float(np.median([r.refined for r in m.runs])) / result.best_cost,
            "evals_per_s": float(np.median([r.evals / max(r.seconds, 1e-12) for r in m.runs])),
            "seconds": float(np.median([r.seconds for r in m.runs])),
            "notes": sorted({r.note for r in m.runs}),
            "per_eval": m.per_eval,
        }
    return out


def _t(value: float, digits: int = 3) -> str:
    return "> cap" if math.isinf(value) else fmt(value, digits)


def _ratio(ref: float, peer: float, cap: float) -> str:
    if math.isinf(peer):
        return f"< {fmt(ref / cap, 3)}" if math.isfinite(ref) else "—"
    if math.isinf(ref):
        return "—"
    return fmt(ref / peer, 3)


def _references(s: Mapping[str, Mapping[str, Any]]) -> dict[str, float]:
    return {ref: s[ref]["time"] for ref in REFERENCES if ref in s}


def peers_table(result: PeerResult) -> str:
    """Plain-text table (printed by the CLI)."""
    s = summarise_peers(result)
    refs = _references(s)
    rows = [
        (
            name,
            str(row["seeds"]),
            f"{100 * row['success']:.0f}%",
            _t(row["time"]),
            _t(row["evals"], 6),
            fmt(row["final"], 6),
            f"{row['evals_per_s']:.0f}",
            *(_ratio(t, row["time"], result.settings.time_cap) for t in refs.values()),
        )
        for name, row in s.items()
    ]
    header = ("method", "seeds", "success", "time [s]", "evals", "final/c*", "evals/s")
    return format_table(rows, (*header, *(f"{r.removeprefix('fricjax ')}/peer" for r in refs)))


def peers_markdown(result: PeerResult, machine: Machine) -> str:
    ps = result.settings
    s = summarise_peers(result)
    refs = _references(s)
    c_star = result.best_cost
    lines = [
        "# fricjax against peer optimisers on the paper twin",
        "",
        "Generated by `fricjax bench peers` (`benchmarks/peers.py`); every number is "
        "measured in this run, all methods in one process on the same cost, box and target.",
        "",
        "## Machine",
        "",
        machine.markdown(),
        "",
        "## Problem and target",
        "",
        f"- {result.d} free parameters, {result.n_samples} samples; cost = seed eq. 11 [N²]; "
        "peers use the vectorised numpy transcription of `fricjax.bench.seed_cost` "
        f"(largest relative difference from fricjax's cost at 64 random points: "
        f"{result.seed_cost_error:.2g})",
        f"- c* = **{fmt(c_star, 10)} N²**: best cost of any run, every end point polished "
        f"by fricjax's LM; target = (1 + {ps.success_rel:g})·c* = "
        f"{fmt((1 + ps.success_rel) * c_star, 8)} N² (provisional c* used for early stops: "
        f"{fmt(result.provisional, 10)} N²)",
        f"- seeds: {ps.seeds} for fricjax, DE numpy and DE jax; {ps.slow_seeds} for the slow "
        "peers (DE + polish, dual annealing, CMA-ES); each peer run capped at "
        f"{ps.time_cap:g} s and {ps.max_evals} evaluations",
        "- times are warm (every jitted function ran once first) and include everything "
        "the method does (fricjax: sampling, annealing, LM; DE: its own bookkeeping)",
        "- median time/evaluations to target count a failed run as ∞: '> cap' means fewer "
        "than half the seeds reached the target",
        "",
        "## Results",
        "",
        "| method | seeds | success | median time to target [s] | median evals to target "
        "| median final / c* | final after LM / c* | evals/s | "
        + " | ".join(f"time {r} / method's" for r in refs)
        + " |",
        "|---" * (8 + len(refs)) + "|",
    ]
    for name, row in s.items():
        ratios = " | ".join(_ratio(t, row["time"], ps.time_cap) for t in refs.values())
        lines.append(
            f"| {name} | {row['seeds']} | {100 * row['success']:.0f} % | {_t(row['time'])} | "
            f"{_t(row['evals'], 6)} | {fmt(row['final'], 6)} | {fmt(row['final_lm'], 6)} | "
            f"{row['evals_per_s']:.0f} | {ratios} |"
        )
    lines += [
        "",
        "The ratio columns are fricjax/peer ratios: median time to target of the fricjax "
        "path (26-D CSAA + LM; separable + LM) divided by the method's; below 1 fricjax is "
        "faster; '< x' when the method's median is beyond the cap. "
        f"`fricjax identify` with this config runs the {result.default_path} path by "
        "default. 'final after LM': each run's end point polished by fricjax's LM (shows "
        "whether the run ended in the right basin).",
        "",
        "What one evaluation is and why runs stopped:",
        "",
    ]
    for name, row in s.items():
        lines.append(f"- {name}: {row['per_eval']}; stopped: {'; '.join(row['notes'])}")
    for name, why in result.skipped.items():
        lines.append(f"- {name}: skipped, {why}")
    lines += [
        "",
        f"Whole benchmark: {result.wall:.0f} s.",
        "",
    ]
    return "\n".join(lines)


def peers_benchmark(
    recording: str | Path,
    config: str | Path,
    *,
    out_dir: str | Path = "benchmarks/results",
    settings: PeerSettings | None = None,
    on_run: Callable[[str, Run], None] | None = None,
) -> tuple[PeerResult, Path]:
    """:func:`run_peers` on a recording + config; writes ``peers.md`` atomically."""
    from fricjax.api import load

    settings = (settings or PeerSettings()).validate()
    machine = describe(("fricjax", "jax", "jaxlib", "numpy", "scipy", "cma"))
    _, cfg, problem = load(recording, config)
    result = run_peers(
        problem, cfg.tables, settings, source=cfg.source or str(config), on_run=on_run
    )
    path = write_text_atomic(Path(out_dir) / "peers.md", peers_markdown(result, machine))
    return result, path
