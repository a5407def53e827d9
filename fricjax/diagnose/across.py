"""Diagnosis across recordings of one plant, on their joint fit (:mod:`fricjax.joint`).

``K`` recordings (members) of one axis share the config's model; the config's
``[joint].per_recording`` parameters take one value per recording. The diagnosis is the
forward selection of every diagnosis (:func:`fricjax.diagnose.select.select`) with the
joint judge (:class:`JointJudge`) and one held-out check, leaving one recording out
(:class:`LeaveOneOut`). Its candidates are of two kinds:

1. **A catalogue term shared by all recordings**: each applicable effect of
   :data:`fricjax.diagnose.catalogue.CATALOGUE` added to the joint model with one value of
   its parameters for all recordings, fitted jointly (Levenberg–Marquardt from the current
   fit, the term's amplitudes at their null and its shape parameters at up to
   :data:`MAX_STARTS` points of its grid). Direction asymmetry from strokes that each move
   one way only comes out here: no single stroke sees it, the strokes together do.
2. **Run-to-run drift** (``drift of P``): a free base parameter ``P`` that the config does
   not already declare per recording given one value per recording, ``P[1] … P[K]`` (the
   layout of :func:`fricjax.joint.joint_problem`), testing ``P[1] = … = P[K]``.

Both compete in one selection: a Coulomb level that moved in one run and a shared term
that explains the same are rivals of one step, and where the recordings cannot tell them
apart (two opposite one-way strokes: a direction asymmetry, or a Coulomb level that differs
per stroke) the finding is the ambiguity set.

The statistic and its variance. Each candidate's larger model adds ``q`` linear contrasts
``Lθ`` (a term's amplitudes ``β``, null 0; or ``P[k] − P[1]``, k = 2 … K). The test is
Wald's,

    W = (Lθ̂)ᵀ (L C Lᵀ)⁻¹ (Lθ̂),     C = A⁺ (JᵀΣJ) A⁺,   A = JᵀJ       [1]

at the larger model's fit, with J the Jacobian of the weighted joint residual and Σ the
residual's noise covariance propagated from each recording's own displacement noise σ_x
through its preprocessing (:func:`fricjax.residual_noise.stacked_noise`; the record's σ_x
of :func:`fricjax.diagnose.evidence.record_noise`). Why this variance: the equation-error
residual's noise is twice-differentiated x noise, strongly coloured, so a white-noise
likelihood ratio ``ΔE/s²`` has no χ² law; and ``s_k`` (each own fit's residual scale) holds
whatever the model misses, so a ratio in its units grows blind exactly where the model is
wrong. The sandwich ``C`` is the covariance of the weighted least-squares estimate under
the record's noise alone, whatever the weights: the weights ``1/s_k²`` set how efficiently
the recordings are combined, never the test's size. Under the null (linearised)
``W ~ χ²_q``; σ̂_x² is itself estimated with ν degrees of freedom
(:func:`fricjax.diagnose.evidence.effective_dof`), so

    p = P[F(q, ν) > W/q],   ν = min_k ν_k                                  (2)

(the smallest ν over the recordings: the most cautious reference); a term scanned from G
shape starts counts G times (``p·G``, as a record's ``looks``). A contrast that the data do
not determine (it has a component along a null direction of A, as the Coulomb level and an
asymmetry on one stroke) is *not testable*: its p is NaN and it never passes.

The bars (:class:`~fricjax.diagnose.select.Rule`). ``p < α/C`` over the C candidates of
the step, and

    ΔBIC = W − k·ln n,   n = Σ_k n_k                                       (3)

above ``min_delta_bic`` (W stands for the likelihood ratio it equals to first order; ``k``
the parameters the candidate adds, its shape parameters included). The passing candidates
are taken by the weighted joint cost they remove less ``k·ln n`` (that ranks the
explanations by fit, while W says how sure each test is, and a wrong explanation can score
the larger W).

Leaving one recording out (:class:`LeaveOneOut`): for each member k, the current model and
the model with the term are fitted on the other K − 1 recordings, then each predicts
recording k with its shared parameters fixed and k's own per-recording parameters refitted;
the term is named where the summed cost over the folds falls. A fold whose K − 1 recordings
leave a shared parameter undetermined cannot judge and says so. Where no fold can (two
opposite one-way strokes), or for a drift (its left-out value is refitted on the left-out
recording, which always gains: no test), the candidate stands on its statistics
(``standalone``) and the finding says that no held-out check was possible.

Ambiguity (:meth:`JointJudge.vuong`): Vuong's test on the two fits' weighted residuals,
summed over blocks of ``segment_s`` of each recording (the equation error's noise is
coloured by the preprocessing filter over a few samples; blocks of 50 ms are far longer).

Time. The stages and their clock are the single-record diagnosis'
(:class:`~fricjax.diagnose.stages.Clock`): the joint fit (``base_fit``) always runs; the
candidates' fits and the held-out checks run under their limits and the total one,
checked between units of work (one candidate's fit, one candidate's folds); a candidate
left untested is never named.
"""

