"""Diagnosis across recordings of one plant, on their joint fit (:mod:`fricjax.joint`).

``K`` recordings (members) of one axis share the config's model; the config's
``[joint].per_recording`` parameters take one value per recording. On the joint fit
(:func:`fricjax.joint.identify_joint`, each member's residual over its noise scale
``s_k``) two questions are asked:

1. **The catalogue across recordings.** Each applicable effect of
   :data:`fricjax.diagnose.catalogue.CATALOGUE` is added to the joint model as a *shared*
   term (one value of its parameters for all recordings) and fitted jointly
   (Levenberg–Marquardt from the current fit, the term's amplitudes at their null and its
   shape parameters at up to :data:`MAX_STARTS` points of its grid). Direction asymmetry
   from strokes that each move one way only comes out here: no single stroke sees it,
   the strokes together do.
2. **Run-to-run drift.** Each free base parameter ``P`` that the config does not already
   declare per recording is given one value per recording, ``P[1] … P[K]`` (the layout of
   :func:`fricjax.joint.joint_problem`), and the hypothesis ``P[1] = … = P[K]`` tested.

The statistic and its variance. Both tests compare nested joint models: the larger one's
extra directions are ``q`` linear contrasts ``Lθ`` (a term's amplitudes ``β``, null 0; or
``P[k] − P[1]``, k = 2 … K). The test is Wald's,

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
the recordings are combined, never the test's size. It holds no white excess (unlike the σ
that ``identify`` reports, :func:`fricjax.refine.uncertainty_at`): the excess is the misfit
under test. Under the null (linearised) ``W ~ χ²_q``; σ̂_x² is itself estimated with ν
degrees of freedom (:func:`fricjax.diagnose.evidence.effective_dof`), so

    p = P[F(q, ν) > W/q],   ν = min_k ν_k                                  (2)

(the smallest ν over the recordings: the most cautious reference). A contrast that the
data do not determine (it has a component along a null direction of A, as the Coulomb
level and an asymmetry on one stroke) is *not testable* and is reported so.

The bars. A term or a drift is named when (a) ``p < α/M`` (Bonferroni over the M
candidates, or the M parameters tested for drift; a term with shape parameters scanned
from G starts counts G times, ``p·G``), (b) the Bayesian information criterion with the
noise variance known,

    ΔBIC = W − (q + q_shape)·ln n,   n = Σ_k n_k                            (3)

exceeds ``min_delta_bic`` (W stands for the likelihood ratio it equals to first order;
``q_shape`` the term's shape parameters), and, for a term, (c) **leave one recording out**:
for each member k, the current model and the model with the term are fitted on the other
K − 1 recordings, then each predicts recording k with its shared parameters fixed and k's
own per-recording parameters refitted; the gain ``Σ_k (E_k^base − E_k^term)/s_k²`` over
the folds must be positive. A fold whose K − 1 recordings leave a shared parameter
undetermined (two opposite one-way strokes: one stroke cannot tell the Coulomb level from
the asymmetry) cannot judge and says so; when no fold can, the term stands on (a) and (b)
and the finding says that the held-out check was not possible.

Order. Terms are selected first (forward, up to ``max_terms``: among those that pass,
the one that lowers the weighted joint cost most, less ``ln n`` per parameter; that ranks
the explanations by fit, while W says how sure each test is, and a wrong explanation can
score the larger W). Drift is tested next, on the model with the selected terms, forward
too: the parameter ranked first among those that pass is named and made per recording,
and the others are tested again beside it (a Coulomb level that moved in one run would
otherwise also show as a viscous level that moved, the shared Coulomb level being wrong
for that run). On one-way strokes a shared asymmetry and a Coulomb level that differs per
stroke give the same fit; the shared term is the smaller explanation (no new parameter
per recording), and the finding notes the alternative.

Time. The stages and their clock are the single-record diagnosis'
(:class:`~fricjax.diagnose.stages.Clock`): the joint fit (``base_fit``) always runs; every
later stage (``candidates``, ``heldout``, ``drift``) runs under its own limit and the total
one, checked between units of work (one candidate's fit, one fold, one parameter's drift
fit): a stage that hits a limit stops there, and what it left out is reported; a candidate
or parameter left untested is never named.
"""

