"""The one judge of the diagnosis: every candidate refitted by output error.

Metric. Base and base + candidate are fitted by output error with multiple shooting
(:func:`fricjax.output_error.fit_output_error`) with the residual in units of the record's own
displacement noise σ̂_x (:func:`fricjax.diagnose.evidence.record_noise`), so the cost
``E = Σ r_aug²`` is a sum of squares of N(0, 1) variables where the model is right. Output
error compares the simulated position with the recorded one: no velocity or acceleration is
differentiated from x, so what happens near rest (stops, breakaways) is judged like the rest
of the motion, and no band of samples is left out.

Statistic. With k the candidate's free parameters, n the samples and ν the degrees of freedom
of σ̂_x² (:attr:`~fricjax.diagnose.evidence.Evidence.nu`), for nested models (the term is
exactly zero at its amplitudes' null):

    LR = E_base − E_cand                                                [σ_x²]
    p  = P(F(k, ν) > LR/k)          (σ̂_x² itself carries ν degrees of freedom)
    ΔBIC = LR − k·ln n              (BIC of a known variance)

``E_base`` is the lower of the base's own fit and the base refitted from where the
candidate's fit ended: LM may stop short of the base's minimum, and a longer descent must not
pass for the term's gain.

Starts. Each candidate starts from the base's optimum with its amplitudes at their null and
its nonlinear parameters (a place, a width, a frequency) at ``n_starts`` points of the
catalogue's grid: the best local maxima of a cheap ranking, the equation-error score of the
candidate's force columns against the base's equation-error residual (projected off the
base's own columns; samples near rest left out, where the sign of the filtered velocity is
noise). The grids are spaced so that no peak lies between two points (catalogue), and LM
started within a grid cell of a peak converges to it; the second local maximum guards
against a ranking bent by the equation error's preprocessing bias. Every start of every
candidate is refitted (:func:`fit_candidates`): a local test at the base (a score test)
sees nothing of a term the base absorbs by bending its own parameters, which then pays
when refitted.

Calibration. The LR of a term whose shape was searched is the largest of many LRs, one per
shape the record can tell apart, and the maximum over a scan is not F-distributed (Davies
1987; the look-elsewhere effect). Each candidate's p is therefore that of the best of its
``looks`` shapes (:func:`looks`, the points of its grid), by the union bound:
``p = min(1, looks·p_raw)``. Valid whatever the dependence between shapes, and
conservative where neighbouring shapes are alike. A candidate without a shape has one look.

Ambiguity. Two candidates that both pass may explain the record equally well (on a
monotone stroke a bump in position and a harmonic in time bend x(t) alike): Vuong's test
(:func:`vuong`) of the best against each other, on the residuals of the two fits, says
whether the record prefers the best significantly.

One model. Base and candidates are all the same :class:`Superset` model, the terms not
under test pinned at their nulls by the fit's mask (:meth:`Superset.moving`), so one
compiled output-error program serves every fit of a forward-selection step; all the
candidates' output-error fits go through :func:`fit_candidates`.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float
from scipy import stats

from fricjax.diagnose.catalogue import CATALOGUE, candidate, grid_size
from fricjax.diagnose.evidence import NearRest
from fricjax.diagnose.select import Gain, vuong_t
from fricjax.diagnose.stages import Clock
from fricjax.model.simulate import simulate
from fricjax.model.system import Model
from fricjax.output_error import (
    OutputErrorFit,
    OutputErrorSettings,
    fit_output_error_batch,
)
from fricjax.params import ParamSpec
from fricjax.problem import EquationError, Problem
from fricjax.programs import stored
from fricjax.refine import covariance

__all__ = [
    "CandidateFit",
    "Fitted",
    "OutputErrorJudge",
    "Superset",
    "converged_rows",
    "fit_base",
    "fit_candidates",
    "fit_rows",
    "lack_of_fit_p",
    "looks",
    "starts",
    "vuong",
]


@dataclass(frozen=True)
class Superset:
    """The base model with every simulable, applicable candidate's term appended: ONE model,
    so that one compiled output-error program serves the base fit, every candidate's fit at
    every step and every held-out fit of a record of that length.

    A model "base + active terms" is this superset with every other term *pinned*: its
    parameters held at their nulls (amplitudes at 0, shape parameters at their grid's
    middle), where its force is zero, by the fit's mask (:meth:`moving`), the one encoding
    of a pinned term. The mask is an input of the compiled program, not part of it, so
    pinning costs no compilation, and a pinned parameter takes no tangent and no step.

    Attributes:
        record: the record with the base model.
        problem: the record with the superset model, every parameter in its search range.
        names: each effect's parameters (in the superset spec).
    """

    record: Problem
    problem: Problem
    names: dict[str, tuple[str, ...]]

    @classmethod
    def build(cls, record: Problem) -> Superset:
        """The superset of ``record``'s base model (the catalogue's order)."""
        model, spec, names = record.model, record.spec, {}
        for c in CATALOGUE:
            if not (c.simulable and c.applicable(model, spec)):
                continue
            before = set(spec.names)
            model, spec = c.extend(model, spec, record)
            names[c.effect] = tuple(n for n in spec.names if n not in before)
        return cls(record, replace(record, model=model, spec=spec), names)

    @property
    def effects(self) -> tuple[str, ...]:
        return tuple(self.names)

    def pinned(self, active: Sequence[str]) -> frozenset[str]:
        """The parameters of every term not in ``active``: held at their nulls."""
        return frozenset(n for e, ns in self.names.items() if e not in active for n in ns)

    def moving(self, active: Sequence[str]) -> np.ndarray:
        """[d] bool over the superset's free parameters: those a fit of base + ``active``
        moves (every free one but the pinned)."""
        pinned = self.pinned(active)
        return np.array([n not in pinned for n in self.problem.spec.free_names])

    def n_directions(self, active: Sequence[str]) -> int:
        """K of every output-error fit of a forward-selection step from base + ``active``:
        its free parameters and the most any one further term adds, so that the current
        model, every candidate and every held-out fit of the step share one compiled
        program (:func:`~fricjax.output_error.fit_output_error_batch`)."""
        own = self.n_free(active)
        rest = [self.n_free((*active, e)) for e in self.effects if e not in active]
        return max([own, *rest])

    def n_free(self, active: Sequence[str]) -> int:
        """Free parameters of base + ``active`` (the pinned ones are not free)."""
        own = sum(self.problem.spec[n].free for e in active for n in self.names[e])
        return self.record.spec.n_free + own


@dataclass(frozen=True)
class Fitted:
    """A model fitted to the record by output error: base + ``active`` terms of ``superset``,
    ``fit`` the output-error fit (cost in σ_x²)."""

    superset: Superset
    active: tuple[str, ...]
    fit: OutputErrorFit

    @property
    def problem(self) -> Problem:
        """The record with the superset model (its inactive terms at their nulls in
        ``fit``)."""
        return self.superset.problem

    @property
    def moving(self) -> np.ndarray:
        """[d] bool: the superset's free parameters this model moves."""
        return self.superset.moving(self.active)

    @property
    def n_free(self) -> int:
        return self.superset.n_free(self.active)

    @property
    def theta(self) -> np.ndarray:
        """All superset parameters [D] at the optimum (the superset spec's order)."""
        return self.superset.problem.spec.flatten(self.fit.params)

    @property
    def cost(self) -> float:
        """E at the optimum [σ_x²]."""
        return float(self.fit.cost)

    def covariance(self, names: Sequence[str]) -> np.ndarray:
        """[k, k] Gauss–Newton covariance of the named fitted parameters (SI units²), from
        the fit's σ and correlations; a name the fit did not move gets σ = 0."""
        where = {n: i for i, n in enumerate(self.fit.names)}
        idx = np.array([where.get(n, -1) for n in names], dtype=int)
        ok = idx >= 0
        std = np.where(ok, np.asarray(self.fit.std)[np.maximum(idx, 0)], 0.0)
        corr = np.eye(len(idx))
        corr[np.ix_(ok, ok)] = np.asarray(self.fit.corr)[np.ix_(idx[ok], idx[ok])]
        np.fill_diagonal(corr, 1.0)
        return covariance(std, corr)

    def reduced(self) -> tuple[Model, ParamSpec, np.ndarray]:
        """(model, spec, θ) of base + the active terms alone, for files a user reads."""
        model, spec = self.superset.record.model, self.superset.record.spec
        for e in self.active:
            model, spec = candidate(e).extend(model, spec, self.superset.record)
        return model, spec, spec.flatten({n: self.fit.params[n] for n in spec.free_names})