from __future__ import annotations

import itertools
import json
import math
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from jaxtyping import Float
from scipy import stats

from fricjax.diagnose.catalogue import CATALOGUE, Candidate, candidate
from fricjax.diagnose.evidence import effective_dof, record_noise
from fricjax.diagnose.select import (
    Decision,
    Finding,
    Gain,
    Rule,
    Step,
    Verdict,
    outcome,
    refused,
    refused_by_step,
    select,
    vuong_t,
)
from fricjax.diagnose.stages import TIME_LIMIT_S, Clock, OnStage
from fricjax.errors import FricjaxError
from fricjax.identify import IdentifySettings
from fricjax.joint import (
    JointProblem,
    JointSettings,
    identify_joint,
    joint_problem,
    member_name,
    split_name,
)
from fricjax.params import Param
from fricjax.problem import Problem
from fricjax.refine import RefineSettings, refine_many, value_and_jacobian
from fricjax.report.tables import p_text
from fricjax.residual_noise import stacked_noise

__all__ = [
    "DRIFT",
    "MAX_STARTS",
    "TIME_LIMIT",
    "AcrossDiagnosis",
    "JointCandidateFit",
    "JointFit",
    "JointJudge",
    "JointModel",
    "LeaveOneOut",
    "across_clock",
    "diagnose_across",
    "fit_joint",
    "wald",
]

#: Shape-parameter starts per candidate (evenly spaced points of its grid, all recordings'
#: grids merged): each is one Levenberg–Marquardt start of the vmapped polish.
MAX_STARTS = 16
#: Seconds in all by default (no stage limit by default, as for one recording): five times
#: one recording's default, as every candidate is fitted on every recording; a user who
#: waits longer sets ``--time-limit`` (``inf``: none).
TIME_LIMIT = 5 * TIME_LIMIT_S
#: A contrast is determined when its component along A's null directions is below this
#: fraction of its norm (in the column-scaled coordinates of the SVD).
_NULL_TOL = 1e-6
_SV_RCOND = 1e-10
#: The effect name of a run-to-run drift finding (its parameter under ``parameter``).
DRIFT = "run_drift"
_DRIFT_PREFIX = "drift of "


def across_clock(
    stage_limits: Mapping[str, float] | None = None,
    total: float | None = None,
    on_stage: OnStage | None = None,
    stop: threading.Event | None = None,
) -> Clock:
    """The clock of a diagnosis across recordings: ``stage_limits`` (``[diagnose]``, none
    by default) and ``total`` seconds in all (default :data:`TIME_LIMIT`)."""
    return Clock(
        limits=dict(stage_limits or {}),
        total=TIME_LIMIT if total is None else total,
        on_stage=on_stage,
        stop=stop,
    )


# -- joint fits ---------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class JointFit:
    """A joint model fitted by Levenberg–Marquardt with the noise-only sandwich (module
    docstring, eq. 1).

    Attributes:
        jp: the joint problem (members, layout, weights ``1/s_k²``).
        theta: [D] the fit. cost: the weighted joint cost there [1].
        cov: [D, D] ``A⁺ (JᵀΣJ) A⁺`` in θ's units squared.
        null: [D, D − rank] A's null directions in the column-scaled coordinates.
        scale: [D] the column norms of J that scale them.
        member_cost: [K] each member's weighted cost ``‖r_k‖²/s_k²`` at ``theta``.
        residual: [Σ n_k] the weighted joint residual at ``theta`` (members in order).
    """

    jp: JointProblem
    theta: np.ndarray
    cost: float
    cov: np.ndarray
    null: np.ndarray
    scale: np.ndarray
    member_cost: np.ndarray
    residual: np.ndarray

    def std(self) -> np.ndarray:
        """[D] σ of every joint parameter (∞ along an undetermined direction)."""
        sd = np.sqrt(np.clip(np.diag(self.cov), 0.0, None))
        return np.where(self.determined(np.eye(sd.size)), sd, np.inf)

    def determined(self, contrasts: Float[np.ndarray, "q D"]) -> np.ndarray:
        """[q] whether each row of ``contrasts`` lies in A's determined directions."""
        rows = np.atleast_2d(contrasts) / self.scale
        if self.null.shape[1] == 0:
            return np.ones(rows.shape[0], dtype=bool)
        along = np.linalg.norm(rows @ self.null, axis=1)
        return along <= _NULL_TOL * np.linalg.norm(rows, axis=1)

    def value(self, name: str) -> float:
        return float(self.theta[self.jp.names.index(name)])


