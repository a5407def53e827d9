"""Name the missing physics: score tests over the catalogue, refits, forward selection.

All statistics live in the whitened space of :mod:`fricjax.diagnose.whiten`, where the
residual noise of white displacement noise is i.i.d. N(0, σ_x²):

* Base fit re-weighted (generalised least squares): LM on the whitened residual ``W·r``.
* Score (Lagrange-multiplier) test of a candidate at its null: with ``G(θ_nl) = ∂r/∂β`` at
  β = 0 (jax.jacfwd, vmapped over a grid of the candidate's shape parameters θ_nl), whitened
  and projected off the whitened base Jacobian, ``S(θ_nl) = rᵀP_G r / σ̂²`` ~ χ²_k under H0.
  Each projected score is first centred on its mean under H0, which is not zero because
  the regressors are evaluated on the same noisy signals as the residual
  (:mod:`fricjax.diagnose.errors_in_variables`; a stateful term's columns, which are not
  sample by sample, are taken as noise-free), where that lowers the statistic: the
  estimated mean is itself noisy, so it may remove a finding but never make one.
  The family statistic is ``max_θ S``; its p-value comes from a Monte Carlo of the same max
  under H0 (the look-elsewhere effect over the grid is thus calibrated).
* Changes of the friction law itself (``Candidate.by_refit``: Stribeck drop and shape,
  asymmetry, quadratic drag, presliding lag) are tested by the likelihood ratio of a refit instead,
  ``LR = (RSS_w(base) − RSS_w(base+term))/σ̂²``, calibrated by the same null as the score
  (Wilks: under H0 LR and S agree to first order), where the record leaves more residual
  degrees of freedom than the base has parameters. The base's own nonlinear friction
  parameters bend towards such a term, so the one-step score at the base optimum sees
  little of what a refit recovers.
* The best few candidates are refitted (GLS, LM on base + term, from up to three distinct
  grid maxima of the score: :func:`refit_starts`); ΔBIC = BIC(base) − BIC(base+term) with
  ``BIC = M·ln(RSS_w/M) + k·ln M``. Where none of them is both paying and confirmed, the
  next few eligible ones are refitted, until none is left.
* The variance of every statistic is the record's own σ̂_x² (:mod:`fricjax.diagnose.evidence`,
  with ν = 2(σ̂/se)² degrees of freedom), not the residual's: the scores follow F(k, ν)
  (:func:`~fricjax.diagnose.locate.score_pvalue` with ``external`` = ν), the BIC is that
  of a known variance, ``RSS_w/σ̂² + k·ln M`` (:func:`bic_known`), a term need leave only
  one whitened dimension, and the base's lack of fit, ``(RSS_w/dof)/σ̂² ~ F(dof, ν)``, is
  tested on every record. Under a spectral whitener (a recorded drive input) the whitened
  unit is the base residual's own, and the scores follow Beta with σ̂ from the residual.
* Forward selection: add the best candidate while its p-value < α / (number of candidates)
  and ΔBIC > ``min_delta_bic``, the model leaves ``MIN_DOF_LEFT`` whitened degrees of
  freedom (1 with σ̂ from the record), and, when a ``confirm`` is given (the
  diagnosis' held-out check, :class:`fricjax.diagnose.run.Confirm`), the check favours
  it; a candidate the check refuses is set aside and the next one that passes the tests is
  asked. Repeat from the enlarged model.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float
from scipy.optimize import lsq_linear
from scipy.stats import chi2

from fricjax.diagnose.catalogue import CATALOGUE, Candidate, is_stateful
from fricjax.diagnose.errors_in_variables import (
    ScoreBias,
    basis_bias,
    candidate_bias,
    equation_error,
    score_bias,
    with_signals,
)
from fricjax.diagnose.evidence import Evidence, record_noise
from fricjax.diagnose.locate import (
    compiled_jacfwd,
    default_whitener,
    max_score_null,
    project_out,
    score_pvalue,
)
from fricjax.diagnose.stages import Clock
from fricjax.diagnose.whiten import Whitener, WhitenOp, dc_scale
from fricjax.model.system import Model
from fricjax.params import ParamSpec
from fricjax.problem import EquationError, Problem
from fricjax.refine import RefineSettings, refine
from fricjax.search.fast_compile import FAST_COMPILE


@dataclass
class Score:
    """Score test of one candidate at the current model."""

    effect: str
    stat: float  # max over the grid of the score statistic
    p_value: float  # calibrated for the max over the grid
    nonlinear: dict[str, float]  # grid point of the max
    direction: np.ndarray  # whitened, projected unit signature [M] (first principal column)
    k: int
    delta_bic_linear: float = float("nan")  # ΔBIC of a one-step (linearised) refit
    null: np.ndarray | None = None  # Monte Carlo draws of the statistic under H0 [n_mc]
    grid_size: int = 1  # G, the grid points the max runs over
    rank: int = 0  # columns of the best grid point's basis (the statistic's χ² dof)
    dof: int = 1  # residual degrees of freedom of σ̂²
    test: str = "score"  # "score", or "likelihood ratio" (by_refit candidates)
    external: int = 0  # ν of a σ̂² estimated outside the residual (0: from the residual)
    starts: list[dict[str, float]] = field(default_factory=list)  # refit start points


@dataclass
class Refit:
    """A candidate refitted together with the base model (GLS)."""

    effect: str
    model: Model
    spec: ParamSpec
    theta: np.ndarray
    rss_w: float
    bic: float
    delta_bic: float
    params: dict[str, float]  # the candidate's own parameters


@dataclass
class Step:
    """One forward-selection step: every score, the refits, and what was chosen."""

    scores: list[Score]
    refits: list[Refit]
    chosen: Refit | None
    p_value: float
    overlap: float  # |cos| between the two best candidates' signatures
    runner_up: str
    bic_base: float
    # candidates that passed the tests but not the held-out check (``confirm``), each with
    # what the check reported; and the chosen one's report
    rejected: list[tuple[Refit, dict[str, Any]]] = field(default_factory=list)
    heldout: dict[str, Any] = field(default_factory=dict)
    # p of the base's excess over the known noise (short records, :func:`lack_of_fit_p`);
    # below alpha every candidate was refitted and judged by its likelihood ratio
    lack_of_fit_p: float = 1.0
    lack_of_fit_excess: float = 0.0  # RSS_w/σ̂² − dof [1]: what the noise does not account for


@dataclass
class Selection:
    """Outcome of :func:`forward_select`."""

    steps: list[Step]
    model: Model
    spec: ParamSpec
    theta: np.ndarray
    base_theta: np.ndarray
    whitener: Whitener
    sigma: float
    extra: dict[str, Any] = field(default_factory=dict)


# -- whitened residuals in JAX -------------------------------------------------------------


class WhitenedResidual(eqx.Module):
    """``theta -> W·r(theta)`` [M]: the GLS residual of an equation-error model (metres)."""

    residual: EquationError
    op: WhitenOp

    def __call__(self, theta: Float[Array, " d"]) -> Float[Array, " M"]:
        return self.op(self.residual(theta))


def whitened_residual(
    problem: Problem, model: Model, spec: ParamSpec, wh: Whitener
) -> WhitenedResidual:
    return WhitenedResidual(equation_error(problem, model, spec), wh.module)


class PinnedResidual(eqx.Module):
    """``theta -> [W·r, mean(r)/s]`` [M + 1] (metres): the whitened residual with the
    residual's mean beside it, scaled by its own noise ``s`` (:func:`~fricjax.diagnose.
    whiten.dc_scale` [N/m]), so that the fit also honours the DC bin the whitener drops.
    Under the noise model each entry has variance σ_x²."""

    inner: WhitenedResidual
    scale: Float[Array, ""]

    def __call__(self, theta: Float[Array, " d"]) -> Float[Array, " M1"]:
        r = self.inner.residual(theta)
        return jnp.concatenate([self.inner.op(r), jnp.mean(r)[None] / self.scale])


# -- helpers -------------------------------------------------------------------------------


def bic(rss_w: float, m: int, k: int) -> float:
    """``M·ln(RSS/M) + k·ln M`` on whitened residuals."""
    return float(m * np.log(rss_w / m) + k * np.log(m))


def bic_known(rss_w: float, m: int, k: int, sigma2: float) -> float:
    """``RSS/σ² + k·ln M``: the BIC of whitened residuals whose noise variance σ² is known
    (the record's own, :mod:`fricjax.diagnose.evidence`), up to a constant."""
    return float(rss_w / sigma2 + k * np.log(m))


# Refits of a candidate with shape parameters start from this many grid points
# (:func:`refit_starts`); they share one compiled fit.
N_STARTS = 3

# The diagnosis' Jacobians and score columns run once per record and candidate, in
# milliseconds, after compiling for a second or more each: compile time is what counts.
_fast_jit = eqx.filter_jit(compiler_options=FAST_COMPILE)


def base_range(j_w: Float[np.ndarray, "M d"]) -> Float[np.ndarray, "M r"]:
    """Orthonormal basis [M, r] of the range of whitened base columns ``j_w`` [M, d] (the
    Jacobian, or the part of it free to move); singular values below 1e-10 of the largest
    do not count."""
    q, sv, _ = np.linalg.svd(j_w, full_matrices=False)
    return q[:, sv > 1e-10 * sv[0]]


def _jacobian(fn: Any, theta: np.ndarray) -> np.ndarray:
    return np.asarray(compiled_jacfwd(fn, jnp.asarray(theta)))


@_fast_jit
def _eval(fn: Any, theta: Array) -> Array:
    return fn(theta)


# -- score tests ---------------------------------------------------------------------------


def candidate_columns(
    problem: Problem,
    model: Model,
    spec: ParamSpec,
    theta: np.ndarray,
    cand: Candidate,
    wh: Whitener,
    bias: ScoreBias | None = None,
) -> tuple[np.ndarray, list[dict[str, float]], ParamSpec, Model, np.ndarray]:
    """Whitened regressor columns ``W·∂r/∂β`` at β = 0 for every grid point: [G, M, k],
    and their errors-in-variables biases ``E[colᵀ·P⊥·z]`` [G, k] (zeros without ``bias``;
    :mod:`fricjax.diagnose.errors_in_variables`)."""
    model_e, spec_e = cand.extend(model, spec, problem)
    d = spec.n_free
    n_lin = len(cand.linear_params(problem))
    grid = cand.grid(problem)
    names_nl = [q.name for q in cand.nonlinear_params(problem)]
    g_count = len(next(iter(grid.values()))) if grid else 1
    nl = (
        np.stack([np.asarray(grid[n], dtype=np.float64) for n in names_nl], axis=1)
        if names_nl
        else np.zeros((g_count, 0))
    )
    wres = whitened_residual(problem, model_e, spec_e, wh)
    base = jnp.asarray(theta)
    # free vector of the extended spec: base free params (same order), then the candidate's
    # free params; mass_error frees the base mass instead (no new term).
    extra_free = [q.name for q in spec_e.free if q.name not in spec.free_names]
    layout = _layout(spec, spec_e, extra_free, names_nl, n_lin, d)
    cols = np.asarray(_columns(wres, base, jnp.asarray(nl), layout))
    points = [dict(zip(names_nl, map(float, row), strict=True)) for row in nl]
    if bias is None:
        col_bias = np.zeros((cols.shape[0], cols.shape[2]))
    else:
        own = None
        term = cand.term(problem)
        if term is None or not is_stateful(term):
            own = np.asarray(
                _own_parts(wres.residual, base, jnp.asarray(nl), layout, jnp.asarray(bias.kappa))
            )
        col_bias = candidate_bias(bias, cols, own)
    return cols, points, spec_e, model_e, col_bias


def _layout(
    spec: ParamSpec,
    spec_e: ParamSpec,
    extra_free: list[str],
    names_nl: list[str],
    n_lin: int,
    d: int,
) -> tuple[tuple[int, ...], tuple[int, ...], tuple[int, ...], tuple[float, ...]]:
    """Index maps into the extended free vector: base slots, linear slots, nonlinear slots,
    plus the values the base spec holds for newly freed parameters (mass_error)."""
    free_e = spec_e.free_names
    base_slots = tuple(free_e.index(n) for n in spec.free_names)
    lin_names = [n for n in extra_free if n not in names_nl]
    lin_slots = tuple(free_e.index(n) for n in lin_names)
    nl_slots = tuple(free_e.index(n) for n in names_nl)
    lin_at = tuple(spec[n].init if n in spec else 0.0 for n in lin_names)
    assert len(lin_slots) == n_lin or not spec_e.free_names
    return base_slots, lin_slots, nl_slots, lin_at


def _theta_e(layout: tuple, base: Array, beta: Array, nl_row: Array) -> Array:
    """The extended free vector: base values, the candidate's linear parameters at
    ``beta`` (+ the base's value for a freed parameter), its nonlinear ones at ``nl_row``."""
    base_slots, lin_slots, nl_slots, lin_at = layout
    d_e = len(base_slots) + len(lin_slots) + len(nl_slots)
    th = jnp.zeros(d_e, dtype=jnp.float64)
    th = th.at[jnp.asarray(base_slots, dtype=int)].set(base)
    th = th.at[jnp.asarray(lin_slots, dtype=int)].set(beta + jnp.asarray(lin_at))
    if nl_slots:
        th = th.at[jnp.asarray(nl_slots, dtype=int)].set(nl_row)
    return th


@_fast_jit
def _columns(wres: Any, base: Array, nl: Array, layout: tuple) -> Array:
    n_lin = len(layout[1])

    def one(nl_row: Array) -> Array:
        return jax.jacfwd(lambda beta: wres(_theta_e(layout, base, beta, nl_row)))(
            jnp.zeros(n_lin, dtype=jnp.float64)
        )

    return jax.vmap(one)(nl)


@_fast_jit
def _own_parts(res_e: EquationError, base: Array, nl: Array, layout: tuple, kappa: Array) -> Array:
    """``Σ_s Σ_i κ_s,i·∂j_c,i/∂s_i`` [G, k] for the unwhitened candidate columns
    (:mod:`fricjax.diagnose.errors_in_variables`): sample by sample, one jvp along κ."""
    n_lin = len(layout[1])

    def one(nl_row: Array) -> Array:
        def column(x: Array, v: Array, a: Array) -> Array:
            res = with_signals(res_e, x, v, a)
            return jax.jacfwd(lambda beta: res(_theta_e(layout, base, beta, nl_row)))(
                jnp.zeros(n_lin, dtype=jnp.float64)
            )

        _, tangent = jax.jvp(column, (res_e.x, res_e.v, res_e.a), tuple(kappa))
        return jnp.sum(tangent, axis=0)

    return jax.vmap(one)(nl)


def column_basis(cols: Float[np.ndarray, "M k"]) -> Float[np.ndarray, "M r"]:
    """Orthonormal basis of ``cols``' span (QR, columns whose R diagonal falls below
    1e-10 of its largest entry dropped: a term whose columns are off span J only in part)."""
    q, rr = np.linalg.qr(cols)
    ok = np.abs(np.diag(rr)) > 1e-10 * max(1.0, float(np.abs(rr).max()))
    return q[:, ok]


class Boxed(NamedTuple):
    """The base's linearised fit with its box (:func:`boxed_base`): ``q_free`` [M, r] an
    orthonormal basis of the whitened Jacobian's columns whose parameters may move,
    ``r_free`` [M] the whitened residual with that span projected out."""

    q_free: Float[np.ndarray, "M r"]
    r_free: Float[np.ndarray, " M"]


def boxed_base(
    j_w: Float[np.ndarray, "M d"], r_w: Float[np.ndarray, " M"], theta: np.ndarray, spec: ParamSpec
) -> Boxed:
    """The parameters a linearised step of the base cannot move, and what the others leave.

    ``min_δ ‖r_w + J_w·δ‖`` with ``θ + δ`` in the box (bounded linear least squares): a
    parameter whose step ends at its bound is held there, and only the rest of J_w is
    projected out. The score tests project out all of J_w, as if every parameter could
    move; on a short record the base absorbs an effect until some parameters reach their
    box, and what they would still have to take is left in span J, where no score sees it.
    """
    # in units of each parameter's box width: the columns span ~10 decades (N against rad)
    width = np.asarray(spec.upper - spec.lower, dtype=np.float64)
    lo = np.minimum((spec.lower - theta) / width, 0.0)
    hi = np.maximum((spec.upper - theta) / width, 0.0)
    fit = lsq_linear(j_w * width, -r_w, bounds=(lo, hi), method="bvls")
    cols = j_w[:, fit.active_mask == 0]
    if cols.shape[1] == 0:
        return Boxed(np.zeros((j_w.shape[0], 0)), np.asarray(r_w, dtype=np.float64))
    q = base_range(cols)
    return Boxed(q, project_out(q, r_w))


def boxed_gains(boxed: Boxed, cols: Float[np.ndarray, "G M k"]) -> Float[np.ndarray, " G"]:
    """``‖P_c·r_free‖²`` [m²] per grid point: the fall of the residual :class:`Boxed` leaves
    when the candidate's columns (``cols`` [G, M, k], off span ``q_free``) join the base's
    movable ones, i.e. what its linearised refit would gain with the box respected.

    Only the refit's first start (:func:`refit_starts`): where the base sits at its box it
    points at the effect's place where the projected score does not (same record: the
    impact's grid point by this gain t0 = 0.165 s (truth 0.165), refit ΔBIC 143; the
    score's three starts reached 36, below a presliding lag's 57).
    """
    q = boxed.q_free
    perp = cols - np.einsum("mj,gjk->gmk", q, np.einsum("mj,gmk->gjk", q, cols))
    out = np.zeros(cols.shape[0])
    for i in range(cols.shape[0]):
        qi = column_basis(perp[i])
        out[i] = float(np.sum((qi.T @ boxed.r_free) ** 2))
    return out


def score_candidate(
    problem: Problem,
    model: Model,
    spec: ParamSpec,
    theta: np.ndarray,
    cand: Candidate,
    wh: Whitener,
    q_base: np.ndarray,
    r_perp: np.ndarray,
    sigma2: float,
    *,
    n_mc: int,
    seed: int,
    dof: int,
    bias: ScoreBias | None = None,
    external: int = 0,
    boxed: Boxed | None = None,
) -> Score:
    """Max-over-grid score test of ``cand``, calibrated by Monte Carlo; with ``bias`` each
    score is centred on its errors-in-variables mean under H0 first
    (:mod:`fricjax.diagnose.errors_in_variables`); ``external`` = ν > 0: ``sigma2`` is an
    independent estimate with ν degrees of freedom, not the residual's. ``boxed``: the
    refit's first start is the grid point of the largest :func:`boxed_gains` (the test
    itself is unchanged)."""
    cols, points, _, _, col_bias = candidate_columns(problem, model, spec, theta, cand, wh, bias)
    g, m, k = cols.shape
    perp = cols - np.einsum("mj,gjk->gmk", q_base, np.einsum("mj,gmk->gjk", q_base, cols))
    stats = np.empty(g)
    raw = np.empty(g)
    bases = []
    shifts = []
    for i in range(g):  # G ≲ 400 small QRs; the heavy part (columns) is one vmapped call
        q = column_basis(perp[i])
        bases.append(q)
        u = q.T @ r_perp
        shift = np.zeros(q.shape[1])
        if bias is not None and q.shape[1]:
            # The score's mean under H0 is not zero when the regressors carry the noise.
            # Its estimate is one draw of a noisy derivative: where the fitted friction
            # turns sharply (vs at its bound) it can be off by several σ, so it is used
            # only where it lowers the statistic: never a finding made by the correction.
            centred = basis_bias(perp[i], q, col_bias[i])
            if np.sum((u - centred) ** 2) < np.sum(u**2):
                shift = centred
        shifts.append(shift)
        stats[i] = float(np.sum((u - shift) ** 2) / sigma2) if q.shape[1] else 0.0
        raw[i] = float(np.sum(u**2) / sigma2)
    best = int(np.argmax(stats))
    # the Monte Carlo noise must live where the whitened noise lives: off the base Jacobian
    # and off the excluded samples (wh.N), with the same degrees of freedom
    nuisance = np.hstack([q_base, wh.N]) if wh.N.shape[1] else q_base
    null = max_score_null(_pad(bases, k), n_mc, seed, J_w=nuisance, dof=dof, external=external)
    rank = int(bases[best].shape[1])
    p = calibrated_p(float(stats[best]), null, g, rank, dof, external)
    q = bases[best]
    direction = q[:, 0] if q.shape[1] else np.zeros(m)
    if q.shape[1]:  # the column of the basis most aligned with the residual
        proj = q.T @ r_perp - shifts[best]
        direction = q @ proj / max(np.linalg.norm(proj), 1e-300)
    return Score(
        cand.effect,
        float(stats[best]),
        p,
        points[best],
        direction,
        k,
        null=null,
        grid_size=g,
        rank=rank,
        dof=dof,
        external=external,
        starts=[
            points[i]
            for i in refit_starts(
                stats,
                raw,
                points,
                lead=() if boxed is None else (int(np.argmax(boxed_gains(boxed, cols))),),
            )
        ],
    )


def refit_starts(
    stats: np.ndarray,
    raw: np.ndarray,
    points: list[dict[str, float]],
    n: int = N_STARTS,
    lead: Sequence[int] = (),
) -> list[int]:
    """Grid points [indices] to start a candidate's refit from: ``lead`` (each one more
    start, beyond ``n``), the statistic's maximum, the uncentred statistic's maximum, then
    the highest remaining grid points, at most ``n + len(lead)``, none a grid neighbour of
    one already chosen (index distance ≤ 1 along every shape parameter). They need not be
    local maxima (a broad peak's flank two steps out can be chosen).

    Why. A frequency, a location or a width makes the refit's cost multimodal, and the
    grid's best point is not always in the true optimum's basin (the centred and the
    uncentred maxima can lie in different ones).
    """
    names = list(points[0]) if points else []
    if not names:
        return [int(np.argmax(stats))]
    n += len(lead)
    # each grid coordinate as its rank among the values that coordinate takes
    idx = np.stack(
        [
            np.searchsorted(np.unique(v), v)
            for v in (np.array([pt[nm] for pt in points]) for nm in names)
        ],
        axis=1,
    )
    picked: list[int] = []
    for i in [*lead, int(np.argmax(stats)), int(np.argmax(raw)), *map(int, np.argsort(-stats))]:
        if len(picked) >= n:
            break
        if all(np.max(np.abs(idx[i] - idx[j])) > 1 for j in picked):
            picked.append(i)
    return picked


def calibrated_p(
    stat: float, null: np.ndarray, g: int, rank: int, dof: int, external: int = 0
) -> float:
    """p-value of a max-over-grid statistic: the Monte Carlo ``null`` [n_mc], which cannot
    resolve p below ``1/(n_mc + 1)``, or the Bonferroni bound over the G grid points (the
    single-point p from the exact law of a ``rank``-column score: Beta with σ̂ from the
    same residual, F with an ``external`` one), which is valid there and sharper."""
    p_mc = float((1 + np.sum(null >= stat)) / (1 + null.size))
    p_bonf = float(g * score_pvalue(stat, rank, dof, external)) if rank else 1.0
    return min(p_mc, p_bonf, 1.0)


def likelihood_ratio(score: Score, refit: Refit, rss_base: float, sigma2: float) -> Score:
    """``score`` with its statistic replaced by the refit's likelihood ratio
    ``(RSS_w(base) − RSS_w(refit))/σ̂²`` and re-calibrated by the same null (module
    docstring): the test of a ``by_refit`` candidate."""
    lr = max((rss_base - refit.rss_w) / sigma2, 0.0)
    p = calibrated_p(lr, score.null, score.grid_size, max(score.rank, 1), score.dof, score.external)
    nonlinear = {n: refit.params[n] for n in score.nonlinear if n in refit.params}
    return replace(score, stat=float(lr), p_value=p, nonlinear=nonlinear, test="likelihood ratio")


def _pad(bases: list[np.ndarray], k: int) -> np.ndarray:
    m = bases[0].shape[0]
    out = np.zeros((len(bases), m, k))
    for i, q in enumerate(bases):
        out[i, :, : q.shape[1]] = q
    return out


# -- refits --------------------------------------------------------------------------------


def gls_fit(
    problem: Problem,
    model: Model,
    spec: ParamSpec,
    theta0: np.ndarray,
    wh: Whitener,
    settings: RefineSettings | None = None,
) -> tuple[np.ndarray, float]:
    """Levenberg–Marquardt on the whitened residual from ``theta0``, its mean held by
    :class:`PinnedResidual` where the whitener drops DC: (theta, RSS_w = ‖W·r(theta)‖² [m²],
    the whitened part alone, the statistic every test compares)."""
    fn = whitened_residual(problem, model, spec, wh)
    theta0 = np.clip(theta0, spec.lower, spec.upper)
    assert problem.preprocess is not None  # the whitener was made from it
    scale = dc_scale(wh, problem.preprocess)
    target = fn if scale == 0.0 else PinnedResidual(fn, jnp.asarray(scale, dtype=jnp.float64))
    out = refine(
        target,
        jnp.asarray(theta0),
        spec.lower,
        spec.upper,
        settings or RefineSettings(max_steps=100, rtol=1e-8, atol=1e-8),
        # each (model, whitener) pair is fitted once or twice: compile time dominates
        fast_compile=True,
    )
    theta = np.asarray(out.x)
    if scale == 0.0:
        return theta, float(out.cost_after)
    r_w = np.asarray(_eval(fn, jnp.asarray(theta)))
    return theta, float(r_w @ r_w)


def refit_candidate(
    problem: Problem,
    model: Model,
    spec: ParamSpec,
    theta: np.ndarray,
    cand: Candidate,
    score: Score,
    wh: Whitener,
    bic_base: float,
    sigma2_known: float | None = None,
) -> Refit:
    """GLS refit of base + ``cand`` started at the base optimum and the score's grid points
    (``score.starts``, else its best one), the lowest RSS_w kept; its BIC is
    :func:`bic_known` where ``sigma2_known`` is given, else :func:`bic`."""
    model_e, spec_e = cand.extend(model, spec, problem, score.nonlinear)
    start = spec_e.init.copy()
    for i, name in enumerate(spec_e.free_names):
        if name in spec.free_names:
            start[i] = theta[spec.free_names.index(name)]
    fits = []
    for point in score.starts or [score.nonlinear]:
        # same model and spec for every start: one compiled fit
        x0 = start.copy()
        for name, value in point.items():
            x0[spec_e.free_names.index(name)] = value
        fits.append(gls_fit(problem, model_e, spec_e, x0, wh))
    theta_e, rss = min(fits, key=lambda f: f[1])
    k = spec_e.n_free
    b = bic(rss, wh.dof, k) if sigma2_known is None else bic_known(rss, wh.dof, k, sigma2_known)
    own = {
        n: float(v)
        for n, v in zip(spec_e.free_names, theta_e, strict=True)
        if n not in spec.free_names or n == "mass"
    }
    return Refit(cand.effect, model_e, spec_e, theta_e, rss, b, bic_base - b, own)


def best_supported(
    problem: Problem,
    wh: Whitener,
    thetas: Sequence[np.ndarray],
    rss_min: float,
    evidence: Evidence,
    alpha: float,
) -> np.ndarray:
    """The base parameters of least EMS [N²] among ``thetas`` [d] that the whitened metric
    cannot tell from its least-squares fit (RSS_w ``rss_min``): those inside the fit's
    likelihood-ratio confidence region, ``(RSS_w(θ) − rss_min)/σ² ≤ χ²_{r, 1−α}`` with r the
    rank of the whitened Jacobian (σ² the record's σ̂_x², or under a spectral whitener the
    fit's own ``rss_min/(dof − r)``). The first entry is the fit itself.

    Why. Every θ in that region explains the record as well as the fit does, as far as the
    noise lets the tests see; the whitened metric weighs only the band where the noise is
    known, so on a short record the fit spends its freedom on that band and can leave the
    user's own metric, the EMS, far worse than identify's. Of the equally supported fits,
    the one that is also best on the EMS is the base the diagnosis reports and tests
    from; the tests' statistics project the fitted directions out and compare RSS_w
    against ``rss_min``, so the choice within the region does not enter them."""
    spec = problem.spec
    fn = whitened_residual(problem, problem.model, spec, wh)
    j_w = _jacobian(fn, thetas[0])
    rank = int(base_range(j_w).shape[1])
    if wh.spectral:
        sigma2 = rss_min / max(wh.dof - rank, 1)
    else:
        sigma2 = evidence.sigma_x**2
    bar = float(chi2.ppf(1.0 - alpha, max(rank, 1)))
    best, best_ems = thetas[0], problem.ems(thetas[0])
    for th in thetas[1:]:
        th = np.clip(th, spec.lower, spec.upper)
        r_w = np.asarray(_eval(fn, jnp.asarray(th)))
        if (float(r_w @ r_w) - rss_min) / sigma2 > bar:
            continue
        ems = problem.ems(th)
        if ems < best_ems:
            best, best_ems = th, ems
    return np.asarray(best)


def rebase(
    problem: Problem, model: Model, spec: ParamSpec, refit: Refit, wh: Whitener
) -> tuple[np.ndarray, float]:
    """The base alone refitted (GLS) from ``refit``'s base parameters: (theta, RSS_w)."""
    start = np.array([refit.theta[refit.spec.free_names.index(n)] for n in spec.free_names])
    return gls_fit(problem, model, spec, start, wh)


# Residual degrees of freedom a model must leave for its σ̂² and its mismatch maps
# (:func:`~fricjax.diagnose.locate.locate_plan` needs 2).
MIN_DOF_LEFT = 2

# A candidate whose signature overlaps a refused one's by more than this (|cos| of their
# whitened, projected signatures) and that gains no more than it would only re-explain the
# structure the judge refused; it is not asked. One that gains more explains more than the
# refused one did. (0.5: more than half of either signature is the other's.)
SAME_STRUCTURE = 0.5


def lack_of_fit_p(rss: float, dof: int, sigma2: float, nu: int) -> float:
    """p-value of the base's excess over a noise variance known from outside the residual:
    ``F = (RSS_w/dof)/σ̂²`` against ``F(dof, ν)`` (σ̂² with ν degrees of freedom,
    :mod:`fricjax.diagnose.evidence`); ``RSS_w`` [m²] the base's whitened residual, ``dof`` the
    whitened dimensions its Jacobian leaves."""
    if dof < 1 or sigma2 <= 0:
        return 1.0
    return float(score_pvalue(rss / sigma2, dof, dof, max(nu, 1)))


def signature_overlap(a: np.ndarray, b: np.ndarray) -> float:
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na == 0 or nb == 0:
        return 0.0
    return float(abs(a @ b) / (na * nb))


# -- forward selection ---------------------------------------------------------------------


def forward_select(
    problem: Problem,
    theta: np.ndarray,
    *,
    candidates: Sequence[Candidate] = CATALOGUE,
    alpha: float = 0.01,
    min_delta_bic: float = 10.0,
    max_terms: int = 3,
    n_refit: int = 2,
    n_mc: int = 2000,
    seed: int = 0,
    noise: str = "auto",
    eiv: bool = True,
    starts: Sequence[np.ndarray] = (),
    evidence: Evidence | None = None,
    confirm: Callable[
        [tuple[Model, ParamSpec, np.ndarray], Refit], tuple[bool, dict[str, Any]]
    ] = lambda current, refit: (True, {}),
    clock: Clock | None = None,
) -> Selection:
    """Add catalogue terms one at a time while they keep paying (module docstring);
    ``noise``: the noise model of :func:`~fricjax.diagnose.locate.default_whitener`;
    ``eiv``: centre the scores on their errors-in-variables bias
    (:mod:`fricjax.diagnose.errors_in_variables`; no effect under spectral noise);
    ``starts``: further start points [d] of the base's GLS fit, the lowest RSS_w is kept
    (the whitener is always that of ``theta``); ``evidence``: the record's own noise
    (default :func:`~fricjax.diagnose.evidence.record_noise`), whose σ̂_x² with its ν
    degrees of freedom is the variance of every test and BIC (F law); only a spectral
    whitener (a recorded drive input) takes its scale from the whitened residual (Beta law).

    ``confirm(current, refit) -> (ok, report)``: the held-out check, part of the stopping
    rule (default: none, every candidate that passes the tests is ``ok``). A candidate that
    passes the tests is added only if ``ok``; otherwise it is kept in
    :attr:`Step.rejected` (never offered again) and the next candidate that passes the tests
    at this step is asked; a step with none left ends the selection.

    ``clock``: the diagnosis' stages and time limits (:mod:`fricjax.diagnose.stages`); a
    candidate a limit leaves unscored, unrefitted or unchecked is recorded there as not
    tested and never named."""
    clock = clock or Clock()
    model, spec = problem.model, problem.spec
    evidence = evidence or record_noise(problem)
    with clock.stage("whitening"):
        wh = default_whitener(problem, theta, noise, evidence.sigma_x)
        # A base left in a poorer minimum than the data allow leaves its misfit in every
        # test, where the most flexible candidate takes it for physics.
        theta_gls, rss_floor = min(
            (gls_fit(problem, model, spec, th, wh) for th in (theta, *starts)),
            key=lambda f: f[1],
        )
        theta = best_supported(problem, wh, [theta_gls, theta, *starts], rss_floor, evidence, alpha)
    base_theta = theta.copy()
    steps: list[Step] = []
    used: set[str] = set()
    first_known: float | None = None
    sigma = math.nan
    for _ in range(max_terms):
        with clock.stage("scores"):
            fn = whitened_residual(problem, model, spec, wh)
            r_w = np.asarray(_eval(fn, jnp.asarray(theta)))
            j_w = _jacobian(fn, theta)
            q_base = base_range(j_w)
            r_perp = project_out(q_base, r_w)
            dof = max(wh.dof - q_base.shape[1], 1)
            if wh.spectral:
                # a recorded drive input: the whitened unit is the base residual's spectrum
                sigma2, external = float(r_perp @ r_perp / dof), 0
            else:
                # the record's own displacement noise is the whitened variance
                sigma2, external = evidence.sigma_x**2, evidence.nu
            # With σ̂ from outside the residual, the BIC is that of a known variance: the
            # profile form M·ln(RSS/M) divides by what the residual happens to hold.
            known = sigma2 if external else None
            if not steps:
                first_known, sigma = known, math.sqrt(sigma2)
            min_left = 1 if external else MIN_DOF_LEFT
            # the base's least RSS_w: at the first step that of its GLS fit, which the
            # chosen base (best_supported) may exceed by less than its confidence region
            rss_base = min(float(r_w @ r_w), rss_floor)
            rss_floor = math.inf
            bic_base = (
                bic(rss_base, wh.dof, spec.n_free)
                if known is None
                else bic_known(rss_base, wh.dof, spec.n_free, known)
            )
            bias = score_bias(problem, model, spec, theta, wh, sigma2) if eiv else None
            pool = [cd for cd in candidates if cd.effect not in used and cd.applicable(model, spec)]
            if not pool:
                break
            # A short record leaves no more whitened dimensions than the base has
            # parameters: there the base fills its box to absorb an effect, and Wilks'
            # calibration of a refit's ratio needs a well-determined base.
            short = dof <= spec.n_free
            boxed = boxed_base(j_w, r_w, theta, spec) if short and external else None
            scores = []
            for i, cd in enumerate(pool):
                if clock.over("scores"):
                    clock.untested("scores", cd.effect)
                    continue
                clock.note(
                    f"step {len(steps) + 1}: score test of {cd.effect} ({i + 1}/{len(pool)})"
                )
                scores.append(
                    score_candidate(
                        problem,
                        model,
                        spec,
                        theta,
                        cd,
                        wh,
                        q_base,
                        r_perp,
                        sigma2,
                        n_mc=n_mc,
                        seed=seed + i,
                        dof=dof,
                        bias=bias,
                        external=external,
                        boxed=boxed,
                    )
                )
            if not scores:
                break
        by_name = {cd.effect: cd for cd in pool}
        done: dict[str, Refit] = {}
        # Short records keep the score test (Wilks needs a well-determined base), unless
        # the base leaves significant structure there (below).
        by_lr = not short
        # The whole residual, not only its part outside span J: a base held at its box (an
        # effect absorbed until amplitudes hit their bounds) leaves misfit along J too.
        lof_p = lack_of_fit_p(rss_base, dof, sigma2, external) if external else 1.0
        lof_excess = rss_base / sigma2 - dof if external else 0.0
        # On a short record the base moves far to absorb an effect, to the edges of its
        # box, and the linearised scores, which see only the residual outside span J, miss
        # what it leaves; where the base fails its lack-of-fit test against the record's
        # noise, every candidate is refitted and judged by its likelihood ratio.
        refit_all = short and bool(external) and lof_p < alpha
        lr_unfit: set[str] = set()
        for i, sc in enumerate(scores):
            if (by_lr and by_name[sc.effect].by_refit) or refit_all:
                if clock.over("refits"):
                    # its test is the likelihood ratio: unrefitted, it has none
                    clock.untested("refits", sc.effect)
                    lr_unfit.add(sc.effect)
                    continue
                with clock.stage("refits", f"likelihood-ratio refit of {sc.effect}"):
                    rf = refit_candidate(
                        problem, model, spec, theta, by_name[sc.effect], sc, wh, bic_base, known
                    )
                # The refit may have left the base's basin for a better one that the base
                # alone reaches too: the ratio is taken against the base refitted from the
                # refit's end point.
                rss_ref = min(rss_base, rebase(problem, model, spec, rf, wh)[1])
                bic_ref = (
                    bic(rss_ref, wh.dof, spec.n_free)
                    if known is None
                    else bic_known(rss_ref, wh.dof, spec.n_free, known)
                )
                done[sc.effect] = replace(rf, delta_bic=bic_ref - rf.bic)
                scores[i] = likelihood_ratio(sc, done[sc.effect], rss_ref, sigma2)
        scores = [sc for sc in scores if sc.effect not in lr_unfit]
        if not scores:
            break
        ranked = sorted(scores, key=lambda s: (s.p_value, -s.stat))
        # Linearised ΔBIC of each candidate from its statistic (for a score, one
        # Gauss-Newton step from the base optimum: the whitened RSS drops by S·σ²; for a
        # likelihood ratio, the refit's own drop); it ranks the candidates for the refits.
        lin = {
            sc.effect: (
                wh.dof * np.log(rss_base / max(rss_base - sc.stat * sigma2, 1e-300))
                if known is None
                else sc.stat
            )
            - (sc.k + len(sc.nonlinear)) * np.log(wh.dof)
            for sc in scores
        }
        eligible = sorted(
            (sc for sc in ranked if sc.p_value < alpha / len(pool)), key=lambda sc: -lin[sc.effect]
        )
        if not eligible:  # nothing significant: no refit can be accepted, spare its cost
            steps.append(
                Step(
                    scores,
                    [],
                    None,
                    ranked[0].p_value,
                    0.0,
                    ranked[1].effect if len(ranked) > 1 else "",
                    bic_base,
                    lack_of_fit_p=lof_p,
                    lack_of_fit_excess=lof_excess,
                )
            )
            for sc in scores:
                sc.delta_bic_linear = float(lin[sc.effect])
            break
        # the linearisation misjudges terms whose shape (location, width) the refit moves,
        # so the best two eligible candidates are refitted and compared by their true ΔBIC
        # The likelihood-ratio candidates are refitted already and compete as they are; the
        # refit slots go to the best score-tested ones (whose ranking is linearised).
        refits = [done[sc.effect] for sc in eligible if sc.effect in done]
        queue = [sc for sc in eligible if sc.effect not in done]
        p_of = {sc.effect: sc.p_value for sc in scores}
        direction = {sc.effect: sc.direction for sc in scores}
        rejected: list[tuple[Refit, dict[str, Any]]] = []
        asked: set[str] = set()
        chosen, report = None, {}
        # On a short record the linearised ranking can be far off and a refit is cheap: all
        # eligible candidates are refitted before any is asked, so the best true ΔBIC is
        # asked first.
        batch = len(queue) if short else max(n_refit, 1)
        while True:
            for sc in queue[:batch]:
                if clock.over("refits"):
                    clock.untested("refits", sc.effect)
                    continue
                with clock.stage("refits", f"step {len(steps) + 1}: refit of {sc.effect}"):
                    refits.append(
                        refit_candidate(
                            problem, model, spec, theta, by_name[sc.effect], sc, wh, bic_base, known
                        )
                    )
            queue = queue[batch:]
            if not refits:
                break
            by_gain = sorted(refits, key=lambda r: -r.delta_bic)
            passes = [
                p_of[rf.effect] < alpha / len(pool)
                and rf.delta_bic > min_delta_bic
                and wh.dof - rf.spec.n_free >= min_left
                for rf in by_gain
            ]
            # the best refit decides whether the step adds anything; the others that pass
            # are asked only when the held-out check rejects the one before them
            passing = (
                [rf for rf, ok in zip(by_gain, passes, strict=True) if ok] if passes[0] else []
            )
            for rf in passing:
                if rf.effect in asked:
                    continue
                asked.add(rf.effect)
                same = max(
                    (
                        signature_overlap(direction[rf.effect], direction[r.effect])
                        for r, _ in rejected
                        if r.delta_bic >= rf.delta_bic
                    ),
                    default=0.0,
                )
                if same > SAME_STRUCTURE:
                    continue
                if clock.over("heldout"):
                    # a term is named only once a held-out check has judged it
                    clock.untested("heldout", rf.effect)
                    continue
                with clock.stage(
                    "heldout", f"step {len(steps) + 1}: held-out check of {rf.effect}"
                ):
                    ok, report = confirm((model, spec, theta), rf)
                if ok:
                    chosen = rf
                    break
                rejected.append((rf, report))
                used.add(rf.effect)
            if chosen is not None or not queue:
                break
            # None of the refits so far is both paying and confirmed, and eligible
            # candidates are left: the linearised ranking can be far off, so the next ones
            # are refitted before the step gives up.
        if not refits:  # a time limit left every eligible candidate unrefitted
            for sc in scores:
                sc.delta_bic_linear = float(lin[sc.effect])
            steps.append(
                Step(
                    scores,
                    [],
                    None,
                    eligible[0].p_value,
                    0.0,
                    "",
                    bic_base,
                    [],
                    {},
                    lof_p,
                    lof_excess,
                )
            )
            break
        best = chosen or by_gain[0]
        best_score = next(sc for sc in scores if sc.effect == best.effect)
        others = [
            sc for sc in sorted(scores, key=lambda sc: -lin[sc.effect]) if sc.effect != best.effect
        ]
        overlap = signature_overlap(best_score.direction, others[0].direction) if others else 0.0
        steps.append(
            Step(
                scores,
                refits,
                chosen,
                best_score.p_value,
                overlap,
                others[0].effect if others else "",
                bic_base,
                rejected,
                report if chosen is not None else {},
                lof_p,
                lof_excess,
            )
        )
        for sc in scores:
            sc.delta_bic_linear = float(lin[sc.effect])
        if chosen is None:
            break
        used.add(chosen.effect)
        # the whitener stays that of the base fit, so every RSS_w and BIC is comparable
        model, spec, theta = chosen.model, chosen.spec, chosen.theta
    # the BIC form of the first step, for the fit figures of the whole diagnosis
    extra = {"bic_sigma2": first_known} if first_known is not None else {}
    return Selection(steps, model, spec, theta, base_theta, wh, sigma, extra)