@dataclass(frozen=True)
class CandidateFit:
    """One candidate fitted next to ``base`` (module docstring).

    Attributes:
        effect: catalogue name.
        fitted: base + term at its best start.
        base: the base fit its LR is taken against (the lower of the two, docstring).
        k: the term's free parameters.
        lr, p_raw, delta_bic: the statistic at the fitted shape (module docstring).
        params: the term's own parameters [SI].
        looks: the shapes the search chose among (:func:`looks`).
    """

    effect: str
    fitted: Fitted
    base: Fitted
    k: int
    lr: float
    p_raw: float
    delta_bic: float
    params: dict[str, float]
    looks: int = 1

    @property
    def name(self) -> str:
        return self.effect

    @property
    def rank(self) -> float:
        """ΔBIC: the rule takes the passing candidates in its order."""
        return self.delta_bic

    @property
    def p_value(self) -> float:
        """``min(1, looks·p_raw)``: the p of the best of ``looks`` shapes (module
        docstring, "Calibration")."""
        return min(1.0, self.looks * self.p_raw)

    def passes(self, limit: float, min_delta_bic: float) -> bool:
        """Significant at ``limit`` (the per-candidate α) and ΔBIC above ``min_delta_bic``."""
        return self.p_value < limit and self.delta_bic > min_delta_bic