def fit_joint(
    problems: Sequence[Problem],
    per_recording: Sequence[str],
    sigma: Sequence[float],
    starts: Float[np.ndarray, "B D"],
) -> JointFit:
    """Polish ``starts`` on the joint problem of ``problems`` (weights ``1/sigma²``), keep
    the best, and qualify it with the noise-only sandwich (module docstring, eq. 1)."""
    jp = joint_problem(problems, per_recording, sigma)
    residual = jp.residual_fn
    x0 = np.clip(np.atleast_2d(np.asarray(starts, np.float64)), jp.lower, jp.upper)
    out = refine_many(residual, x0, jp.lower, jp.upper, RefineSettings(), fast_compile=True)
    costs = np.asarray(out.cost_after)
    best = np.asarray(out.x)[int(np.nanargmin(costs))]
    r, jac = value_and_jacobian(residual, best, fast_compile=True)
    noise = stacked_noise(jp.problems, [best[np.asarray(i)] for i in jp.index], jac, 1.0 / jp.sigma)
    if noise is None:
        raise FricjaxError(
            "diagnose: no displacement noise model for a recording (preprocessing unknown "
            "or too few samples); the tests across recordings need one"
        )
    scale = np.linalg.norm(jac, axis=0)
    scale = np.where(scale > 0.0, scale, 1.0)
    _, s, vt = np.linalg.svd(jac / scale, full_matrices=False)
    keep = s > _SV_RCOND * s[0] if s[0] > 0 else np.zeros_like(s, dtype=bool)
    v = vt[keep].T
    a_pinv = (v / s[keep] ** 2) @ v.T / np.outer(scale, scale)
    edges = np.cumsum([0] + [p.n_residual for p in jp.problems])
    member_cost = np.array([float(r[a:b] @ r[a:b]) for a, b in itertools.pairwise(edges)])
    return JointFit(
        jp=jp,
        theta=best,
        cost=float(r @ r),
        cov=a_pinv @ noise.jsj @ a_pinv,
        null=vt[~keep].T,
        scale=scale,
        member_cost=member_cost,
        residual=np.asarray(r),
    )


@dataclass(frozen=True)
class Wald:
    """The Wald test of ``Lθ = 0`` (module docstring, eqs. 1–2): statistic ``W`` [1], its
    degrees of freedom ``q``, p-value, and whether the contrasts are determined at all."""

    statistic: float
    dof: int
    p_value: float
    determined: bool


def wald(fit: JointFit, contrasts: Float[np.ndarray, "q D"], nu: int) -> Wald:
    """Test ``contrasts · θ = 0`` at ``fit`` against ``F(q, ν)`` (module docstring, eq. 2)."""
    lmat = np.atleast_2d(contrasts)
    if not fit.determined(lmat).all():
        return Wald(math.nan, lmat.shape[0], math.nan, False)
    value = lmat @ fit.theta
    cov = lmat @ fit.cov @ lmat.T
    q = int(np.linalg.matrix_rank(cov, hermitian=True))
    if q == 0:
        return Wald(math.nan, lmat.shape[0], math.nan, False)
    w = float(value @ np.linalg.pinv(cov, hermitian=True) @ value)
    return Wald(w, q, float(stats.f.sf(w / q, q, nu)), True)


# -- models -------------------------------------------------------------------------------
def _extend(problems: Sequence[Problem], cand: Candidate) -> list[Problem] | None:
    """Each member with ``cand``'s term appended, its parameters in one box for all
    members (the union of each member's bounds: the term is shared); None when the
    candidate does not apply to this base."""
    first = problems[0]
    if not cand.applicable(first.model, first.spec):
        return None
    ext = [cand.extend_problem(p) for p in problems]
    base_names = set(first.spec.names)
    added = [p for p in ext[0].spec.params if p.name not in base_names]
    box: dict[str, tuple[float, float]] = {}
    for q in ext:
        for p in (q.spec[a.name] for a in added):
            lo, hi = box.get(p.name, (p.lower, p.upper))
            box[p.name] = (min(lo, p.lower), max(hi, p.upper))

    def widened(p: Param) -> Param:
        return replace(p, lower=box[p.name][0], upper=box[p.name][1]) if p.name in box else p

    return [
        replace(q, spec=replace(q.spec, params=tuple(map(widened, q.spec.params)))) for q in ext
    ]


def _shape_starts(problems: Sequence[Problem], cand: Candidate) -> list[dict[str, float]]:
    """Up to :data:`MAX_STARTS` shape-parameter points: every member's grid merged, evenly
    spaced picks (``[{}]`` for a term without shape parameters)."""
    points: list[tuple[float, ...]] = []
    names: tuple[str, ...] = ()
    for p in problems:
        grid = cand.grid(p)
        if not grid:
            return [{}]
        names = tuple(grid)
        points.extend(zip(*(np.asarray(grid[n], np.float64) for n in names), strict=True))
    unique = sorted(set(points))
    pick = np.unique(np.linspace(0, len(unique) - 1, min(MAX_STARTS, len(unique))).round())
    return [dict(zip(names, unique[int(i)], strict=True)) for i in pick]