from __future__ import annotations

import itertools
import json
import math
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from jaxtyping import Float
from scipy import stats

from fricjax.diagnose.catalogue import CATALOGUE, Candidate, candidate
from fricjax.diagnose.evidence import effective_dof, record_noise
from fricjax.diagnose.run import jsonable
from fricjax.diagnose.stages import Clock, OnStage
from fricjax.errors import FricjaxError
from fricjax.identify import IdentifySettings
from fricjax.io.atomic import make_folder, write_text_atomic
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
    "MAX_STARTS",
    "STAGE_LIMITS",
    "TIME_LIMIT",
    "AcrossDiagnosis",
    "JointFit",
    "diagnose_across",
    "fit_joint",
    "wald",
    "write_across",
]

#: Shape-parameter starts per candidate (evenly spaced points of its grid, all recordings'
#: grids merged): each is one Levenberg–Marquardt start of the vmapped polish.
MAX_STARTS = 16
#: Seconds per stage (and in all) by default: an ordinary diagnosis of a few 1–30 s
#: recordings stays well inside them on two shared cores; a limit acts only when hit.
STAGE_LIMITS: dict[str, float] = {"candidates": 300.0, "heldout": 300.0, "drift": 180.0}
TIME_LIMIT = 900.0
#: A contrast is determined when its component along A's null directions is below this
#: fraction of its norm (in the column-scaled coordinates of the SVD).
_NULL_TOL = 1e-6
_SV_RCOND = 1e-10
_OUTPUTS = ("diagnosis.json", "report.md")