def _fit(
    problem: Problem,
    free: np.ndarray,
    start: Mapping[str, float],
    settings: OutputErrorSettings,
    states: tuple[np.ndarray, np.ndarray] | None,
    n_directions: int | None,
    accelerate: bool = True,
) -> OutputErrorFit:
    """One output-error fit of a superset model from named values, its pinned parameters
    held by the mask ``free`` ([d] bool, :meth:`Superset.moving`), K = ``n_directions``;
    ``accelerate``: geodesic or plain steps (:mod:`fricjax.levenberg`)."""
    spec = problem.spec
    known = {k: float(v) for k, v in start.items() if k in spec}
    row = spec.flatten({**spec.as_dict(), **known})[None]
    k = n_directions or int(free.sum())
    return fit_output_error_batch(
        problem, row, free[None], settings, states, n_directions=k, accelerate=accelerate
    )[0]


# A fit is run again from its end while its cost still falls by more than this [σ_x²]: the
# judge's thresholds are tens of σ_x² (ΔBIC > 10 beyond k·ln n), so a fit this close to its
# minimum cannot move a decision, and a descent cut short cannot pass for a term's gain.
CONVERGED = 0.5
# most restarts of one fit of each kind, bent and plain (each at most ``max_steps``
# Levenberg–Marquardt steps)
MAX_ROUNDS = 8


def converged(
    problem: Problem,
    free: np.ndarray,
    start: Mapping[str, float],
    settings: OutputErrorSettings,
    states: tuple[np.ndarray, np.ndarray] | None = None,
    fit: OutputErrorFit | None = None,
    n_directions: int | None = None,
    more: Callable[[float], bool] | None = None,
    rounds: list[tuple[float, int, float]] | None = None,
) -> OutputErrorFit:
    """An output-error fit (:func:`_fit`) from ``start`` (or continued from ``fit``),
    restarted from its end until a restart lowers its cost by less than :data:`CONVERGED`,
    whether or not the fit met its own tolerance: Levenberg–Marquardt's stop is local (its
    Gauss–Newton decrement), and a restart with a fresh trust region can still descend
    (0.272 s twin's base: stopped at 191.86 σ_x², two restarts reached 189.07). The
    restarts bend their steps until one gains less than :data:`CONVERGED`, then take plain
    ones until a plain one does too: plain steps do not stall where the simulation's events
    spoil the bend (:mod:`fricjax.levenberg`, "Two kinds of step"), bent ones go further
    along the seed model's curved valley.
    ``more(seconds)``: whether a round expected to take that long (the last one's wall
    time) may still start (a time limit); None: always. ``rounds``: each round's (cost
    [σ_x²], LM steps, wall seconds) is appended to it (benchmarks)."""
    began = time.perf_counter()
    fit = fit or _fit(problem, free, start, settings, states, n_directions)
    last = time.perf_counter() - began
    if rounds is not None:
        rounds.append((fit.cost, fit.n_steps, last))
    for accelerate in (True, False):
        for _ in range(MAX_ROUNDS - 1):
            if more is not None and not more(last):
                return fit
            began = time.perf_counter()
            states = (fit.states_x, fit.states_v)
            again = _fit(problem, free, fit.params, settings, states, n_directions, accelerate)
            last = time.perf_counter() - began
            if rounds is not None:
                rounds.append((again.cost, again.n_steps, last))
            done = fit.cost - again.cost < CONVERGED
            fit = again if again.cost < fit.cost else fit
            if done:
                break
    return fit