def _theta_for(jp: JointProblem, values: Mapping[str, float]) -> np.ndarray:
    """θ [D] of ``jp`` from named values: ``NAME[k]`` from ``values[NAME[k]]``, else
    ``values[NAME]``, else the member spec's init (a new term's null / grid point)."""
    out = np.empty(len(jp.names))
    init = {p.name: p.init for p in jp.problems[0].spec.params}
    for i, name in enumerate(jp.names):
        base = split_name(name)[0]
        out[i] = values.get(name, values.get(base, init.get(base, 0.0)))
    return out


def _named(fit: JointFit) -> dict[str, float]:
    return dict(zip(fit.jp.names, map(float, fit.theta), strict=True))


def _added(base: Sequence[Problem], ext: Sequence[Problem]) -> tuple[list[str], list[str]]:
    """The extension's (linear, shape) parameter names: linear ones have a null value."""
    names = set(base[0].spec.names)
    new = [p for p in ext[0].spec.free if p.name not in names]
    return [p.name for p in new if not math.isnan(p.null)], [
        p.name for p in new if math.isnan(p.null)
    ]


def _contrast(names: Sequence[str], rows: Sequence[Mapping[str, float]]) -> np.ndarray:
    lmat = np.zeros((len(rows), len(names)))
    for i, row in enumerate(rows):
        for name, c in row.items():
            lmat[i, names.index(name)] = c
    return lmat


# -- leave one recording out --------------------------------------------------------------
def _predict(
    problem: Problem, per_recording: Sequence[str], values: Mapping[str, float], sigma: float
) -> float:
    """Weighted cost ``E_k/s_k²`` of ``problem`` with every parameter fixed at ``values``
    except its own per-recording ones, refitted (LM from ``values``)."""

    def fix(p: Param) -> Param:
        if p.free and p.name not in per_recording and p.name in values:
            v = float(values[p.name])
            return replace(p, init=v, free=False, lower=min(p.lower, v), upper=max(p.upper, v))
        return p

    spec = replace(problem.spec, params=tuple(map(fix, problem.spec.params)))
    prob = replace(problem, spec=spec)
    x0 = np.array([values.get(n, p.init) for n, p in zip(spec.free_names, spec.free, strict=True)])
    if x0.size:
        lo, hi = spec.lower, spec.upper
        out = refine_many(
            prob.residual_fn, np.clip(x0, lo, hi)[None], lo, hi, RefineSettings(), fast_compile=True
        )
        x0 = np.asarray(out.x)[0]
    return float(prob.cost(x0)) / sigma**2


def _fold_fit(
    members: Sequence[Problem],
    per_recording: Sequence[str],
    sigma: Sequence[float],
    keep: Sequence[int],
    start: JointFit,
) -> tuple[JointFit, bool]:
    """The fit on members ``keep`` from ``start``'s values, and whether it determines every
    shared parameter (else its prediction of a left-out member is not defined)."""
    sub = [members[k] for k in keep]
    jp = joint_problem(sub, per_recording, [sigma[k] for k in keep])
    full = _named(start)
    vals = _shared_values(start)
    for j, k in enumerate(keep):  # member k is member j of the fold
        vals.update({member_name(n, j): full[member_name(n, k)] for n in per_recording})
    fit = fit_joint(sub, per_recording, [sigma[k] for k in keep], _theta_for(jp, vals)[None])
    shared = [i for i, n in enumerate(fit.jp.names) if split_name(n)[1] is None]
    return fit, bool(fit.determined(np.eye(len(fit.jp.names))[shared]).all())


def _shared_values(fit: JointFit) -> dict[str, float]:
    """The shared parameters of a fit (a left-out member brings its own per-recording ones)."""
    return {n: v for n, v in _named(fit).items() if split_name(n)[1] is None}


# -- the judge ----------------------------------------------------------------------------
@dataclass(frozen=True)
class JointModel:
    """A joint model fitted: the config's model plus the ``active`` candidates (terms shared
    by every member, drifts one value per member), ``fit`` its joint fit."""

    fit: JointFit
    active: tuple[str, ...] = ()

    @property
    def problems(self) -> list[Problem]:
        """The members, each with the model's shared terms appended."""
        return list(self.fit.jp.problems)

    @property
    def per(self) -> tuple[str, ...]:
        """The parameters with one value per recording (the config's and the drifts')."""
        return self.fit.jp.per_recording

    @property
    def cost(self) -> float:
        return self.fit.cost


