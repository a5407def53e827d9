"""Identification = search (parallel annealing chains) → refine (optimistix LM) → uncertainty.

This is the seed paper's procedure (sections 3–4) as one API call::

    problem = build_problem(recording, config)
    run = identify(problem, IdentifySettings(method="csaa", chains=64, seed=0))
    run.params, run.ems, run.std

The search minimises the equation-error cost (seed eq. 11) over the box of the config; the
best ``refine_top`` chain end points are polished together (vmapped Levenberg–Marquardt) and
the best polished point is kept. Gauss–Newton standard deviations, correlations and
identifiability flags follow, plus a census of the distinct minima the chains ended in.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, fields, replace
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from fricjax.errors import FricjaxError, where
from fricjax.io.results import RunResult
from fricjax.problem import Problem
from fricjax.refine import RefineSettings, cluster_minima, refine_many, uncertainty
from fricjax.search.annealing import AnnealSettings
from fricjax.search.chains import METHODS, LevelInfo, SearchResult, run_chains

SEARCH_KEYS = ("method", "chains", "seed", "refine_top", "refine")


@dataclass(frozen=True)
class IdentifySettings:
    """What ``identify`` does; the ``[search]``, ``[anneal]``, ``[refine]`` config tables.

    Attributes:
        method: search algorithm (``csaa``, ``csaa-gauss``, ``dsaa``, ``dsaa-gray``, ``rdsa``).
        chains: number of parallel chains (restarts are just more chains).
        seed: integer seed; the same seed and settings reproduce a run bit for bit.
        refine_top: how many of the best chain end points the refiner polishes (vmapped).
        refine: whether to run the refiner at all.
        anneal: annealing control (eq. 15–16, schedules, stopping rule, move sizes).
        refiner: Levenberg–Marquardt settings.
    """

    method: str = "csaa"
    chains: int = 64
    seed: int = 0
    refine_top: int = 4
    refine: bool = True
    anneal: AnnealSettings = field(default_factory=AnnealSettings)
    refiner: RefineSettings = field(default_factory=RefineSettings)

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
        (e.g. ``alpha``, ``schedule``, ``steps_per_level``).
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
        for key, value in (overrides or {}).items():
            if value is None:
                continue
            if key in SEARCH_KEYS:
                search[key] = value
            elif key in anneal_names:
                anneal_table[key] = value
            else:
                raise FricjaxError(f"override {key!r}: unknown setting")
        method = str(search.get("method", cls.method))
        if method not in METHODS:
            raise FricjaxError(
                f"{where(source, '[search].method')}: unknown method {method!r} "
                f"(known: {', '.join(METHODS)})"
            )
        try:
            chains = int(search.get("chains", cls.chains))
            seed = int(search.get("seed", cls.seed))
            top = int(search.get("refine_top", cls.refine_top))
        except (TypeError, ValueError) as err:
            raise FricjaxError(f"{where(source, '[search]')}: not an integer ({err})") from None
        if chains < 1 or top < 1:
            raise FricjaxError(f"{where(source, '[search].chains')}: must be >= 1")
        return cls(
            method=method,
            chains=chains,
            seed=seed,
            refine_top=top,
            refine=bool(search.get("refine", True)),
            anneal=AnnealSettings.from_dict(anneal_table, source=source),
            refiner=RefineSettings.from_dict(dict(tables.get("refine", {})), source=source),
        )


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
    lower, upper = spec.lower, spec.upper
    start = time.perf_counter()
    search = run_chains(
        jax.random.PRNGKey(settings.seed),
        problem.cost_fn,
        lower,
        upper,
        method=settings.method,
        settings=settings.anneal,
        n_chains=settings.chains,
        on_level=on_level,
        source=spec.source,
    )
    best_x, cost_search = np.asarray(search.best_x), float(search.best_cost)
    best_cost = cost_search
    if settings.refine and not search.interrupted:
        best_x, best_cost = _polish(problem, search, settings)
    wall = time.perf_counter() - start
    unc = uncertainty(
        problem.residual_fn, jnp.asarray(best_x), lower, upper, names=list(spec.free_names)
    )
    minima = cluster_minima(search.chain_x, search.chain_cost, lower, upper)
    d = spec.n_free
    return RunResult(
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
            "interrupted": bool(search.interrupted),
            "refined": bool(settings.refine and not search.interrupted),
            "wall_time": wall,
            "t0": float(search.t0),
            "n_devices": search.n_devices,
            "objective": "equation error (seed eq. 11)",
            "cond": float(unc.cond),
        },
    )


def _polish(
    problem: Problem, search: SearchResult, settings: IdentifySettings
) -> tuple[np.ndarray, float]:
    """LM on the best ``refine_top`` chain end points at once; keep the best result."""
    order = np.argsort(np.asarray(search.chain_cost))
    top = order[: min(settings.refine_top, order.size)]
    starts = jnp.asarray(np.asarray(search.chain_x)[top])
    out = refine_many(
        problem.residual_fn, starts, problem.spec.lower, problem.spec.upper, settings.refiner
    )
    costs = np.asarray(out.cost_after)
    k = int(np.argmin(costs))
    x, cost = np.asarray(out.x[k]), float(costs[k])
    if not np.isfinite(cost) or cost > float(search.best_cost):
        return np.asarray(search.best_x), float(search.best_cost)
    return x, cost


def with_settings(settings: IdentifySettings, **changes: Any) -> IdentifySettings:
    """A copy with ``IdentifySettings`` or ``AnnealSettings`` fields changed."""
    anneal_names = {f.name for f in fields(AnnealSettings)}
    anneal = {k: v for k, v in changes.items() if k in anneal_names}
    top = {k: v for k, v in changes.items() if k not in anneal_names}
    new = replace(settings, **top)
    if anneal:
        new = replace(new, anneal=replace(new.anneal, **anneal))
    return new
