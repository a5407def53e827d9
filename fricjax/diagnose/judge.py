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
started within a grid cell of a peak converges to it, so the best point is enough when the
ranking is right; the second local maximum guards against a ranking bent by the
equation error's preprocessing bias. Every start costs one output-error fit, so the count
is kept at two.

All output-error fits of the candidates go through :func:`fit_candidates`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float
from scipy import stats

from fricjax.diagnose.catalogue import CATALOGUE, Candidate, candidate
from fricjax.diagnose.evidence import NearRest
from fricjax.model.simulate import simulate
from fricjax.output_error import OutputErrorFit, OutputErrorSettings, fit_output_error
from fricjax.params import ParamSpec
from fricjax.problem import EquationError, Problem

__all__ = [
    "CandidateFit",
    "Fitted",
    "fit_base",
    "fit_candidates",
    "judge",
    "lack_of_fit_p",
    "starts",
]


@dataclass(frozen=True)
class Fitted:
    """A model fitted to the record by output error: ``problem`` carries the model and spec,
    ``fit`` the output-error fit (cost in σ_x²)."""

    problem: Problem
    fit: OutputErrorFit

    @property
    def theta(self) -> np.ndarray:
        """Free parameters [d] at the optimum (the problem's spec order)."""
        return self.problem.spec.flatten(self.fit.params)

    @property
    def cost(self) -> float:
        """E at the optimum [σ_x²]."""
        return float(self.fit.cost)


@dataclass(frozen=True)
class CandidateFit:
    """One candidate fitted next to ``base`` (module docstring).

    Attributes:
        effect: catalogue name.
        fitted: base + term at its best start.
        base: the base fit its LR is taken against (the lower of the two, docstring).
        k: the term's free parameters.
        lr, p_value, delta_bic: the statistic (module docstring).
        params: the term's own parameters [SI].
    """

    effect: str
    fitted: Fitted
    base: Fitted
    k: int
    lr: float
    p_value: float
    delta_bic: float
    params: dict[str, float]

    def passes(self, limit: float, min_delta_bic: float) -> bool:
        """Significant at ``limit`` (the per-candidate α) and ΔBIC above ``min_delta_bic``."""
        return self.p_value < limit and self.delta_bic > min_delta_bic


def applicable(problem: Problem) -> list[Candidate]:
    """The catalogue entries the judge tries on ``problem``'s model."""
    return [c for c in CATALOGUE if c.simulable and c.applicable(problem.model, problem.spec)]


def fit_base(problem: Problem, start: Mapping[str, float], settings: OutputErrorSettings) -> Fitted:
    """The base model fitted by output error from ``start`` (named values)."""
    return Fitted(problem, fit_output_error(problem, dict(start), settings))


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


def fit_candidates(
    base: Fitted,
    candidates: Sequence[tuple[str, Sequence[Mapping[str, float]]]],
    settings: OutputErrorSettings,
    nu: int,
) -> list[CandidateFit]:
    """Every candidate ``(effect, starts)`` fitted by output error from ``base``'s optimum
    (amplitudes at their null, nonlinear parameters at each start), the best start kept,
    judged against ``base`` (module docstring). The one place where the candidates'
    output-error fits run."""
    problem, n = base.problem, base.problem.n
    states = (base.fit.states_x, base.fit.states_v)
    out = []
    for effect, nl_starts in candidates:
        best: Fitted | None = None
        for nl in nl_starts or ({},):
            ext = candidate(effect).extend_problem(problem, nl)
            fit = fit_output_error(ext, dict(base.fit.params), settings, states)
            if best is None or fit.cost < best.fit.cost:
                best = Fitted(ext, fit)
        assert best is not None
        k = best.problem.spec.n_free - problem.spec.n_free
        lr, p, dbic = _judge_numbers(base.cost, best.fit, k, n, nu)
        own = {q: float(v) for q, v in best.fit.params.items() if q not in problem.spec}
        if effect == "mass_error":
            own = {"mass_eps": float(best.fit.params["mass_eps"])}
        out.append(CandidateFit(effect, best, base, k, lr, p, dbic, own))
    return out


def rebased(cf: CandidateFit, settings: OutputErrorSettings, nu: int) -> CandidateFit:
    """``cf`` judged against the lower of its base and the base refitted from where the
    candidate's fit ended (module docstring)."""
    problem = cf.base.problem
    fit = fit_output_error(
        problem,
        dict(cf.fitted.fit.params),
        settings,
        (cf.fitted.fit.states_x, cf.fitted.fit.states_v),
    )
    if fit.cost >= cf.base.cost:
        return cf
    base = Fitted(problem, fit)
    lr, p, dbic = _judge_numbers(base.cost, cf.fitted.fit, cf.k, problem.n, nu)
    return replace(cf, base=base, lr=lr, p_value=p, delta_bic=dbic)