@dataclass(frozen=True)
class JointCandidateFit:
    """One candidate fitted jointly beside ``base`` (module docstring).

    Attributes:
        name: the catalogue effect, or ``drift of P``.
        effect: the catalogue effect, or :data:`DRIFT`.
        base, fitted: the joint model before and with it.
        test: the Wald test of its contrasts (eq. 1–2).
        k: the parameters it adds (a term's shape parameters included; K − 1 for a drift).
        looks: the shape starts it was fitted from (its p counts each).
        params: its own parameters ``{name: (value, σ)}`` (a drift's ``P[k]``).
    """

    name: str
    effect: str
    base: JointModel
    fitted: JointModel
    test: Wald
    k: int
    looks: int
    params: dict[str, tuple[float, float]]

    @property
    def parameter(self) -> str:
        """The drifting parameter (``""`` for a term)."""
        return self.name.removeprefix(_DRIFT_PREFIX) if self.effect == DRIFT else ""

    @property
    def n(self) -> int:
        return self.fitted.fit.jp.n

    @property
    def p_value(self) -> float:
        """Eq. 2, ``min(1, looks·p)``; NaN where the recordings do not determine it."""
        return min(1.0, self.looks * self.test.p_value) if self.test.determined else math.nan

    @property
    def delta_bic(self) -> float:
        """Eq. 3."""
        return self.test.statistic - self.k * math.log(self.n)

    @property
    def rank(self) -> float:
        """Weighted joint cost removed, less ``k·ln n`` (module docstring)."""
        return self.base.cost - self.fitted.cost - self.k * math.log(self.n)

    def passes(self, limit: float, min_delta_bic: float) -> bool:
        return self.test.determined and self.p_value < limit and self.delta_bic > min_delta_bic


@dataclass(frozen=True)
class JointJudge:
    """The judge across recordings for :func:`~fricjax.diagnose.select.select`: shared
    catalogue terms and run-to-run drifts fitted jointly, tested by Wald's statistic in the
    recordings' own noise (module docstring).

    Attributes:
        sigma: each member's weight scale ``s_k`` [N].
        nu: the degrees of freedom of eq. 2.
        effects: the catalogue entries tried.
        drift: the base parameters whose drift is tried.
        segment_s: block length of Vuong's test [s].
        standalone: a candidate no fold can judge stands on its statistics (module
            docstring: the asymmetry of opposite one-way strokes, every drift).
    """

    sigma: tuple[float, ...]
    nu: int
    effects: tuple[Candidate, ...]
    drift: tuple[str, ...]
    segment_s: float = 0.05
    standalone: bool = True

    def candidates(self, current: JointModel) -> list[str]:
        terms = [
            c.effect
            for c in self.effects
            if c.effect not in current.active and _extend(current.problems, c) is not None
        ]
        return terms + [_DRIFT_PREFIX + p for p in self.drift if p not in current.per]

    def fit(
        self, current: JointModel, names: Sequence[str], clock: Clock
    ) -> list[JointCandidateFit]:
        out = []
        for name in names:
            if clock.over("candidates"):
                clock.untested("candidates", name)
                continue
            clock.note(f"{name}: joint fit")
            if name.startswith(_DRIFT_PREFIX):
                out.append(self._drift(current, name.removeprefix(_DRIFT_PREFIX)))
            else:
                fit = self._term(current, candidate(name))
                if fit is not None:
                    out.append(fit)
        return out

    def _term(self, current: JointModel, cand: Candidate) -> JointCandidateFit | None:
        """``current`` + ``cand`` fitted jointly; the Wald test of its amplitudes."""
        ext = _extend(current.problems, cand)
        if ext is None:
            return None
        linear, shape = _added(current.problems, ext)
        jp = joint_problem(ext, current.per, self.sigma)
        base_vals = _named(current.fit)
        starts = np.stack([_theta_for(jp, {**base_vals, **pt}) for pt in _shape_starts(ext, cand)])
        tfit = fit_joint(ext, current.per, self.sigma, starts)
        test = wald(tfit, _contrast(tfit.jp.names, [{n: 1.0} for n in linear]), self.nu)
        sd = tfit.std()
        params = {n: (tfit.value(n), float(sd[tfit.jp.names.index(n)])) for n in linear + shape}
        fitted = JointModel(tfit, (*current.active, cand.effect))
        k = len(linear) + len(shape)
        return JointCandidateFit(
            cand.effect, cand.effect, current, fitted, test, k, starts.shape[0], params
        )

    def _drift(self, current: JointModel, name: str) -> JointCandidateFit:
        """``current`` with ``name`` one value per recording; the Wald test of
        ``name[k] = name[1]``."""
        members = current.problems
        layout = (*current.per, name)
        jp = joint_problem(members, layout, self.sigma)
        dfit = fit_joint(members, layout, self.sigma, _theta_for(jp, _named(current.fit))[None])
        names = list(dfit.jp.names)
        cols = [member_name(name, k) for k in range(len(members))]
        rows = [{cols[k]: 1.0, cols[0]: -1.0} for k in range(1, len(members))]
        test = wald(dfit, _contrast(names, rows), self.nu)
        sd = dfit.std()
        params = {c: (dfit.value(c), float(sd[names.index(c)])) for c in cols}
        label = _DRIFT_PREFIX + name
        fitted = JointModel(dfit, (*current.active, label))
        return JointCandidateFit(label, DRIFT, current, fitted, test, len(members) - 1, 1, params)

    def confirm(self, fit: JointCandidateFit) -> JointCandidateFit:
        return fit

    def base(self, fit: JointCandidateFit) -> JointModel:
        return fit.base

    def model(self, fit: JointCandidateFit) -> JointModel:
        return fit.fitted

    def place(self, fit: JointCandidateFit) -> Mapping[str, Any]:
        return location(fit)

    def gains(self, fit: JointCandidateFit) -> tuple[Gain, ...]:
        return ()

    def vuong(self, best: JointCandidateFit, other: JointCandidateFit) -> tuple[float, int]:
        """Vuong's t of ``best`` over ``other`` on the weighted joint residuals, summed per
        block of :attr:`segment_s` of each recording (module docstring)."""
        d = other.fitted.fit.residual**2 - best.fitted.fit.residual**2
        sums = []
        edges = np.cumsum([0] + [p.n_residual for p in best.fitted.problems])
        for p, (a, b) in zip(best.fitted.problems, itertools.pairwise(edges), strict=True):
            span = float(p.t[-1] - p.t[0]) if p.n > 1 else 0.0
            blocks = max(1, min(b - a, round(span / self.segment_s)))
            sums += [float(np.sum(c)) for c in np.array_split(d[a:b], blocks)]
        return vuong_t(np.asarray(sums))