def fit_base(
    sup: Superset,
    start: Mapping[str, float],
    settings: OutputErrorSettings,
    more: Callable[[float], bool] | None = None,
) -> Fitted:
    """The base model fitted by output error from ``start`` (named values, the equation-error
    estimate), from the config's initial values and from the centre of the box: one round
    each, then the best to convergence or until ``more`` (:func:`converged`) refuses another
    round.

    Why three starts: an equation-error estimate is biased where the record sticks and slips,
    and a fit from it can stop in a basin far above the base's minimum; every candidate
    then "explains" what the base failed to fit (a null of the stick-slip rig: base
    6.2·10³ σ_x² on 232 samples, and three terms named). The user's starting values and the
    box's centre are starts independent of that bias (as ``identify``'s output-error
    refinement, :func:`fricjax.identify._output_error_polish`)."""
    base, free = sup.problem, sup.moving(())
    spec, record = base.spec, sup.record.spec
    k = sup.n_directions(())
    own = {p.name for p in record.params if p.free}
    centre = {p.name: 0.5 * (p.lower + p.upper) for p in record.params if p.free}
    candidates = [dict(start), {p.name: p.init for p in record.params if p.free}, centre]
    starts_: list[dict[str, float]] = []
    for c in candidates:
        row = {q: float(v) for q, v in c.items() if q in own}
        if row not in starts_:
            starts_.append(row)
    began = time.perf_counter()
    firsts = [_fit(base, free, {**spec.as_dict(), **row}, settings, None, k) for row in starts_]
    best = min(firsts, key=lambda f: f.cost if np.isfinite(f.cost) else np.inf)
    last = (time.perf_counter() - began) / len(firsts)
    if more is not None and not more(last):
        return Fitted(sup, (), best)
    fit = converged(base, free, {}, settings, fit=best, n_directions=k, more=more)
    return Fitted(sup, (), fit)


def f_pvalue(lr: Float[np.ndarray, "..."], k: int, nu: int) -> Float[np.ndarray, "..."]:
    """``P(F(k, ν) > LR/k)``: the p of a likelihood ratio [σ̂_x²] of k parameters when σ̂_x²
    carries ν degrees of freedom (module docstring)."""
    kk = max(k, 1)
    return stats.f.sf(np.asarray(lr) / kk, kk, nu)


def _judge_numbers(
    base_cost: float, fit: OutputErrorFit, k: int, n: int, nu: int
) -> tuple[float, float, float]:
    """(LR, p, ΔBIC) of a fit against the base cost (module docstring)."""
    # LM never ends above its start, the base optimum with the term at its null, so the
    # nested fit is not worse than the base up to the solver's tolerance
    lr = max(base_cost - float(fit.cost), 0.0)
    return lr, float(f_pvalue(lr, k, nu)), float(lr - k * math.log(n))


def looks(effect: str, record: Problem) -> int:
    """How many shapes of ``effect`` its search chooses among: the points of its grid of
    nonlinear parameters (a place, a width, a frequency), 1 for a term without any. The
    catalogue spaces a grid so that no peak lies between two points, so its points are the
    shapes the record can tell apart (module docstring, "Calibration")."""
    return grid_size(candidate(effect).grid(record))


def _padded(n: int) -> int:
    """Rows of a batch: the next power of two, so that a few compiled programs serve every
    step and round (a padded row repeats the first)."""
    return 1 << max(n - 1, 0).bit_length()