def across_clock(
    stage_limits: Mapping[str, float] | None = None,
    total: float | None = None,
    on_stage: OnStage | None = None,
    stop: threading.Event | None = None,
) -> Clock:
    """The clock of a diagnosis across recordings: :data:`STAGE_LIMITS` and
    :data:`TIME_LIMIT` by default, a tighter ``stage_limits`` entry (``[diagnose]``) or
    ``total`` where given."""
    limits = {
        k: min(STAGE_LIMITS.get(k, math.inf), (stage_limits or {}).get(k, math.inf))
        for k in (*STAGE_LIMITS, *(stage_limits or {}))
    }
    return Clock(
        limits=limits, total=TIME_LIMIT if total is None else total, on_stage=on_stage, stop=stop
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
    """

    jp: JointProblem
    theta: np.ndarray
    cost: float
    cov: np.ndarray
    null: np.ndarray
    scale: np.ndarray
    member_cost: np.ndarray

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


# -- the diagnosis ------------------------------------------------------------------------
@dataclass
class AcrossDiagnosis:
    """What :func:`diagnose_across` found: ``findings`` (terms then drifts, each with its
    evidence), ``tested`` (every candidate and parameter with its statistics and verdict),
    the base and final joint fits' summaries, and the time budget."""

    recordings: list[dict[str, Any]]
    findings: list[dict[str, Any]]
    tested: list[dict[str, Any]]
    fit: dict[str, Any]
    settings: dict[str, Any]
    clock: Clock

    def to_json(self) -> dict[str, Any]:
        return {
            "kind": "diagnosis across recordings",
            "recordings": self.recordings,
            "findings": self.findings,
            "tested": self.tested,
            "fit": self.fit,
            "settings": self.settings,
            "timing": self.clock.summary(),
        }


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


def _judge_term(
    cand: Candidate,
    current: list[Problem],
    fit: JointFit,
    per_recording: Sequence[str],
    sigma: Sequence[float],
    nu: int,
    n_tests: int,
    alpha: float,
    bar: float,
) -> tuple[dict[str, Any], list[Problem] | None, JointFit | None]:
    """Fit ``current`` + ``cand`` jointly and test its amplitudes (module docstring)."""
    ext = _extend(current, cand)
    record: dict[str, Any] = {"kind": "term", "name": cand.effect}
    if ext is None:
        return {**record, "verdict": "not applicable"}, None, None
    linear, shape = _added(current, ext)
    jp = joint_problem(ext, per_recording, sigma)
    base_vals = _named(fit)
    starts = np.stack([_theta_for(jp, {**base_vals, **pt}) for pt in _shape_starts(ext, cand)])
    tfit = fit_joint(ext, per_recording, sigma, starts)
    test = wald(tfit, _contrast(tfit.jp.names, [{n: 1.0} for n in linear]), nu)
    n = tfit.jp.n
    g = starts.shape[0]
    p_adj = min(1.0, test.p_value * g) if test.determined else math.nan
    dbic = test.statistic - (len(linear) + len(shape)) * math.log(n)
    sd = tfit.std()
    record.update(
        {
            "parameters": {
                name: _pm(tfit.value(name), sd[tfit.jp.names.index(name)])
                for name in linear + shape
            },
            "statistic": test.statistic,
            "dof": test.dof,
            "shape_starts": g,
            "p_value": p_adj,
            "p_threshold": alpha / n_tests,
            "delta_bic": dbic,
            "cost": {"before": fit.cost, "after": tfit.cost},
            "rank": fit.cost - tfit.cost - (len(linear) + len(shape)) * math.log(n),
        }
    )
    if not test.determined:
        record["verdict"] = "not determined by these recordings"
    elif not (p_adj < alpha / n_tests):
        record["verdict"] = "not significant"
    elif not dbic > bar:
        record["verdict"] = "below the ΔBIC bar"
    else:
        record["verdict"] = "passes p and ΔBIC"
    return record, ext, tfit


def _heldout(
    current: list[Problem],
    ext: list[Problem],
    fit: JointFit,
    tfit: JointFit,
    per_recording: Sequence[str],
    sigma: Sequence[float],
    cache: dict[int, tuple[JointFit, bool]],
    clock: Clock,
    effect: str,
) -> dict[str, Any] | None:
    """Leave-one-recording-out gain of the term (module docstring); None when the time
    limit cut it (the candidate is then not named)."""
    folds: list[dict[str, Any]] = []
    total, judged = 0.0, 0
    names = [p.name for p in current]
    for k in range(len(current)):
        if clock.over("heldout"):
            clock.skip("heldout", f"{effect}: leaving out {names[k]} (time limit)", effect)
            return None
        keep = [j for j in range(len(current)) if j != k]
        if k not in cache:
            cache[k] = _fold_fit(current, per_recording, sigma, keep, fit)
        bfit, b_ok = cache[k]
        efit, e_ok = _fold_fit(ext, per_recording, sigma, keep, tfit)
        if not (b_ok and e_ok):
            folds.append(
                {
                    "left_out": names[k],
                    "gain": None,
                    "why": "the other recordings do not determine every shared parameter",
                }
            )
            continue
        own = {n: fit.value(member_name(n, k)) for n in per_recording}
        e_base = _predict(current[k], per_recording, {**_shared_values(bfit), **own}, sigma[k])
        e_term = _predict(ext[k], per_recording, {**_shared_values(efit), **own}, sigma[k])
        folds.append({"left_out": names[k], "gain": e_base - e_term, "why": ""})
        total += e_base - e_term
        judged += 1
    return {"folds": folds, "gain": total if judged else None, "judged": judged}


def diagnose_across(
    problems: Sequence[Problem],
    identify_settings: IdentifySettings,
    joint: JointSettings,
    *,
    alpha: float = 0.01,
    min_delta_bic: float = 10.0,
    max_terms: int = 3,
    effects: Sequence[str] | None = None,
    clock: Clock | None = None,
) -> AcrossDiagnosis:
    """The diagnosis across ``problems`` (module docstring): joint fit, catalogue terms
    (shared, leave-one-recording-out), then drift of every base parameter that is shared.

    ``effects``: the catalogue entries to try (default: all); ``clock``: stages, progress
    and time limits (default :func:`across_clock`)."""
    if len(problems) < 2:
        raise FricjaxError("diagnose: a diagnosis across recordings needs at least two")
    clock = clock or across_clock()
    cands = [candidate(e) for e in effects] if effects is not None else list(CATALOGUE)
    evidence = [record_noise(p) for p in problems]
    nu = min(effective_dof(e.noise) for e in evidence)
    per = tuple(joint.per_recording)

    with clock.stage("base_fit", "joint fit of the config's model"):
        run = identify_joint(problems, identify_settings, joint)
        sigma = [float(m["sigma"]) for m in json.loads(str(run.attrs["members"]))]
        current = list(problems)
        jp0 = joint_problem(current, per, sigma)
        theta0 = _theta_for(jp0, dict(zip(run.names, run.value, strict=True)))
        fit = fit_joint(current, per, sigma, theta0[None])
    base_fit = fit
    bar = float(min_delta_bic)

    # catalogue: forward selection of shared terms ------------------------------------
    tested: list[dict[str, Any]] = []
    findings: list[dict[str, Any]] = []
    pool = [c for c in cands if _extend(current, c) is not None]
    n_tests = max(len(pool), 1)
    for c in cands:
        if c not in pool:
            tested.append({"kind": "term", "name": c.effect, "verdict": "not applicable"})
    fold_cache: dict[int, tuple[JointFit, bool]] = {}
    for _ in range(max_terms):
        if not pool:
            break
        round_records = []
        with clock.stage("candidates", "joint fits of the model with each catalogue term"):
            for c in pool:
                if clock.over("candidates"):
                    clock.untested("candidates", c.effect)
                    untested = {
                        "kind": "term",
                        "name": c.effect,
                        "verdict": "not tested (time limit)",
                    }
                    round_records.append((untested, None, None, c))
                    continue
                clock.note(f"{c.effect} added to the joint model")
                rec, ext, tfit = _judge_term(c, current, fit, per, sigma, nu, n_tests, alpha, bar)
                round_records.append((rec, ext, tfit, c))
        passing = sorted(
            (r for r in round_records if r[0]["verdict"] == "passes p and ΔBIC"),
            key=lambda r: -r[0]["rank"],
        )
        chosen = None
        with clock.stage("heldout", "leave-one-recording-out fits and predictions"):
            for rec, ext, tfit, c in passing:
                clock.note(f"{c.effect}: leaving one recording out")
                held = _heldout(current, ext, fit, tfit, per, sigma, fold_cache, clock, c.effect)
                rec["heldout"] = held
                if held is None:
                    rec["verdict"] = "held-out check cut by the time limit"
                    continue
                if held["judged"] and not held["gain"] > 0:
                    rec["verdict"] = "no held-out gain"
                    continue
                rec["verdict"] = "named"
                chosen = (rec, ext, tfit, c)
                break
        if chosen is None:
            tested.extend(r[0] for r in round_records)
            break
        rec, ext, tfit, c = chosen
        for other in round_records:
            if other[0]["verdict"] == "passes p and ΔBIC":
                other[0]["verdict"] = (
                    f"passes; {name_of(rec)} explains more (tested again beside it)"
                )
        rec["explanation"] = _explain_term(c, rec, ext, tfit)
        findings.append(rec)
        tested.extend(r[0] for r in round_records if r[3] is not c)
        tested.append(rec)
        pool = [q for q in pool if q is not c and _extend(ext, q) is not None]
        current, fit, fold_cache = ext, tfit, {}

    # drift: one value per recording of a shared base parameter, forward as the terms ----
    with clock.stage("drift", "joint fits with one parameter per recording"):
        drift_names = [n for n in problems[0].spec.free_names if n not in per]
        remaining, layout = list(drift_names), per
        while remaining:
            records = []
            for name in remaining:
                if clock.over("drift"):
                    clock.skip("drift", f"drift of {name}: not tested (time limit)")
                    records.append(
                        (
                            {"kind": "drift", "name": name, "verdict": "not tested (time limit)"},
                            None,
                        )
                    )
                    continue
                clock.note(f"{name} one value per recording")
                records.append(
                    _drift(name, current, fit, layout, sigma, nu, len(drift_names), alpha, bar)
                )
            named = [r for r in records if r[0]["verdict"] == "named"]
            if not named:
                tested.extend(r[0] for r in records)
                break
            rec, dfit = max(named, key=lambda r: r[0]["rank"])
            for other, _ in named:
                if other is not rec:
                    other["verdict"] = (
                        f"passes; {name_of(rec)} explains more (tested again beside it)"
                    )
            tested.extend(r[0] for r in records if r[0] is not rec)
            tested.append(rec)
            findings.append(rec)
            remaining.remove(rec["name"])
            layout, fit = (*layout, rec["name"]), dfit

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
    summary = {
        "before": _fit_summary(base_fit),
        "after": _fit_summary(fit),
        "terms": [f["name"] for f in findings if f["kind"] == "term"],
    }
    settings = {
        "alpha": alpha,
        "min_delta_bic": bar,
        "max_terms": max_terms,
        "nu": nu,
        "per_recording": list(per),
        "effects": [c.effect for c in cands],
    }
    return AcrossDiagnosis(recordings, findings, tested, summary, settings, clock)


def name_of(record: Mapping[str, Any]) -> str:
    """How a finding is named: ``asymmetric_friction``, ``drift of Fc``."""
    return record["name"] if record["kind"] == "term" else f"drift of {record['name']}"


def _fit_summary(fit: JointFit) -> dict[str, Any]:
    sd = fit.std()
    return {
        "cost": fit.cost,
        "n": fit.jp.n,
        "parameters": {n: _pm(v, s) for n, v, s in zip(fit.jp.names, fit.theta, sd, strict=True)},
        "member_cost": [float(c) for c in fit.member_cost],
    }


def _drift(
    name: str,
    current: list[Problem],
    fit: JointFit,
    per: Sequence[str],
    sigma: Sequence[float],
    nu: int,
    n_tests: int,
    alpha: float,
    bar: float,
) -> tuple[dict[str, Any], JointFit]:
    """Joint fit with ``name`` per recording (beside the ``per`` ones); the Wald test of
    ``name[k] = name[1]`` and the recordings where it moved (module docstring)."""
    k_count = len(current)
    layout = (*per, name)
    jp = joint_problem(current, layout, sigma)
    dfit = fit_joint(current, layout, sigma, _theta_for(jp, _named(fit))[None])
    names = list(dfit.jp.names)
    cols = [member_name(name, k) for k in range(k_count)]
    rows = [{cols[k]: 1.0, cols[0]: -1.0} for k in range(1, k_count)]
    test = wald(dfit, _contrast(names, rows), nu)
    sd = dfit.std()
    values = [
        {
            "recording": p.name,
            **_pm(dfit.value(c), sd[names.index(c)]),
        }
        for p, c in zip(current, cols, strict=True)
    ]
    dbic = test.statistic - (k_count - 1) * math.log(dfit.jp.n)
    record: dict[str, Any] = {
        "kind": "drift",
        "name": name,
        "values": values,
        "statistic": test.statistic,
        "dof": test.dof,
        "p_value": test.p_value,
        "p_threshold": alpha / n_tests,
        "delta_bic": dbic,
        "cost": {"before": fit.cost, "after": dfit.cost},
        "rank": fit.cost - dfit.cost - (k_count - 1) * math.log(dfit.jp.n),
    }
    if not test.determined:
        record["verdict"] = "not determined by these recordings"
    elif not test.p_value < alpha / n_tests:
        record["verdict"] = "not significant"
    elif not dbic > bar:
        record["verdict"] = "below the ΔBIC bar"
    else:
        record["verdict"] = "named"
        moved = _moved(dfit, cols, nu, alpha / n_tests)
        record["moved"] = [current[k].name for k in moved]
        unit = current[0].spec[name].unit
        parts = ", ".join(
            f"{v['value']:.4g} ± {v['sigma']:.2g}" if v["sigma"] else f"{v['value']:.4g}"
            for v in values
        )
        record["explanation"] = (
            f"{name} differs between the recordings beyond its σ: {parts} {unit} "
            f"(W = {test.statistic:.1f} on {test.dof} degrees of freedom, p = "
            f"{test.p_value:.2g}); it moved in {', '.join(record['moved'])}."
        )
    return record, dfit


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


def _explain_term(cand: Candidate, rec: dict[str, Any], ext: list[Problem], tfit: JointFit) -> str:
    params = {**{p.name: p.init for p in ext[0].spec.params}, **_named(tfit)}
    text = cand.explain({k: v for k, v in params.items() if split_name(k)[1] is None}, ext[0])
    held = rec.get("heldout") or {}
    if held.get("judged"):
        text += (
            f" Leaving one recording out, it predicts the left-out ones better by "
            f"{held['gain']:.3g} (in units of each recording's noise)."
        )
    else:
        text += (
            " No recording can be left out with the term still determined by the others, "
            "so it rests on its p-value and ΔBIC across all of them."
        )
    dirs = {_direction(p) for p in ext}
    if cand.effect == "asymmetric_friction" and dirs == {"forward", "backward"}:
        text += (
            " Each recording moves one way only: a Coulomb level that differed between the "
            "runs would fit the same; a repeated stroke in one direction tells them apart."
        )
    return text


# -- output -------------------------------------------------------------------------------
def report_markdown(diag: AcrossDiagnosis) -> str:
    """report.md: the recordings, the findings with their evidence, every test, time."""
    d = diag.to_json()
    lines = ["# Diagnosis across recordings", ""]
    lines += [
        "| # | recording | direction | σ_x [m] | ν | s_k [N] |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for k, r in enumerate(d["recordings"], 1):
        lines.append(
            f"| {k} | {r['name']} | {r['direction']} | {r['sigma_x_m']:.3g} | {r['nu']} | "
            f"{r['sigma_weight_N']:.4g} |"
        )
    lines += ["", "## Findings", ""]
    if not d["findings"]:
        lines.append("Nothing found: no catalogue term and no drift passes the bars.")
    for f in d["findings"]:
        lines.append(f"- **{f['name']}** ({f['kind']}): {f['explanation']}")
        lines.append(
            f"  W = {f['statistic']:.2f} ({f['dof']} dof), {p_text(f['p_value'])} "
            f"(bar {f['p_threshold']:.3g}), ΔBIC = {f['delta_bic']:.1f}"
        )
        for fold in (f.get("heldout") or {}).get("folds", []):
            gain = "not judged: " + fold["why"] if fold["gain"] is None else f"{fold['gain']:.3g}"
            lines.append(f"  - left out {fold['left_out']}: gain {gain}")
    lines += ["", "## Every test", "", "| kind | name | W | p | ΔBIC | verdict |"]
    lines.append("| --- | --- | --- | --- | --- | --- |")
    for t in d["tested"]:
        w, p, b = t.get("statistic"), t.get("p_value"), t.get("delta_bic")
        cell = [
            f"{w:.2f}" if isinstance(w, float) and math.isfinite(w) else "",
            f"{p:.3g}" if isinstance(p, float) and math.isfinite(p) else "",
            f"{b:.1f}" if isinstance(b, float) and math.isfinite(b) else "",
        ]
        lines.append(f"| {t['kind']} | {t['name']} | {' | '.join(cell)} | {t['verdict']} |")
    timing = d["timing"]
    lines += ["", "## Time", "", f"{timing['total_s']:.1f} s in all."]
    for stage, s in timing["stages_s"].items():
        lines.append(f"- {stage}: {s:.1f} s")
    for item in timing["skipped"]:
        lines.append(f"- time limit ({item['limit']}) at {item['stage']}: {item['what']}")
    return "\n".join(lines) + "\n"


def write_across(diag: AcrossDiagnosis, out: str | Path) -> dict[str, Path]:
    """Write DIR/diagnosis.json and DIR/report.md (atomic)."""
    folder = make_folder(out)
    text = json.dumps(jsonable(diag.to_json()), indent=2, ensure_ascii=False)
    return {
        "json": write_text_atomic(folder / _OUTPUTS[0], text + "\n"),
        "report": write_text_atomic(folder / _OUTPUTS[1], report_markdown(diag)),
    }