def location(fit: JointCandidateFit) -> dict[str, Any]:
    """Where a candidate acts: a term's place on the first recording
    (:meth:`~fricjax.diagnose.catalogue.Candidate.location`), a drift's recordings."""
    if fit.effect == DRIFT:
        return {"recordings": [p.name for p in fit.fitted.problems]}
    own = {n: v for n, (v, _) in fit.params.items()}
    first = fit.fitted.problems[0]
    return candidate(fit.effect).location({**first.spec.as_dict(), **own}, first)


@dataclass
class LeaveOneOut:
    """Leave one recording out (module docstring): a :class:`~fricjax.diagnose.select.Check`
    of :class:`JointModel` s, one part per fold. ``cache``: the current model's fold fits
    (every candidate of a step is judged against the same one)."""

    sigma: tuple[float, ...]
    cache: dict[JointFit, dict[int, tuple[JointFit, bool]]] = field(default_factory=dict)

    def judge(self, before: JointModel, after: JointModel, place: Mapping[str, Any]) -> Verdict:
        check = "leave one recording out"
        names = [p.name for p in before.problems]
        on = f"{len(names)} recordings, each left out in turn"
        if len(after.per) > len(before.per):
            return Verdict(
                check,
                on,
                False,
                why="a drift is a value per recording; left out, a recording's own value is "
                "refitted on it, which always gains",
            )
        per, sigma = before.per, self.sigma
        # keyed by the fit itself (hashed by identity), which the cache keeps alive: an id()
        # could be reused by a later fit once the first is collected
        folds = self.cache.setdefault(before.fit, {})
        parts = []
        for k in range(len(names)):
            keep = [j for j in range(len(names)) if j != k]
            if k not in folds:
                folds[k] = _fold_fit(before.problems, per, sigma, keep, before.fit)
            bfit, b_ok = folds[k]
            efit, e_ok = _fold_fit(after.problems, per, sigma, keep, after.fit)
            fold = f"{names[k]} left out"
            if not (b_ok and e_ok):
                why = "the other recordings do not determine every shared parameter"
                parts.append(Verdict(check, fold, False, why=why))
                continue
            own = {n: before.fit.value(member_name(n, k)) for n in per}
            e_base = _predict(before.problems[k], per, {**_shared_values(bfit), **own}, sigma[k])
            e_term = _predict(after.problems[k], per, {**_shared_values(efit), **own}, sigma[k])
            parts.append(Verdict(check, fold, True, 1 - e_term / e_base, e_base, e_term))
        judged = [v for v in parts if v.judged]
        if not judged:
            why = "no recording can be left out with the term still determined by the others"
            return Verdict(check, on, False, why=why, parts=tuple(parts))
        cost_base = sum(v.cost_base for v in judged)
        cost_term = sum(v.cost_term for v in judged)
        gain = 1 - cost_term / cost_base
        return Verdict(check, on, True, gain, cost_base, cost_term, parts=tuple(parts))


# -- the diagnosis ------------------------------------------------------------------------
@dataclass
class AcrossDiagnosis:
    """What :func:`diagnose_across` found: the selection's ``steps`` (typed), the
    ``findings`` they make (diagnosis.json's layout, as for one recording), the recordings,
    the base and final joint fits, the settings and the clock."""

    recordings: list[dict[str, Any]]
    steps: list[Step[JointModel, JointCandidateFit]]
    findings: list[Finding]
    base: JointModel
    final: JointModel
    settings: dict[str, Any]
    clock: Clock

    def to_json(self) -> dict[str, Any]:
        return {
            "kind": "diagnosis across recordings",
            "recordings": self.recordings,
            "findings": [f.as_json() for f in self.findings],
            "fit": {"before": _fit_summary(self.base), "after": _fit_summary(self.final)},
            "candidates": [
                {
                    "step": i + 1,
                    "limit_p": st.limit,
                    "min_delta_bic": st.min_delta_bic,
                    "tested": [_candidate_json(f, outcome(st, f)) for f in st.fits],
                }
                for i, st in enumerate(self.steps)
            ],
            "settings": self.settings,
            "not_tested": self.clock.not_tested(),
            "timing": self.clock.summary(),
        }