def fit_rows(
    problem: Problem,
    rows: Sequence[np.ndarray],
    free: Sequence[np.ndarray],
    settings: OutputErrorSettings,
    states: Sequence[tuple[np.ndarray, np.ndarray]],
    k: int,
    samples: Sequence[np.ndarray] | None = None,
    more: Callable[[], bool] | None = None,
    accelerate: bool = True,
) -> list[OutputErrorFit]:
    """The rows fitted as ONE program (:func:`fit_output_error_batch`), padded to
    :func:`_padded` rows; the fits of the given rows, in order. ``samples``: each row's
    held-out mask (1 fitted, 0 held out), default every sample. ``more()``: asked before
    every call after the first where the rows take several calls (a CPU: one row a call);
    once it says no, the fits so far are returned, fewer than the rows (a time limit or
    Ctrl-C then waits for one row's fit, not for the whole batch). ``accelerate``: geodesic
    or plain steps (:mod:`fricjax.levenberg`)."""
    lanes = lanes_per_call()
    if len(rows) > lanes:
        out: list[OutputErrorFit] = []
        for i in range(0, len(rows), lanes):
            if i and more is not None and not more():
                break
            part = slice(i, i + lanes)
            out += fit_rows(
                problem,
                rows[part],
                free[part],
                settings,
                states[part],
                k,
                None if samples is None else samples[part],
                accelerate=accelerate,
            )
        return out
    n, B = len(rows), _padded(len(rows))

    def pad(xs: Sequence[Any]) -> list[Any]:
        return [*xs, *[xs[0]] * (B - n)]

    xs = np.stack([np.asarray(st[0]) for st in pad(states)])
    vs = np.stack([np.asarray(st[1]) for st in pad(states)])
    held = None if samples is None else np.stack(pad(samples))
    fits = fit_output_error_batch(
        problem, np.stack(pad(rows)), np.stack(pad(free)), settings, (xs, vs), k, held, accelerate
    )
    return fits[:n]


def lanes_per_call() -> int:
    """Rows of one batched fit program. On an accelerator every row of a step in one call
    (the lanes run side by side). On a CPU one row per call: a batched ``while_loop`` runs
    every row until the slowest has stopped, and its lanes share the same cores, so a batch
    costs its row count times the slowest row's steps where separate calls cost the sum of
    each row's own (the same compiled program serves both: B is padded to a power of two)."""
    return 1 if jax.default_backend() == "cpu" else 1 << 30


def converged_rows(
    problem: Problem,
    fits: Sequence[OutputErrorFit],
    free: Sequence[np.ndarray],
    settings: OutputErrorSettings,
    k: int,
    samples: Sequence[np.ndarray] | None = None,
    more: Callable[[], bool] | None = None,
) -> list[OutputErrorFit]:
    """Each of ``fits`` restarted from its end, all in one batch per round, until a round
    gains less than :data:`CONVERGED` (:func:`converged`, row by row; at most
    :data:`MAX_ROUNDS` rounds of each kind), bent then plain as :func:`converged`'s.
    ``more()``: as in :func:`fit_rows`; once it says no, each fit is the best reached so
    far."""
    spec = problem.spec
    best = list(fits)
    for accelerate in (True, False):
        open_ = list(range(len(best)))
        for _ in range(MAX_ROUNDS - 1):
            if not open_:
                break
            if more is not None and not more():
                return best
            again = fit_rows(
                problem,
                [spec.flatten(best[i].params) for i in open_],
                [free[i] for i in open_],
                settings,
                [(best[i].states_x, best[i].states_v) for i in open_],
                k,
                None if samples is None else [samples[i] for i in open_],
                more,
                accelerate=accelerate,
            )
            still = []
            for i, fit in zip(open_, again, strict=False):
                if best[i].cost - fit.cost >= CONVERGED:
                    still.append(i)
                if fit.cost < best[i].cost:
                    best[i] = fit
            open_ = still
    return best


