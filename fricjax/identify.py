"""Identification = search (parallel annealing chains) → refine (optimistix LM) → uncertainty.

This is the seed paper's procedure (sections 3–4) as one API call::

    problem = build_problem(recording, config)
    run = identify(problem, IdentifySettings(method="csaa", chains=64, seed=0))
    run.params, run.ems, run.std

The search minimises the equation-error cost (seed eq. 11) over the box of the config; the
best ``refine_top`` chain end points are polished together (vmapped Levenberg–Marquardt) and
the best polished point is kept. With ``separable=True`` the chains search only the
nonlinear parameters (ω, vs for the seed model) on the variable-projection cost of
:mod:`fricjax.search.separable` (the linear ones solved exactly at every step); their end
points are expanded to full parameter vectors, which the refiner then polishes as above.
Gauss–Newton standard deviations, correlations and identifiability flags follow, plus a
census of the distinct minima the chains ended in. With ``objective = "simulation"`` the
equation-error estimate is then polished by output error with multiple shooting
(:mod:`fricjax.output_error`), which compares simulated and recorded positions instead of
forces computed from a twice-differentiated position.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from concurrent.futures import TimeoutError as FuturesTimeout
from dataclasses import dataclass, field, fields, replace
from typing import Any

import equinox as eqx
import jax
import numpy as np
from jaxtyping import Array

from fricjax.errors import FricjaxError, where
from fricjax.io.results import RunResult
from fricjax.limits import check_chains
from fricjax.output_error import OutputErrorSettings, fit_output_error_batch
from fricjax.problem import Problem
from fricjax.refine import (
    GAUSS_NEWTON,
    RefineSettings,
    Uncertainty,
    cluster_minima,
    compile_refine,
    refine,
    refine_many,
    uncertainty_at,
    value_and_jacobian,
)
from fricjax.residual_noise import residual_noise
from fricjax.search.annealing import AnnealSettings
from fricjax.search.chains import (
    METHODS,
    LevelInfo,
    SearchResult,
    Traces,
    run_chains,
    run_chains_fused,
)
from fricjax.search.separable import Separable, separate

SEPARABLE_TABLE = "separable_budget"
# How an error names a value given on the command line instead of in the config file.
CLI_SOURCE = "command line"
SEARCH_KEYS = (
    "method",
    "chains",
    "seed",
    "refine_top",
    "refine",
    "separable",
    "objective",
    SEPARABLE_TABLE,
)
#: ``equation``: seed eq. 11 throughout; ``simulation``: then output error with multiple
#: shooting (:mod:`fricjax.output_error`) from the equation-error estimate; ``auto``: the
#: output-error fit only where the equation error is not noise (:data:`MISFIT_LIMIT`).
OBJECTIVES = ("auto", "equation", "simulation")
#: Cost over the cost of the record's noise alone (the dispersion φ of the equation-error
#: fit; E_OE per residual entry of the output-error fit, in σ_x²) above which the residual
#: is not noise: at 4 its rms is twice the noise's, so at least three quarters of the
#: misfit is the model's, not the sensor's. φ's own sampling spread is √(2/n_eff), a few
#: percent on any record long enough to identify from, so 4 is never reached by chance. An
#: equation-error estimate past it is biased (stick and slip put the noise-free a in the
#: residual where the sliding law is wrong) or its model lacks physics; ``auto`` then
#: refines by output error, which compares positions and has no such bias.
MISFIT_LIMIT = 4.0
OUTPUT_ERROR_TABLE = "output_error"


@dataclass(frozen=True)
class IdentifySettings:
    """What ``identify`` does; the ``[search]``, ``[anneal]``, ``[refine]`` config tables.

    Attributes:
        method: search algorithm (``csaa``, ``csaa-gauss``, ``dsaa``, ``dsaa-gray``, ``rdsa``).
        chains: number of parallel chains (restarts are just more chains).
        seed: integer seed; the same seed and settings reproduce a run bit for bit.
        refine_top: how many of the best chain end points the refiner polishes (vmapped).
        refine: whether to run the refiner at all.
        separable: search the nonlinear parameters only, the linear ones solved exactly
            (variable projection, :mod:`fricjax.search.separable`); needs every model term
            to declare a linear basis.
        anneal: annealing control (eq. 15–16, schedules, stopping rule, move sizes).
        refiner: Levenberg–Marquardt settings.
        objective: ``"auto"`` (default), ``"equation"`` (seed eq. 11) or
            ``"simulation"``: after the equation-error search and polish, an output-error
            fit with multiple shooting (:func:`fricjax.output_error.fit_output_error`)
            starts from that estimate, and the run reports its values, cost and σ
            (``[search].objective``). ``auto`` runs that fit only where the equation
            error's dispersion exceeds :data:`MISFIT_LIMIT`, and records why.
        output_error: settings of that fit (the ``[output_error]`` table).
        fast_compile: compile the programs that run once per call (the separable search,
            the Levenberg–Marquardt polish, the Jacobian of the uncertainty) with
            :data:`fricjax.search.fast_compile.FAST_COMPILE`: a cold ``fricjax identify``
            of the paper twin then spends ~2-2.7 s compiling instead of ~7-14 s (2 shared
            CPU cores, measured), and a warm run (compiled code reused: later calls in one
            process, or the persistent cache of the CLI) ~0.2 s longer (~0.34 s instead of
            ~0.16 s on a loaded machine). Off by default (library calls, sweeps and
            benchmarks run many identifications per process); the one-shot entry point
            :func:`fricjax.api.identify_recording` (``fricjax identify``) turns it on. The
            26-D search is never compiled so (its programs run ~10⁵ cost evaluations). Not
            a config key.
    """

    method: str = "csaa"
    chains: int = 64
    seed: int = 0
    refine_top: int = 4
    refine: bool = True
    separable: bool = False
    anneal: AnnealSettings = field(default_factory=AnnealSettings)
    refiner: RefineSettings = field(default_factory=RefineSettings)
    objective: str = "auto"
    output_error: OutputErrorSettings = field(default_factory=OutputErrorSettings)
    fast_compile: bool = False

    @classmethod
    def from_tables(
        cls,
        tables: Mapping[str, Mapping[str, Any]],
        *,
        source: str = "config",
        overrides: Mapping[str, Any] | None = None,
    ) -> IdentifySettings:
        """Build from config tables, then apply CLI ``overrides`` (None values ignored).

        Override keys are ``IdentifySettings`` fields or ``AnnealSettings`` fields
        (e.g. ``alpha``, ``schedule``, ``steps_per_level``, ``separable``, ``objective``);
        the ``[output_error]`` table holds the output-error settings. When the search
        is separable, the ``[search.separable_budget]`` table (``chains``, ``refine_top``
        and any ``[anneal]`` key) overrides ``[search]``/``[anneal]``; CLI overrides come
        last.
        """
        search = dict(tables.get("search", {}))
        for key in search:
            if key not in SEARCH_KEYS:
                raise FricjaxError(
                    f"{where(source, f'[search].{key}')}: unknown key "
                    f"(known: {', '.join(SEARCH_KEYS)})"
                )
        anneal_table = dict(tables.get("anneal", {}))
        anneal_names = {f.name for f in fields(AnnealSettings)}
        cli = {k: v for k, v in (overrides or {}).items() if v is not None}
        for key in cli:
            if key not in SEARCH_KEYS and key not in anneal_names:
                raise FricjaxError(f"override {key!r}: unknown setting")
        if cli.get("objective", OBJECTIVES[0]) not in OBJECTIVES:
            raise FricjaxError(
                f"--objective: must be one of {', '.join(OBJECTIVES)}, got {cli['objective']!r}"
            )
        separable = cli.get("separable", search.get("separable", cls.separable))
        if not isinstance(separable, bool | np.bool_):
            raise FricjaxError(
                f"{where(source, '[search].separable')}: must be true or false, got {separable!r}"
            )
        # The separable search has a few dimensions instead of 26: its own, far smaller
        # budget, layered over [anneal] and [search] (CLI overrides still win).
        extra = search.pop(SEPARABLE_TABLE, {})
        # [search]'s own values are checked before the separable budget may replace them:
        # a bad one is refused, never silently dropped
        for key in ("chains", "refine_top"):
            if key in search:
                _count(search[key], where(source, f"[search].{key}"))
        if separable and extra:
            AnnealSettings.from_dict(anneal_table, source=source)
        if not isinstance(extra, Mapping):
            raise FricjaxError(
                f"{where(source, f'[search].{SEPARABLE_TABLE}')}: must be a table of chains, "
                "refine_top and [anneal] keys"
            )
        if separable:
            for key, value in extra.items():
                if key in ("chains", "refine_top"):
                    search[key] = _count(value, where(source, f"[search.{SEPARABLE_TABLE}].{key}"))
                elif key in anneal_names:
                    anneal_table[key] = value
                else:
                    raise FricjaxError(
                        f"{where(source, f'[search.{SEPARABLE_TABLE}].{key}')}: unknown key "
                        "(known: chains, refine_top and the [anneal] keys)"
                    )
        # The config's own [anneal] is checked before the command line's values join it, so
        # that an error names where the bad value came from: the file, or the command line.
        anneal = AnnealSettings.from_dict(anneal_table, source=source)
        cli_anneal = {k: v for k, v in cli.items() if k not in SEARCH_KEYS}
        if cli_anneal:
            anneal = AnnealSettings.from_dict({**anneal_table, **cli_anneal}, source=CLI_SOURCE)
        search.update({k: v for k, v in cli.items() if k in SEARCH_KEYS})

        def blame(key: str) -> str:
            return where(CLI_SOURCE, f"--{key}") if key in cli else where(source, f"[search].{key}")

        method = str(search.get("method", cls.method))
        if method not in METHODS:
            raise FricjaxError(
                f"{blame('method')}: unknown method {method!r} (known: {', '.join(METHODS)})"
            )
        chains = _count(search.get("chains", cls.chains), blame("chains"))
        top = _count(search.get("refine_top", cls.refine_top), blame("refine_top"))
        seed = search.get("seed", cls.seed)
        if not _is_int(seed):
            raise FricjaxError(f"{blame('seed')}: must be an integer, got {seed!r}")
        refine_on = search.get("refine", True)
        if not isinstance(refine_on, bool | np.bool_):
            raise FricjaxError(f"{blame('refine')}: must be true or false, got {refine_on!r}")
        objective = search.get("objective", cls.objective)
        if objective not in OBJECTIVES:
            raise FricjaxError(
                f"{where(source, '[search].objective')}: must be one of "
                f"{', '.join(OBJECTIVES)}, got {objective!r}"
            )
        return cls(
            method=method,
            chains=chains,
            seed=int(seed),
            refine_top=top,
            refine=bool(refine_on),
            separable=bool(separable),
            anneal=anneal,
            refiner=RefineSettings.from_dict(dict(tables.get("refine", {})), source=source),
            objective=str(objective),
            output_error=OutputErrorSettings.from_dict(
                tables.get(OUTPUT_ERROR_TABLE, {}), source=source
            ),
        )


def _is_int(value: object) -> bool:
    return isinstance(value, int | np.integer) and not isinstance(value, bool | np.bool_)


def _count(value: object, label: str) -> int:
    """A count setting (chains, refine_top): an integer >= 1, else one line naming it."""
    if not _is_int(value):
        raise FricjaxError(f"{label}: must be an integer, got {value!r}")
    if value < 1:  # type: ignore[operator]
        raise FricjaxError(f"{label}: must be >= 1, got {value!r}")
    return int(value)  # type: ignore[arg-type]


def identify(
    problem: Problem,
    settings: IdentifySettings | None = None,
    *,
    on_level: Callable[[LevelInfo], None] | None = None,
    label: str | None = None,
) -> RunResult:
    """Search, refine and qualify the parameters of ``problem`` (see module docstring)."""
    settings = settings or IdentifySettings()
    spec = problem.spec
    check_chains(settings.chains, problem.n, spec.n_free, settings.anneal.max_levels, "identify")
    lower, upper = spec.lower, spec.upper
    start = time.perf_counter()
    sep = separate(problem) if settings.separable else None
    residual = _Residual(problem.residual_fn)
    polish = _compile_polish_ahead(problem, residual, settings, sep is not None)
    if sep is None:
        search = run_chains(
            prng_key(settings.seed),
            problem.cost_fn,
            lower,
            upper,
            method=settings.method,
            settings=settings.anneal,
            n_chains=settings.chains,
            on_level=on_level,
            source=spec.source,
        )
    else:
        # one compiled program: Ctrl-C reaches Python only through _interruptible, and
        # with nothing found yet it ends the run (nothing to keep)
        search = _interruptible(
            lambda: _separable_search(sep, settings, on_level), "fricjax-search"
        )
    best_x, cost_search = np.asarray(search.best_x), float(search.best_cost)
    best_cost = cost_search
    interrupted, refined = bool(search.interrupted), False
    if settings.refine and not interrupted:
        # Ctrl-C while the refiner runs keeps the search's best, unrefined, as Ctrl-C
        # during the search does: the user asked to stop, not to lose the annealing.
        try:
            best_x, best_cost = _interruptible(
                lambda: _polish(problem, search, settings, polish), "fricjax-polish"
            )
            refined = True
        except KeyboardInterrupt:
            interrupted = True
    if polish is not None:
        polish.cancel()  # not needed (interrupted): do not wait for it
    wall = time.perf_counter() - start
    # r and J in one compiled program (uncertainty() would compile the residual twice and
    # build jacfwd's basis op by op)
    try:
        r, jac = _interruptible(
            lambda: value_and_jacobian(
                residual, np.asarray(best_x), fast_compile=settings.fast_compile
            ),
            "fricjax-uncertainty",
        )
        unc = uncertainty_at(
            r,
            jac,
            best_x,
            lower,
            upper,
            names=list(spec.free_names),
            noise=residual_noise(problem, best_x, jac),
        )
    except KeyboardInterrupt:  # keep the point found; its uncertainty stays unknown (NaN)
        interrupted = True
        unc = _no_uncertainty(list(spec.free_names))
    minima = cluster_minima(search.chain_x, search.chain_cost, lower, upper)
    d = spec.n_free
    run = RunResult(
        label=label or settings.method,
        method=settings.method,
        names=list(spec.free_names),
        units=[p.unit for p in spec.free],
        value=np.asarray(best_x, dtype=np.float64),
        lower=lower,
        upper=upper,
        fixed={p.name: p.init for p in spec.params if not p.free},
        cost=best_cost,
        ems=best_cost / problem.n,
        cost_search=cost_search,
        ems_search=cost_search / problem.n,
        std=np.asarray(unc.std, dtype=np.float64),
        rel_std=np.asarray(unc.rel_std, dtype=np.float64),
        corr=np.asarray(unc.corr, dtype=np.float64).reshape(d, d),
        flags=["; ".join(f) for f in unc.flags],
        chain_x=np.asarray(search.chain_x),
        chain_cost=np.asarray(search.chain_cost),
        traces={k: np.asarray(v) for k, v in search.traces._asdict().items()},
        minima_x=np.array([m.x for m in minima]).reshape(len(minima), d),
        minima_cost=np.array([m.cost for m in minima], dtype=np.float64),
        minima_count=np.array([m.count for m in minima], dtype=np.int64),
        attrs={
            "seed": settings.seed,
            "n_chains": settings.chains,
            "schedule": settings.anneal.schedule,
            "alpha": settings.anneal.alpha,
            "steps_per_level": settings.anneal.steps_per_level,
            "levels": search.levels_run,
            "n_evals": int(search.traces.n_evals[-1]) if search.levels_run else 0,
            "interrupted": interrupted,
            "refined": refined,
            "wall_time": wall,
            "t0": float(search.t0),
            "n_devices": search.n_devices,
            "objective": "equation error (seed eq. 11)",
            "cond": float(unc.cond),
            **sigma_attrs(unc),
            "separable": sep is not None,
            "search_space": f"separable ({sep.describe()})" if sep is not None else f"full ({d}-D)",
        },
    )
    dispersion = float(unc.dispersion)
    misfit = bool(dispersion > MISFIT_LIMIT)  # NaN (no noise model): not known to misfit
    if interrupted:
        return run
    if settings.objective == "simulation" or (settings.objective == "auto" and misfit):
        run = _output_error_polish(problem, run, settings.output_error, start)
        if settings.objective == "auto":
            run.attrs["refined_by_output_error"] = (
                f"the equation-error residual was {dispersion:.3g} times the noise's cost "
                f"(> {MISFIT_LIMIT:g}): its estimate is biased where the record sticks and "
                "slips, or the model lacks physics"
            )
    return run


def _output_error_polish(
    problem: Problem, run: RunResult, settings: OutputErrorSettings, started: float
) -> RunResult:
    """Output-error fit (:func:`fit_output_error_batch`) from the equation-error estimate of
    ``run``, and in the same batch from the config's initial values and the box's centre;
    the lowest cost wins. The run then carries its values, cost, σ, correlations and flags,
    and records the equation-error cost it started from. ``cost`` is E_OE [σ_x² units] and
    ``ems`` is E_OE per residual entry (≈ 1 when the misfit is the noise on x).

    Why three starts: an equation-error estimate is biased exactly where output error is
    needed (stick and slip), and it may sit where the simulation cannot see a parameter (a
    Stribeck velocity driven to its lower bound hides the whole drop, so the fit stalls
    there: on ``examples/axis.csv`` with a scaffolded Stribeck config, 1.1 mm rms from the
    estimate, the noise's 1 µm from either other start). The user's starting values and
    the centre of the box are independent of that bias; one vmapped program fits all three.
    """
    spec = problem.spec
    rows = [np.asarray(run.value, dtype=np.float64), spec.init, 0.5 * (spec.lower + spec.upper)]
    starts = np.unique(np.stack(rows), axis=0)
    fits = fit_output_error_batch(problem, starts, None, settings)
    fit = min(fits, key=lambda f: f.cost if np.isfinite(f.cost) else np.inf)
    attrs = {
        **run.attrs,
        "objective": "output error, multiple shooting (fricjax.output_error)",
        "objective_setting": "simulation",
        "equation_cost": float(run.cost),
        "equation_ems": float(run.ems),
        "oe_cost": fit.cost,
        "oe_cost_start": fit.cost_start,
        "position_rms": fit.position_rms,
        "x_scale": fit.x_scale,
        "segments": fit.n_segments,
        "segment_samples": fit.segment_samples,
        "defect_x": fit.defect_x,
        "defect_v": fit.defect_v,
        "oe_steps": fit.n_steps,
        "oe_starts": len(starts),
        "oe_success": fit.success,
        "oe_substeps": settings.substeps,
        "oe_hold": settings.hold,
        "oe_defect_weight": settings.defect_weight,
        "cond": fit.cond,
        # its σ is the output-error fit's own, from the position residual
        "sigma_method": GAUSS_NEWTON,
        "dispersion": float("nan"),
        "sigma_noise": "output-error fit: white position residual assumed",
        "wall_time": time.perf_counter() - started,
    }
    return replace(
        run,
        value=np.asarray(fit.value, dtype=np.float64),
        cost=fit.cost,
        ems=fit.cost / fit.n_residual,
        std=np.asarray(fit.std, dtype=np.float64),
        rel_std=np.asarray(fit.rel_std, dtype=np.float64),
        corr=np.asarray(fit.corr, dtype=np.float64),
        flags=["; ".join(f) for f in fit.flags],
        attrs=attrs,
    )


def _separable_search(
    sep: Separable, settings: IdentifySettings, on_level: Callable[[LevelInfo], None] | None
) -> SearchResult:
    """Chains over the nonlinear parameters on the projected cost; end points expanded to
    full vectors θ [C, d] (their costs are unchanged: E_P(θ_nl) = E(full_theta(θ_nl))).

    One compiled program (:func:`run_chains_fused`): the projection solve compiles once,
    the full vectors come out as the cost's auxiliary output, and the progress lines are
    replayed after it has run (~0.1-0.2 s for the paper twin)."""
    nl = sep.nonlinear_spec
    if nl.n_free == 0:  # every free parameter is linear: one exact solve, nothing to search
        x, cost = sep.project(np.zeros((1, 0)))
        empty = np.zeros((0, 1))
        traces = Traces(empty, empty, empty, np.zeros(0), np.zeros(0, np.int64), np.zeros(0))
        return SearchResult(x[0], float(cost[0]), x, cost, traces, 0, False, "exact", 0.0, 1)
    found, chain_x = run_chains_fused(
        prng_key(settings.seed),
        sep.cost_and_theta,
        nl.lower,
        nl.upper,
        method=settings.method,
        settings=settings.anneal,
        n_chains=settings.chains,
        on_level=on_level,
        has_aux=True,
        fast_compile=settings.fast_compile,
        source=nl.source,
    )
    chain_x = np.asarray(chain_x)
    i = int(np.argmin(found.chain_cost))
    return found._replace(best_x=chain_x[i].copy(), chain_x=chain_x)


def sigma_attrs(unc: Uncertainty) -> dict[str, Any]:
    """The result attributes that say which σ a run reports: ``sigma_method`` (sandwich or
    gauss-newton), ``dispersion`` (φ of :func:`fricjax.refine.uncertainty_at`, nan for
    Gauss–Newton) and ``sigma_noise`` (the noise it was propagated from, or why none)."""
    why = (
        "white residual assumed: no noise model of the preprocessing "
        "(settings unknown, or x noise-free)"
    )
    return {
        "sigma_method": unc.method,
        "dispersion": float(unc.dispersion),
        "sigma_noise": unc.noise if unc.method != GAUSS_NEWTON else why,
    }


def _no_uncertainty(names: list[str]) -> Uncertainty:
    """NaN uncertainty of ``names``, flagged: Ctrl-C stopped its computation."""
    d = len(names)
    nan = np.full(d, np.nan)
    return Uncertainty(
        std=nan,
        rel_std=nan.copy(),
        corr=np.full((d, d), np.nan),
        sigma2=float("nan"),
        on_bound=np.zeros(d, dtype=bool),
        flags=[["uncertainty not computed (interrupted)"] for _ in range(d)],
        cond=float("nan"),
        names=names,
    )


def _interruptible(work: Callable[[], Any], name: str) -> Any:
    """``work()`` in a worker thread, this thread waiting so that Ctrl-C reaches it now.

    A compiled XLA program (or its compilation) returns to Python only when done, so a
    Ctrl-C during the polish would otherwise wait for the whole polish (~20 s cold on the
    paper twin). On Ctrl-C the worker is abandoned, not stopped: the CLI then ends the
    process at once (:func:`fricjax.cli.main`); in a notebook it finishes unseen. The
    work and its result are those of a direct call.
    """
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix=name)
    future = pool.submit(work)
    pool.shutdown(wait=False)
    while True:
        try:
            # a bounded wait: the main thread returns to the interpreter, which raises
            # KeyboardInterrupt here between waits
            return future.result(timeout=0.1)
        except FuturesTimeout:
            continue


def _compile_polish_ahead(
    problem: Problem, residual: _Residual, settings: IdentifySettings, separable: bool
) -> Future | None:
    """Start compiling the single-start polish in a thread, or None where it does not pay.

    For a one-shot run (``fast_compile``) on the separable path the search is one short
    program whose tracing and compilation, and the polish's, make up most of a cold
    ``fricjax identify``; XLA compiles without Python's lock, so the polish's compilation
    runs on the second core while the search is traced, compiled and run. Only with one
    start (``refine_top`` = 1, the paper config's: a batch of starts compiles another
    program)."""
    if not (settings.fast_compile and separable and settings.refine):
        return None
    if min(settings.refine_top, settings.chains) != 1:
        return None
    spec = problem.spec
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="fricjax-polish-compile")
    future = pool.submit(
        compile_refine,
        residual,
        spec.init,
        spec.lower,
        spec.upper,
        settings.refiner,
        fast_compile=True,
    )
    pool.shutdown(wait=False)
    return future


def _polish(
    problem: Problem,
    search: SearchResult,
    settings: IdentifySettings,
    ahead: Future | None = None,
) -> tuple[np.ndarray, float]:
    """LM on the best ``refine_top`` chain end points at once; keep the best result.

    One start goes to :func:`refine` rather than a batch of one: tracing the vmapped
    Levenberg–Marquardt loop costs ~1.5 s more than the plain one (measured), a third of
    a cold ``fricjax identify`` on the separable path.
    """
    order = np.argsort(np.asarray(search.chain_cost))
    top = order[: min(settings.refine_top, order.size)]
    starts = np.asarray(search.chain_x)[top]
    residual = _Residual(problem.residual_fn)
    lower, upper = problem.spec.lower, problem.spec.upper
    fast = settings.fast_compile
    if len(top) == 1:
        program = ahead.result() if ahead is not None else None
        one = refine(
            residual, starts[0], lower, upper, settings.refiner, fast_compile=fast, program=program
        )
        xs, costs = np.asarray(one.x)[None], np.asarray(one.cost_after)[None]
    else:
        out = refine_many(residual, starts, lower, upper, settings.refiner, fast_compile=fast)
        xs, costs = np.asarray(out.x), np.asarray(out.cost_after)
    k = int(np.argmin(costs))
    x, cost = xs[k], float(costs[k])
    if not np.isfinite(cost) or cost > float(search.best_cost):
        return np.asarray(search.best_x), float(search.best_cost)
    return x, cost


@jax.jit
def _residual_at(residual: eqx.Module, theta: Array) -> Array:
    return residual(theta)


class _Residual(eqx.Module):
    """``θ [d] -> r [n]`` through one jit boundary: the refiner traces the residual several
    times (value, linearisation, Jacobian) and the uncertainty differentiates it; behind a
    jit each of those reuses one jaxpr instead of re-running the model's Python, and the
    Jacobian of the uncertainty is one compiled program instead of op-by-op dispatch.
    The data stay array leaves, so problems of the same shape share the compilation."""

    residual: eqx.Module

    def __call__(self, theta: Array) -> Array:
        return _residual_at(self.residual, theta)


def prng_key(seed: int) -> Array:
    """``jax.random.PRNGKey(seed)`` (the raw ``uint32[2]`` threefry key, bit for bit),
    built on the host: PRNGKey compiles a small program on its first call."""
    s = int(seed) % 2**64  # PRNGKey's shift of the int64 seed is a logical one
    return jax.device_put(np.array([s >> 32, s & 0xFFFFFFFF], dtype=np.uint32))


def with_settings(settings: IdentifySettings, **changes: Any) -> IdentifySettings:
    """A copy with ``IdentifySettings`` or ``AnnealSettings`` fields changed."""
    anneal_names = {f.name for f in fields(AnnealSettings)}
    anneal = {k: v for k, v in changes.items() if k in anneal_names}
    top = {k: v for k, v in changes.items() if k not in anneal_names}
    new = replace(settings, **top)
    if anneal:
        new = replace(new, anneal=replace(new.anneal, **anneal))
    return new