def diagnose_across(
    problems: Sequence[Problem],
    identify_settings: IdentifySettings,
    joint: JointSettings,
    *,
    rule: Rule | None = None,
    effects: Sequence[str] | None = None,
    clock: Clock | None = None,
) -> AcrossDiagnosis:
    """The diagnosis across ``problems`` (module docstring): the joint fit, then forward
    selection among shared catalogue terms and run-to-run drifts.

    ``rule``: the levels (default :class:`~fricjax.diagnose.select.Rule`); ``effects``: the
    catalogue entries to try (default: all); ``clock``: stages, progress and time limits
    (default :func:`across_clock`)."""
    if len(problems) < 2:
        raise FricjaxError("diagnose: a diagnosis across recordings needs at least two")
    rule = rule or Rule()
    clock = clock or across_clock()
    cands = tuple(candidate(e) for e in effects) if effects is not None else tuple(CATALOGUE)
    evidence = [record_noise(p) for p in problems]
    nu = min(effective_dof(e.noise) for e in evidence)
    per = tuple(joint.per_recording)

    with clock.stage("base_fit", "joint fit of the config's model"):
        run = identify_joint(problems, identify_settings, joint)
        sigma = tuple(float(m["sigma"]) for m in json.loads(str(run.attrs["members"])))
        jp0 = joint_problem(problems, per, sigma)
        theta0 = _theta_for(jp0, dict(zip(run.names, run.value, strict=True)))
        base = JointModel(fit_joint(problems, per, sigma, theta0[None]))
    drift = tuple(n for n in problems[0].spec.free_names if n not in per)
    judge = JointJudge(sigma, nu, cands, drift)
    steps = select(judge, [LeaveOneOut(sigma)], base, rule, clock)
    named = [st.chosen for st in steps if st.chosen is not None]
    final = named[-1].fit.fitted if named else base
    findings = [_finding(d, nu, st.limit) for st in steps if (d := st.chosen) is not None]
    findings += [
        refused(best, rest, location(best.fit), _candidate_json(best.fit, "refused (held out)"))
        for best, rest in refused_by_step(steps)
    ]
    recordings = [
        {
            "name": p.name,
            "source": p.source,
            "sha256": p.checksum,
            "n": p.n_residual,
            "sigma_weight_N": s,
            "sigma_x_m": e.sigma_x,
            "nu": e.nu,
            "direction": _direction(p),
        }
        for p, s, e in zip(problems, sigma, evidence, strict=True)
    ]
    settings = {
        "alpha": rule.alpha,
        "min_delta_bic": rule.min_delta_bic,
        "max_terms": rule.max_terms,
        "ambiguity": rule.ambiguity,
        "nu": nu,
        "per_recording": list(per),
        "effects": [c.effect for c in cands],
        "drift": list(drift),
    }
    return AcrossDiagnosis(recordings, steps, findings, base, final, settings, clock)


def _fit_summary(m: JointModel) -> dict[str, Any]:
    fit = m.fit
    sd = fit.std()
    return {
        "cost": fit.cost,
        "n": fit.jp.n,
        "parameters": {n: _pm(v, s) for n, v, s in zip(fit.jp.names, fit.theta, sd, strict=True)},
        "member_cost": [float(c) for c in fit.member_cost],
    }


def _candidate_json(f: JointCandidateFit, verdict: str) -> dict[str, Any]:
    return {
        "name": f.name,
        "effect": f.effect,
        **({"parameter": f.parameter} if f.parameter else {}),
        "statistic": f.test.statistic,
        "dof": f.test.dof,
        "k": f.k,
        "looks": f.looks,
        "p_value": f.p_value,
        "delta_bic": f.delta_bic,
        "cost": {"before": f.base.cost, "after": f.fitted.cost},
        "params": {n: _pm(v, s) for n, (v, s) in f.params.items()},
        "verdict": verdict,
    }