def fit_candidates(
    base: Fitted,
    candidates: Sequence[tuple[str, Sequence[Mapping[str, float]]]],
    settings: OutputErrorSettings,
    nu: int,
    more: Callable[[], bool] | None = None,
) -> list[CandidateFit]:
    """Every candidate ``(effect, starts)`` fitted by output error from ``base``'s optimum
    (amplitudes at their null, nonlinear parameters at each start), judged against ``base``
    (module docstring). The one place where the candidates' output-error fits run.
    ``more()``: asked between calls (:func:`fit_rows`); a candidate none of whose starts
    was fitted before it said no is left out of the result (untested).

    One program per round: every (candidate, start) is a row of one batch of the superset
    model, its fitted parameters (the base's and the candidate's own) chosen by the row's
    mask; the best start of each candidate is then restarted from its end, all candidates
    in one batch again, until a round gains less than :data:`CONVERGED` (as
    :func:`converged` does for one fit)."""
    sup, n = base.superset, base.superset.record.n
    spec = sup.problem.spec
    names = list(spec.free_names)
    own = base.moving
    states = (base.fit.states_x, base.fit.states_v)
    k_step = sup.n_directions(base.active)
    rows, masks, owner = [], [], []
    mask_of: dict[str, np.ndarray] = {}
    for effect, nl_starts in candidates:
        mask = own | np.isin(names, sup.names[effect])
        mask_of[effect] = mask
        for nl in nl_starts or ({},):
            row = base.theta.copy()
            for q, value in nl.items():
                row[names.index(q)] = value
            rows.append(row)
            masks.append(mask)
            owner.append(effect)
    if not rows:
        return []
    best: dict[str, OutputErrorFit] = {}
    first = fit_rows(sup.problem, rows, masks, settings, [states] * len(rows), k_step, more=more)
    for effect, fit in zip(owner, first, strict=False):
        if effect not in best or fit.cost < best[effect].cost:
            best[effect] = fit
    ends = converged_rows(
        sup.problem, list(best.values()), [mask_of[e] for e in best], settings, k_step, more=more
    )
    best = dict(zip(best, ends, strict=True))
    out = []
    for effect, fit in best.items():
        active = (*base.active, effect)
        fitted = Fitted(sup, active, fit)
        k = fitted.n_free - base.n_free
        lr, p, dbic = _judge_numbers(base.cost, fit, k, n, nu)
        own_params = {q: float(fit.params[q]) for q in sup.names[effect]}
        out.append(
            CandidateFit(
                effect, fitted, base, k, lr, p, dbic, own_params, looks(effect, sup.record)
            )
        )
    return out


def vuong(best: Fitted, other: Fitted) -> tuple[float, int]:
    """Vuong's test of two non-nested models on one record, in the judge's metric: with
    ``d_i = r_other,i² − r_best,i²`` (output-error residuals in σ̂_x), summed per segment of
    the multiple shooting (``D_s``, S segments: the residual of neighbouring samples is
    correlated through the simulation, the segments much less), the statistic
    ``t = mean(D)/(sd(D)/√S)`` follows Student's t with S − 1 degrees of freedom where the
    two explain the record equally well. Returns (t, S − 1); t large: ``best`` is better."""
    rec = best.superset.record
    d = ((other.fit.x_sim - rec.x) ** 2 - (best.fit.x_sim - rec.x) ** 2) / best.fit.x_scale**2
    return vuong_t(np.bincount(best.fit.segment_of, weights=d))


def rebased(cf: CandidateFit, settings: OutputErrorSettings, nu: int) -> CandidateFit:
    """``cf`` judged against the lower of its base and the base refitted from where the
    candidate's fit ended (module docstring)."""
    end = cf.fitted.fit
    start = {**end.params, **{q: cf.base.fit.params[q] for q in cf.base.superset.names[cf.effect]}}
    fit = converged(
        cf.base.problem,
        cf.base.moving,
        start,
        settings,
        (end.states_x, end.states_v),
        n_directions=cf.base.superset.n_directions(cf.base.active),
    )
    if fit.cost >= cf.base.cost:
        return cf
    base = Fitted(cf.base.superset, cf.base.active, fit)
    lr, p, dbic = _judge_numbers(base.cost, end, cf.k, base.superset.record.n, nu)
    return replace(cf, base=base, lr=lr, p_raw=p, delta_bic=dbic)


