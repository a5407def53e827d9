"""Changes of the friction law tested by simulation (output) error, where equation error is blind.

Why. The equation error ``m·a − F*`` (seed eq. 11) of the diagnosis needs the velocity
and acceleration differentiated from x. Where ``|v| < 4σ_v`` the sign of the velocity is
noise, so those samples are held by the stick/slip rule and left out of the tests
(:func:`fricjax.diagnose.run.with_rest`), and with them most of what tells one friction
law from another near rest: how the plant stops and breaks away. On records that stick
often, a Stribeck drop or a direction-dependent friction then leaves almost nothing the
base model cannot absorb in that metric, though it changes the motion itself by many noise
standard deviations. Measured on the concealed benchmark (v2 cases, hidden term at its
true shape, fitted from the truth): a 1 s record with a Stribeck drop at c = 5 and 34 % of
its samples near rest gains LR = 9.0 σ_x² in equation error and 2720 σ_x² in output
error; a 2 s record with a Stribeck drop at c = 10, 65 % near rest: 0.6 against 210; the
same Stribeck term on a 1 s and a 2 s null record: 0.3 and 0.0 in output error.

Test. The base model (equation-error estimate as start) and base + each pointwise
friction-law candidate of :data:`LAWS` (term at its null; shape parameters free from the
middle of their grid) are fitted by output error with multiple shooting
(:func:`fricjax.output_error.fit_output_error`, costs ``E = Σ r_aug²`` in units of
``σ_x²``, σ_x from the third difference of x). With ``ν`` the residual degrees of
freedom of the larger fit (``n + 2(S − 1) − (d + k) − 2S``):

    LR = (E_base − E_term) / σ̂²,   σ̂² = E_term / ν,   p = P(χ²_k > LR)       k = the term's
                                                                             free parameters
    ΔBIC = n·ln(E_base / E_term) − k·ln n                                    n = kept samples

A candidate is named when ``p < α / len(LAWS)`` and ``ΔBIC > min_delta_bic`` (the
selection's own bars), the best by ΔBIC first, and when it also improves the held-out
check in the same metric: base and base + term are fitted on the first ``1 − fraction`` of
the record and then simulated over the rest with their parameters fixed (only the segment
states are fitted there); the gain is ``1 − E_term,test / E_base,test``. A stateful term
(presliding lag) is not tested here: the simulator integrates pointwise forces only.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from scipy import stats

from fricjax.diagnose.catalogue import candidate
from fricjax.output_error import OutputErrorFit, OutputErrorSettings, fit_output_error, noise_scale
from fricjax.problem import Problem

# The friction-law candidates the simulator can integrate (pointwise forces). The Stribeck
# shape exponent is left out: in output error its signature is that of a Stribeck drop,
# and each candidate costs two fits.
LAWS = ("stribeck", "asymmetric_friction", "quadratic_drag")

# Segment length of the multiple shooting [s]. From the equation-error estimate, where
# the base has absorbed what it cannot model by moving far from the plant's values, the
# default 0.5 s segments left LM in a poor minimum (1 s record, hidden Stribeck drop:
# E_base = 6.2e6 σ_x², against 5036 with 0.05 s segments); short segments keep every
# simulation within the noise of its own start, so the fit stays close to quadratic.
SEGMENT_S = 0.05


@dataclass
class LawFit:
    """One friction-law candidate fitted by output error next to the base."""

    effect: str
    problem: Problem  # the record with base + term
    fit: OutputErrorFit
    lr: float  # (E_base − E_term)/σ̂² [1]
    p_value: float
    delta_bic: float
    k: int  # the term's free parameters
    params: dict[str, float]  # the term's own parameters (SI units)
    cost_base: float  # E_base the ratio is taken against [σ_x²]: the lower of the two base fits


@dataclass
class SimulationTest:
    """Outcome of :func:`simulation_test`: the base fit, every candidate's, and the one
    named (``None``: none passed), with its held-out check."""

    base: OutputErrorFit
    fits: list[LawFit]
    chosen: LawFit | None
    heldout: dict[str, float] = field(default_factory=dict)
    rejected: list[tuple[LawFit, dict[str, float]]] = field(default_factory=list)


def law_fit(
    problem: Problem,
    base: OutputErrorFit,
    effect: str,
    settings: OutputErrorSettings,
) -> LawFit:
    """Base + the candidate ``effect`` fitted by output error from the base's optimum (term
    at its null, shape at its grid middle), with its LR, p-value and ΔBIC."""
    ext = candidate(effect).extend_problem(problem)
    states = (base.states_x, base.states_v)
    fit = fit_output_error(ext, dict(base.params), settings, states)
    # LM may stop short of the base's own minimum (its step limit): the ratio is taken
    # against the base refitted from where the term's fit ended, so that it measures what
    # the term explains and not what the longer descent found
    again = fit_output_error(problem, dict(fit.params), settings, (fit.states_x, fit.states_v))
    e_base = min(base.cost, again.cost)
    k = ext.spec.n_free - problem.spec.n_free
    n = problem.n
    # LM never ends above its start and the start is the base optimum with the term at its
    # null, so the nested fit is never worse than the base up to the solver's tolerance
    e_term = min(fit.cost, e_base)
    nu = max(fit.n_residual - ext.spec.n_free - 2 * fit.n_segments, 1)
    lr = (e_base - e_term) / (e_term / nu)
    return LawFit(
        effect=effect,
        problem=ext,
        fit=fit,
        lr=float(lr),
        p_value=float(stats.chi2.sf(lr, k)),
        delta_bic=float(n * np.log(e_base / e_term) - k * np.log(n)),
        k=k,
        params={q: float(v) for q, v in fit.params.items() if q not in problem.spec},
        cost_base=float(e_base),
    )


def _held_test_cost(
    train: Problem, test: Problem, start: dict[str, float], settings: OutputErrorSettings
) -> float:
    """Output-error cost on ``test`` of the model fitted on ``train`` from ``start``, its
    parameters fixed on ``test`` (only the segment states fitted there)."""
    fitted = fit_output_error(train, start, settings)
    fixed = test.spec.with_fixed({k: fitted.params[k] for k in test.spec.free_names})
    return fit_output_error(replace(test, spec=fixed), fitted.params, settings).cost


def heldout_gain(
    problem: Problem,
    base: OutputErrorFit,
    law: LawFit,
    fraction: float,
    settings: OutputErrorSettings,
) -> dict[str, float]:
    """The held-out check in output error (module docstring): ``heldout_improvement`` =
    ``1 − E_term,test / E_base,test`` on the last ``fraction`` of the record."""
    from fricjax.diagnose.run import heldout_parts

    k = round(problem.n * (1 - fraction))
    # the noise scale of the whole record, so that both parts share one unit
    settings = settings._replace(x_scale=base.x_scale)
    costs = []
    for pb, fit in ((problem, base), (law.problem, law.fit)):
        train, test = heldout_parts(replace(pb, rest=None), fraction)
        costs.append(_held_test_cost(train, test, dict(fit.params), settings))
    return {
        "heldout_improvement": float(1 - costs[1] / costs[0]),
        "heldout_cost_base": float(costs[0]),
        "heldout_cost_term": float(costs[1]),
        "heldout_samples": int(problem.n - k),
    }


def simulation_test(
    problem: Problem,
    start: dict[str, float],
    *,
    laws: Sequence[str] = LAWS,
    alpha: float = 0.01,
    min_delta_bic: float = 10.0,
    fraction: float = 0.3,
    settings: OutputErrorSettings | None = None,
) -> SimulationTest:
    """Test the friction-law candidates ``laws`` by output error on ``problem`` (base model,
    ``start`` its equation-error estimate by name): module docstring."""
    settings = settings or OutputErrorSettings(segment_s=SEGMENT_S)
    if not settings.x_scale:
        settings = settings._replace(x_scale=noise_scale(np.asarray(problem.x)))
    problem = replace(problem, rest=None)
    base = fit_output_error(problem, start, settings)
    applicable = [e for e in laws if candidate(e).applicable(problem.model, problem.spec)]
    fits = [law_fit(problem, base, e, settings) for e in applicable]
    limit = alpha / max(len(laws), 1)
    passing = sorted(
        (f for f in fits if f.p_value < limit and f.delta_bic > min_delta_bic),
        key=lambda f: -f.delta_bic,
    )
    out = SimulationTest(base=base, fits=fits, chosen=None)
    for law in passing:
        report = heldout_gain(problem, base, law, fraction, settings)
        if report["heldout_improvement"] > 0:
            out.chosen, out.heldout = law, report
            break
        out.rejected.append((law, report))
    return out