def _finding(d: Decision[JointCandidateFit], nu: int, level: float) -> Finding:
    """One named finding (one recording's layout, plus ``name``, ``sigma``, Wald's
    statistic and, for a drift, ``parameter``, ``values`` and ``moved``: the recordings
    whose value moved, at the step's ``level``)."""
    f = d.fit
    evidence: dict[str, Any] = {
        "sigma": {n: s for n, (_, s) in f.params.items()},
        "statistic": f.test.statistic,
        "dof": f.test.dof,
        "test": "Wald, joint equation error in the recordings' own noise",
    }
    if f.effect == DRIFT:
        members = f.fitted.problems
        cols = list(f.params)
        # of two recordings, neither is the odd one out
        moved = _moved(f.fitted.fit, cols, nu, level) if len(members) > 2 else []
        evidence |= {
            "parameter": f.parameter,
            "values": [
                {"recording": p.name, **_pm(*f.params[c])}
                for p, c in zip(members, cols, strict=True)
            ],
            "moved": [members[k].name for k in moved],
        }
    return Finding(
        effect=f.effect,
        name=f.name,
        explanation=_explain(f, evidence, d),
        location=location(f),
        params=_values(f),
        delta_bic=f.delta_bic,
        p_value=f.p_value,
        heldout=d.verdicts,
        alternatives=tuple(
            Finding(
                effect=a.fit.effect,
                name=a.fit.name,
                explanation="",
                location=location(a.fit),
                params=_values(a.fit),
                delta_bic=a.fit.delta_bic,
                p_value=a.fit.p_value,
                evidence={"vuong_t": a.t, "vuong_p": a.p_value},
            )
            for a in d.alternatives
        ),
        evidence=evidence,
    )


def _values(f: JointCandidateFit) -> dict[str, float]:
    return {n: v for n, (v, _) in f.params.items()}


def _explain(
    f: JointCandidateFit, evidence: Mapping[str, Any], d: Decision[JointCandidateFit]
) -> str:
    """The finding in words: what, the test, the held-out check, the rivals."""
    if f.effect == DRIFT:
        unit = f.base.problems[0].spec[f.parameter].unit
        parts = ", ".join(
            f"{v['value']:.4g} ± {v['sigma']:.2g}" if v["sigma"] else f"{v['value']:.4g}"
            for v in evidence["values"]
        )
        text = (
            f"{f.parameter} differs between the recordings beyond its σ: {parts} {unit} "
            f"(W = {f.test.statistic:.1f} on {f.test.dof} degrees of freedom, "
            f"{p_text(f.p_value)})"
            + (
                f"; it moved in {', '.join(evidence['moved'])}."
                if evidence["moved"]
                else "; which recording moved, these cannot tell."
            )
        )
    else:
        first = f.fitted.problems[0]
        text = candidate(f.effect).explain({**first.spec.as_dict(), **_values(f)}, first)
        held = next((v for v in d.verdicts if v.judged), None)
        if held is not None:
            text += (
                f" Leaving one recording out, it predicts the left-out ones better: their "
                f"cost falls from {held.cost_base:.4g} to {held.cost_term:.4g} (in units of "
                "each recording's weight)."
            )
        else:
            text += (
                " No recording can be left out with the term still determined by the others, "
                "so it rests on its p-value and ΔBIC across all of them."
            )
    if d.alternatives:
        names = ", ".join(a.fit.name for a in d.alternatives)
        text += (
            f" These recordings cannot tell it from {names}: each explains them about as "
            "well (Vuong's test not significant)."
        )
        dirs = {_direction(p) for p in f.fitted.problems}
        if dirs == {"forward", "backward"}:
            text += (
                " Each recording moves one way only: a stroke that moves both ways would "
                "tell a direction asymmetry from a level that changed between runs."
            )
    return text


def _pm(value: float, sd: float) -> dict[str, float | None]:
    return {"value": float(value), "sigma": float(sd) if math.isfinite(sd) else None}


def _direction(problem: Problem) -> str:
    v = np.asarray(problem.v)
    share = float(np.mean(v > 0)) if v.size else 0.5
    if share > 0.95:
        return "forward"
    if share < 0.05:
        return "backward"
    return "both"


def _moved(fit: JointFit, cols: Sequence[str], nu: int, level: float) -> list[int]:
    """The members whose value moved: removed greedily, the one furthest (in σ) from the
    inverse-variance mean of the rest first, until the rest agree at ``level``."""
    idx = [fit.jp.names.index(c) for c in cols]
    rest, moved = list(range(len(cols))), []
    while len(rest) >= 2:
        rows = np.zeros((len(rest) - 1, len(fit.theta)))
        for i, k in enumerate(rest[1:]):
            rows[i, idx[k]], rows[i, idx[rest[0]]] = 1.0, -1.0
        test = wald(fit, rows, nu)
        if not (test.determined and test.p_value < level):
            break
        var = np.array([fit.cov[idx[k], idx[k]] for k in rest])
        val = np.array([fit.theta[idx[k]] for k in rest])
        z = []
        for i in range(len(rest)):
            w = np.delete(1.0 / var, i)
            mean = float(np.delete(val, i) @ w / w.sum())
            z.append(abs(val[i] - mean) / math.sqrt(var[i] + 1.0 / w.sum()))
        # ties (two recordings) go to the later one: the first is the reference
        worst = max(range(len(rest)), key=lambda i: (round(z[i], 9), i))
        moved.append(rest.pop(worst))
    return sorted(moved)