def lack_of_fit_p(fitted: Fitted, nu: int) -> float:
    """p of a model's output-error cost against the record's noise: E over its
    ``ν_r = n_residual − d − 2S`` residual degrees of freedom (d parameters, S segments' two
    states) follows ``F(ν_r, ν)`` when the model is right."""
    f = fitted.fit
    dof = max(f.n_residual - fitted.n_free - 2 * f.n_segments, 1)
    return float(stats.f.sf(f.cost / dof, dof, nu))


def simulation_error(fitted: Fitted) -> float:
    """RMS of x_sim − x [m] of one open-loop simulation over the whole record from its first
    recorded state (the figure a user sees when replaying the model); recordings joined
    into one problem are each simulated from their own first state. NaN where the
    simulator rejects the model."""
    pb = fitted.problem
    p = pb.spec.unflatten(jnp.asarray(fitted.theta))
    bounds = [0, *pb.joins, pb.n]
    errs = []
    for a, b in itertools.pairwise(bounds):
        try:
            traj = simulate(
                pb.model,
                p,
                jnp.asarray(pb.t[a:b]),
                float(pb.x[a]),
                float(pb.v[a]),
                jnp.asarray(pb.drive_input[a:b]),
            )
        except Exception:  # a model the simulator rejects: report no figure rather than fail
            return math.nan
        errs.append(np.asarray(traj.x) - pb.x[a:b])
    err = np.concatenate(errs)
    return float(np.sqrt(np.mean(err**2)))


def record_gains(before: Fitted, after: Fitted) -> tuple[float, float]:
    """Relative gains ``1 − after/before`` of the record's own EMS [N²] (equation error at
    the output-error optimum) and open-loop simulation error [m]: a term that wins the test
    statistic but worsens what the user sees stands in for something else."""
    ems = 1 - after.problem.ems(after.theta) / before.problem.ems(before.theta)
    sim_b, sim_a = simulation_error(before), simulation_error(after)
    sim = 1 - sim_a / sim_b if math.isfinite(sim_a) and math.isfinite(sim_b) else math.nan
    return float(ems), float(sim)


# -- the starts -----------------------------------------------------------------------


@stored
def _columns(fn: EquationError, thetas: Float[Array, "B d"]) -> Float[Array, "B n"]:
    """Equation-error residuals [N] at a batch of parameter vectors."""
    return jax.vmap(fn)(thetas)


@stored
def _jacobian(fn: EquationError, theta: Float[Array, " d"]) -> Float[Array, "n d"]:
    """Equation-error Jacobian [N per parameter unit] at ``theta``."""
    return jax.jacfwd(fn)(theta)


def starts(current: Fitted, effect: str, band: NearRest, n_starts: int) -> list[dict[str, float]]:
    """Up to ``n_starts`` grid points of ``effect``'s nonlinear parameters, the best local
    maxima of its equation-error score at ``current``'s optimum (module docstring); ``[{}]``
    for a candidate without nonlinear parameters."""
    sup, c = current.superset, candidate(effect)
    grid = c.grid(sup.record)
    if not grid:
        return [{}]
    spec = sup.problem.spec
    names = list(spec.free_names)
    lin = [q for q in sup.names[effect] if q not in grid]
    keys = list(grid)
    g = len(grid[keys[0]])
    theta0 = current.theta
    b = g * (1 + len(lin))
    # batches padded to a power of two: a few compiled shapes serve every grid
    rows = np.repeat(theta0[None, :], 1 << (b - 1).bit_length(), axis=0)
    for name in keys:
        rows[:b, names.index(name)] = np.tile(grid[name], 1 + len(lin))
    step = {q: 0.01 * (spec[q].upper - spec[q].lower) for q in lin}
    for j, q in enumerate(lin, 1):
        rows[j * g : (j + 1) * g, names.index(q)] = step[q]
    r = np.asarray(_columns(sup.problem.residual_fn, jnp.asarray(rows)))[:b]
    keep = ~band.mask if band.mask.shape[0] == r.shape[1] else np.ones(r.shape[1], bool)
    r = r[:, keep]
    r0 = r[:g]  # the current residual, the same at every grid point (term at its null)
    cols = np.stack([(r[j * g : (j + 1) * g] - r0) / step[q] for j, q in enumerate(lin, 1)], -1)
    # the current model's own columns, projected off: what it absorbs is no score
    own = np.flatnonzero(current.moving)
    jac = np.asarray(_jacobian(sup.problem.residual_fn, jnp.asarray(theta0)))[keep][:, own]
    qb, _ = np.linalg.qr(jac)
    res = r0[0] - qb @ (qb.T @ r0[0])
    cols = cols - np.einsum("nk,gkj->gnj", qb, np.einsum("nk,gnj->gkj", qb, cols))
    z = np.einsum("gnj,n->gj", cols, res)
    gram = np.einsum("gnj,gnk->gjk", cols, cols) + 1e-30 * np.eye(len(lin))
    score = np.einsum("gj,gj->g", z, np.linalg.solve(gram, z[..., None])[..., 0])
    score = np.where(np.isfinite(score), score, -np.inf)
    # local maxima along the first (slowest) axis, each the best over the other axes
    first = grid[keys[0]]
    axis = np.unique(first)
    best = np.array([np.max(score[first == a]) for a in axis])
    peaks = [
        i
        for i in range(axis.size)
        if (i == 0 or best[i] >= best[i - 1]) and (i == axis.size - 1 or best[i] >= best[i + 1])
    ]
    peaks = sorted(peaks, key=lambda i: -best[i])[:n_starts]
    out = []
    for i in peaks:
        idx = np.flatnonzero(first == axis[i])
        j = int(idx[np.argmax(score[idx])])
        out.append({k: float(grid[k][j]) for k in keys})
    return out or [{}]