def lack_of_fit_p(fitted: Fitted, nu: int) -> float:
    """p of a model's output-error cost against the record's noise: E over its
    ``ν_r = n_residual − d − 2S`` residual degrees of freedom (d parameters, S segments' two
    states) follows ``F(ν_r, ν)`` when the model is right."""
    f = fitted.fit
    dof = max(f.n_residual - fitted.problem.spec.n_free - 2 * f.n_segments, 1)
    return float(stats.f.sf(f.cost / dof, dof, nu))


def simulation_error(fitted: Fitted) -> float:
    """RMS of x_sim − x [m] of one open-loop simulation over the whole record from its first
    recorded state (the figure a user sees when replaying the model); NaN where the
    simulator rejects the model."""
    pb = fitted.problem
    p = pb.spec.unflatten(jnp.asarray(fitted.theta))
    try:
        traj = simulate(
            pb.model,
            p,
            jnp.asarray(pb.t),
            float(pb.x[0]),
            float(pb.v[0]),
            jnp.asarray(pb.u),
        )
    except Exception:  # a model the simulator rejects: report no figure rather than fail
        return math.nan
    err = np.asarray(traj.x) - pb.x
    return float(np.sqrt(np.mean(err**2)))


def record_gains(before: Fitted, after: Fitted) -> tuple[float, float]:
    """Relative gains ``1 − after/before`` of the record's own EMS [N²] (equation error at
    the output-error optimum) and open-loop simulation error [m]: a term that wins the test
    statistic but worsens what the user sees stands in for something else."""
    ems = 1 - after.problem.ems(after.theta) / before.problem.ems(before.theta)
    sim_b, sim_a = simulation_error(before), simulation_error(after)
    sim = 1 - sim_a / sim_b if math.isfinite(sim_a) and math.isfinite(sim_b) else math.nan
    return float(ems), float(sim)


# -- starts --------------------------------------------------------------------------------


@eqx.filter_jit
def _columns(fn: EquationError, thetas: Float[Array, "B d"]) -> Float[Array, "B n"]:
    """Equation-error residuals [N] at a batch of parameter vectors."""
    return jax.vmap(fn)(thetas)


def starts(base: Fitted, c: Candidate, band: NearRest, n_starts: int) -> list[dict[str, float]]:
    """Up to ``n_starts`` grid points of ``c``'s nonlinear parameters, the best local maxima
    of its equation-error score at the base optimum (module docstring); ``[{}]`` for a
    candidate without nonlinear parameters."""
    problem = base.problem
    grid = c.grid(problem)
    if not grid:
        return [{}]
    ext = c.extend_problem(problem)
    spec: ParamSpec = ext.spec
    names = list(spec.free_names)
    lin = [q.name for q in c.linear_params(problem)]
    keys = list(grid)
    g = len(grid[keys[0]])
    theta0 = spec.flatten({**base.fit.params, **{q: 0.0 for q in lin}})
    rows = np.repeat(theta0[None, :], g * (1 + len(lin)), axis=0)
    for name in keys:
        rows[:, names.index(name)] = np.tile(grid[name], 1 + len(lin))
    step = {q: 0.01 * (spec[q].upper - spec[q].lower) for q in lin}
    for j, q in enumerate(lin, 1):
        rows[j * g : (j + 1) * g, names.index(q)] = step[q]
    r = np.asarray(_columns(ext.residual_fn, jnp.asarray(rows)))
    keep = ~band.mask if band.mask.shape[0] == r.shape[1] else np.ones(r.shape[1], bool)
    r = r[:, keep]
    r0 = r[:g]  # the base residual, the same at every grid point (term at its null)
    cols = np.stack([(r[j * g : (j + 1) * g] - r0) / step[q] for j, q in enumerate(lin, 1)], -1)
    # the base's own columns, projected off: what the base absorbs is no score
    jac = np.asarray(jax.jacfwd(problem.residual_fn)(jnp.asarray(base.theta)))[keep]
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


def judge(
    base: Fitted,
    band: NearRest,
    *,
    settings: OutputErrorSettings,
    nu: int,
    n_starts: int,
) -> list[CandidateFit]:
    """Every applicable candidate of ``base``'s model fitted and judged (not yet decided:
    :func:`fricjax.diagnose.run.diagnose` applies the rule)."""
    cands = applicable(base.problem)
    todo = [(c.effect, starts(base, c, band, n_starts)) for c in cands]
    return fit_candidates(base, todo, settings, nu)