def remaining(current: Fitted) -> list[str]:
    """The superset's effects not yet in ``current``'s model."""
    return [e for e in current.superset.effects if e not in current.active]


@dataclass(frozen=True)
class OutputErrorJudge:
    """The judge of one record for :func:`~fricjax.diagnose.select.select`: every remaining
    catalogue term refitted by output error from each of its ``n_starts`` starts
    (:func:`starts`, :func:`fit_candidates`), the EMS and open-loop simulation error
    reported beside each (:func:`record_gains`), ambiguity by :func:`vuong`. A term no
    held-out check can judge is not named (``standalone`` False): one record always has a
    check (cross-validation) unless it is one segment long, too short to name anything."""

    settings: OutputErrorSettings
    nu: int
    band: NearRest
    n_starts: int
    standalone: bool = False

    def candidates(self, current: Fitted) -> list[str]:
        return remaining(current)

    def fit(self, current: Fitted, names: Sequence[str], clock: Clock) -> list[CandidateFit]:
        todo = []
        clock.note("ranking the candidates' starts")
        for effect in names:
            if clock.over("candidates"):
                clock.untested("candidates", effect)
                continue
            todo.append((effect, starts(current, effect, self.band, self.n_starts)))
        clock.note(f"output-error fits of {len(todo)} candidates")
        fits = (
            fit_candidates(
                current, todo, self.settings, self.nu, lambda: not clock.over("candidates")
            )
            if todo
            else []
        )
        fitted = {f.effect for f in fits}
        for effect, _ in todo:
            if effect not in fitted:  # the limit (or Ctrl-C) came first
                clock.untested("candidates", effect)
        return fits

    def confirm(self, fit: CandidateFit) -> CandidateFit:
        return rebased(fit, self.settings, self.nu)

    def base(self, fit: CandidateFit) -> Fitted:
        return fit.base

    def model(self, fit: CandidateFit) -> Fitted:
        return fit.fitted

    def place(self, fit: CandidateFit) -> Mapping[str, Any]:
        return candidate(fit.effect).location(fit.params, fit.base.superset.record)

    def gains(self, fit: CandidateFit) -> tuple[Gain, ...]:
        ems, sim = record_gains(fit.base, fit.fitted)
        return (Gain(EMS, ems), Gain(SIMULATION, sim))

    def vuong(self, best: CandidateFit, other: CandidateFit) -> tuple[float, int]:
        return vuong(best.fitted, other.fitted)


#: The figures reported beside a finding of one record (:meth:`OutputErrorJudge.gains`).
EMS = "equation-error EMS"
SIMULATION = "open-loop simulation error"
