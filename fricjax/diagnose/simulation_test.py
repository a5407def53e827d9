"""Changes of the friction law tested by simulation (output) error, where equation error is blind.

Why. The equation error ``m·a − F*`` (seed eq. 11) of the diagnosis needs the velocity
and acceleration differentiated from x. Where ``|v| < 4σ_v`` the sign of the velocity is
noise, so those samples are held by the stick/slip rule and left out of the tests
(:func:`fricjax.diagnose.run.with_rest`), and with them most of what tells one friction
law from another near rest: how the plant stops and breaks away. On records that stick
often, a Stribeck drop or a direction-dependent friction then leaves almost nothing the
base model cannot absorb in that metric, though it changes the motion itself by many noise
standard deviations.

Test. The base model (equation-error estimate as start) is fitted by output error with
multiple shooting (:func:`fricjax.output_error.fit_output_error`, costs ``E = Σ r_aug²`` in
units of the record's own ``σ̂_x²``, :mod:`fricjax.diagnose.evidence`; its lack of fit,
:func:`lack_of_fit_p`, is reported). Each friction law of the catalogue (entries marked
``by_simulation``) is fitted from the base's optimum, the law at its null and its shape at
its grid's middle. With the costs in units of the record's σ̂_x² (ν degrees of freedom), k
the term's free parameters and n the samples:

    LR = E_base − E_term,   p = P(F(k, ν) > LR/k),   ΔBIC = LR − k·ln n

``E_base`` is the lower of the base's fit and the base refitted from where the term's
fit ended (LM may stop short of the base's minimum, and the longer descent must not pass
for the term's gain); the refit is run only for a candidate that passes against the
base's fit, since a lower base only lowers LR and ΔBIC. Every candidate starts from the
base's fit: when the base misfits the record by far, which law wins is decided by where
each LM descent ends, and a base refitted for an earlier one would favour the later.
A candidate is named when ``p < α / len(effects)`` and ``ΔBIC > min_delta_bic`` (the
selection's own bars), the best by ΔBIC first, and when it also improves the held-out
check in the same metric: base and base + term are fitted on the training part and then
simulated over the test part with their parameters fixed (only the segment states are
fitted there); the gain is ``1 − E_term,test / E_base,test``. The test part is the last
``fraction`` of the record, or the first where only that one reaches the term's place
(:func:`heldout_cut`); a term whose place neither reaches is not named. Given a second
recording of the same plant, the term must gain there too (:func:`second_recording_gain`),
as an equation-error finding must gain in every held-out check that reaches its place
(``run.Confirm``); where the record's split reaches no place, the second recording judges
alone. Both are needed: a second recording of the same motion confirms any law that
reproduces the plant there, right name or not.

A stateful term (presliding lag) is not offered: the simulator integrates pointwise forces
only; nor are the local and periodic terms, which equation error sees directly.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy import stats

from fricjax.diagnose.catalogue import candidate, simulation_candidates
from fricjax.diagnose.evidence import EXACT_DOF, Evidence, record_noise
from fricjax.diagnose.stages import Clock
from fricjax.output_error import (
    OutputErrorFit,
    OutputErrorSettings,
    fit_output_error,
)
from fricjax.problem import Problem

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
    lr: float  # E_base − E_term [σ_x²]
    p_value: float
    delta_bic: float
    k: int  # the term's free parameters
    params: dict[str, float]  # the term's own parameters (SI units)
    cost_base: float  # E_base the ratio is taken against [σ_x²]: the lower of the two base fits
    rebased: bool = True  # False: judged against the base's first fit only (law_fit's bars)
    # the base fit whose cost is ``cost_base``; the held-out checks start from it (None:
    # the test's own base fit)
    base_fit: OutputErrorFit | None = None


@dataclass
class SimulationTest:
    """Outcome of :func:`simulation_test`: the base fit, every candidate's, and the one
    named (``None``: none passed), with its held-out check."""

    base: OutputErrorFit
    fits: list[LawFit]
    chosen: LawFit | None
    heldout: dict[str, float] = field(default_factory=dict)
    rejected: list[tuple[LawFit, dict[str, float]]] = field(default_factory=list)
    # p of the base's output-error cost against the record's noise (lack_of_fit_p)
    lack_of_fit_p: float = 0.0


def _judge(
    problem: Problem, ext: Problem, fit: OutputErrorFit, e_base: float, nu: int
) -> tuple[float, float, float, int]:
    """(LR, p, ΔBIC, k) of the term fit ``fit`` against the base cost ``e_base`` [σ_x²]: the
    costs are in units of the record's own σ̂_x², so ``LR = E_base − E_term`` with
    ``LR/k ~ F(k, ν)`` and the BIC of a known variance, ``ΔBIC = LR − k·ln n``."""
    k = ext.spec.n_free - problem.spec.n_free
    n = problem.n
    # LM never ends above its start and the start is the base optimum with the term at its
    # null, so the nested fit is never worse than the base up to the solver's tolerance
    e_term = min(fit.cost, e_base)
    lr = e_base - e_term
    return (
        float(lr),
        float(stats.f.sf(lr / max(k, 1), max(k, 1), nu)),
        float(lr - k * np.log(n)),
        k,
    )


def lack_of_fit_p(base: OutputErrorFit, n_free: int, nu: int) -> float:
    """p of the base's output-error cost against the record's own noise: ``E_base`` [σ_x²]
    over its ``ν_r = n_residual − d − 2S`` residual degrees of freedom (d parameters, S
    segments' two states) follows ``F(ν_r, ν)`` when the base is right."""
    dof = max(base.n_residual - n_free - 2 * base.n_segments, 1)
    return float(stats.f.sf(base.cost / dof, dof, nu))


def law_fit(
    problem: Problem,
    base: OutputErrorFit,
    effect: str,
    settings: OutputErrorSettings,
    nonlinear: Mapping[str, float] | None = None,
    bars: tuple[float, float] | None = None,
    nu: int = EXACT_DOF,
) -> LawFit:
    """Base + the candidate ``effect`` fitted by output error from the base's optimum (term
    at its null, shape parameters at ``nonlinear``, else at their grid middle), with its
    LR, p-value and ΔBIC.

    ``bars`` = (p limit, ΔBIC floor): the base is refitted from the term's end point (see
    below) only when the term passes both against the base's first fit; a lower base cost
    only lowers LR and ΔBIC, so a term that fails there fails anyway (``rebased`` False).
    """
    ext = candidate(effect).extend_problem(problem, nonlinear)
    states = (base.states_x, base.states_v)
    fit = fit_output_error(ext, dict(base.params), settings, states)
    e_base, best = base.cost, base
    lr, p, dbic, k = _judge(problem, ext, fit, e_base, nu)
    rebased = bars is None or (p < bars[0] and dbic > bars[1])
    if rebased:
        # LM may stop short of the base's own minimum (its step limit): the ratio is taken
        # against the base refitted from where the term's fit ended, so that it measures
        # what the term explains and not what the longer descent found
        again = fit_output_error(problem, dict(fit.params), settings, (fit.states_x, fit.states_v))
        best = again if again.cost < base.cost else base
        e_base = best.cost
        lr, p, dbic, k = _judge(problem, ext, fit, e_base, nu)
    return LawFit(
        effect=effect,
        problem=ext,
        fit=fit,
        lr=lr,
        p_value=p,
        delta_bic=dbic,
        k=k,
        params={q: float(v) for q, v in fit.params.items() if q not in problem.spec},
        cost_base=float(e_base),
        rebased=rebased,
        base_fit=best,
    )


def _held_test_cost(
    train: Problem, test: Problem, start: dict[str, float], settings: OutputErrorSettings
) -> float:
    """Output-error cost on ``test`` of the model fitted on ``train`` from ``start``, its
    parameters fixed on ``test`` (only the segment states fitted there)."""
    fitted = fit_output_error(train, start, settings)
    return _fixed_cost(test, dict(fitted.params), settings)


def _fixed_cost(test: Problem, params: dict[str, float], settings: OutputErrorSettings) -> float:
    """Output-error cost on ``test`` of the model at ``params``, every parameter fixed:
    only the segment states are fitted (a held-out simulation, not a refit)."""
    fixed = test.spec.with_fixed({k: params[k] for k in test.spec.free_names})
    return fit_output_error(replace(test, spec=fixed), params, settings).cost


def heldout_cut(
    problem: Problem, place: Mapping[str, Any], fraction: float
) -> tuple[str, slice, slice] | str:
    """(part, training samples, test samples) of the held-out check of a term acting at
    ``place`` (:meth:`~fricjax.diagnose.catalogue.Candidate.location`): the test part is
    the record's last ``fraction``, or its first when the term acts only where the last
    part never goes (a bump, an impact: there its "gain" would be the base's extrapolation
    alone); the training part is the rest. Where neither test part reaches the place, the
    reasons (a string) instead."""
    from fricjax.diagnose.run import record_part, untested_place

    n_test = round(problem.n * fraction)
    cuts = {
        "last": (slice(0, problem.n - n_test), slice(problem.n - n_test, problem.n)),
        "first": (slice(n_test, problem.n), slice(0, n_test)),
    }
    whole = replace(problem, rest=None)
    why = {
        part: untested_place(dict(place), record_part(whole, test.start, test.stop))
        for part, (_, test) in cuts.items()
    }
    part = next((q for q in cuts if not why[q]), None)
    if part is None:
        return "; ".join(dict.fromkeys(why.values()))
    return (part, *cuts[part])


def heldout_gain(
    problem: Problem,
    base: OutputErrorFit,
    law: LawFit,
    fraction: float,
    settings: OutputErrorSettings,
) -> dict[str, Any]:
    """The held-out check in output error (module docstring) on the part chosen by
    :func:`heldout_cut`: ``heldout_improvement`` = ``1 − E_term,test / E_base,test``, the
    base started from the fit its LR was taken against (``law.base_fit``; ``base`` where
    that is unset). Where no part can judge the term, ``heldout_untestable`` says why and
    the gain is NaN: the term is not named on this record."""
    from fricjax.diagnose.run import record_part

    cut = heldout_cut(problem, candidate(law.effect).location(law.params, problem), fraction)
    if isinstance(cut, str):
        return {"heldout_improvement": float("nan"), "heldout_untestable": cut}
    part, train_sl, test_sl = cut
    # the noise scale of the whole record, so that both parts share one unit
    settings = settings._replace(x_scale=base.x_scale)
    costs = []
    for pb, fit in ((problem, law.base_fit or base), (law.problem, law.fit)):
        pb = replace(pb, rest=None)
        train = record_part(pb, train_sl.start, train_sl.stop)
        test = record_part(pb, test_sl.start, test_sl.stop)
        costs.append(_held_test_cost(train, test, dict(fit.params), settings))
    return {
        "heldout_improvement": float(1 - costs[1] / costs[0]),
        "heldout_cost_base": float(costs[0]),
        "heldout_cost_term": float(costs[1]),
        "heldout_part": part,
    }


def second_recording_gain(
    validation: Problem, base: OutputErrorFit, law: LawFit, settings: OutputErrorSettings
) -> dict[str, Any]:
    """The held-out check on a second recording of the same plant (``--validation``): base
    and base + term, each at the parameters fitted on the whole record, simulated over the
    second recording (only its segment states fitted there), the base at the fit its LR was
    taken against (``law.base_fit``; ``base`` where that is unset: a base stopped short of
    its minimum would pass any term that completes its descent for a gain);
    ``heldout_improvement`` = ``1 − E_term,2nd / E_base,2nd``, in the record's noise unit.
    No part of the record is set aside, so the gain is not the base's extrapolation into a
    place the fit never saw, wherever the term acts."""
    from fricjax.diagnose.run import with_model

    settings = settings._replace(x_scale=base.x_scale)
    term = with_model(validation, law.problem.model, law.problem.spec)
    costs = [
        _fixed_cost(replace(pb, rest=None), dict(fit.params), settings)
        for pb, fit in ((validation, law.base_fit or base), (term, law.fit))
    ]
    return {
        "heldout_improvement": float(1 - costs[1] / costs[0]),
        "heldout_cost_base": float(costs[0]),
        "heldout_cost_term": float(costs[1]),
        "heldout_part": "second recording",
    }


def judging_gains(report: Mapping[str, Any]) -> list[float]:
    """The held-out gains of a law's ``report`` that judge it: the primary check's always
    (the second recording when given, else the record's split, whose NaN where no part
    reaches the place refuses the law: ``NaN > 0`` is false) and the split's beside a
    second recording unless it is marked untestable there. Not ``run.heldout_judged``,
    which drops an untestable primary check and leaves the finding to the cross-validation:
    this stage has none, so a law no check reaches is not named."""
    from fricjax.diagnose.run import HELDOUT_KEYS

    (primary, _), (split, split_why) = HELDOUT_KEYS
    gains = [report[primary]]
    if split in report and not report.get(split_why):
        gains.append(report[split])
    return gains


def simulation_test(
    problem: Problem,
    start: dict[str, float],
    *,
    effects: Sequence[str] | None = None,
    alpha: float = 0.01,
    min_delta_bic: float = 10.0,
    fraction: float = 0.3,
    settings: OutputErrorSettings | None = None,
    validation: Problem | None = None,
    clock: Clock | None = None,
    evidence: Evidence | None = None,
) -> SimulationTest:
    """Test the pointwise candidates ``effects`` by output error on ``problem`` (base model,
    ``start`` its equation-error estimate by name): module docstring. With ``validation``
    (a second recording of the same plant, base model) a candidate is judged by its gain
    there (:func:`second_recording_gain`) and by the record's own split where that reaches
    its place (reported as ``heldout_split_improvement``; where it does not,
    ``heldout_split_untestable`` says why): it is named only if it gains in every check
    that judges it. ``clock``: the diagnosis' time limits (stage ``simulation_test``); a
    candidate a limit leaves unfitted or unchecked is recorded there as not tested."""
    clock = clock or Clock()
    effects = simulation_candidates() if effects is None else effects
    evidence = evidence or record_noise(problem)
    settings = settings or OutputErrorSettings(segment_s=SEGMENT_S)
    # costs in units of the record's own σ̂_x² (fricjax.diagnose.evidence)
    settings = settings._replace(x_scale=evidence.sigma_x)
    problem = replace(problem, rest=None)
    base = fit_output_error(problem, start, settings)
    # reported, not a gate: an omnibus test over every residual dimension has far less
    # power than a law's own ratio against an effect that lives in a few of them
    lof = lack_of_fit_p(base, problem.spec.n_free, evidence.nu)
    applicable = [e for e in effects if candidate(e).applicable(problem.model, problem.spec)]
    limit = alpha / max(len(effects), 1)
    fits = []
    for effect in applicable:
        if clock.over("simulation_test"):
            clock.untested("simulation_test", effect)
            continue
        clock.note(f"output-error fit of {effect}")
        # fitted from its grid's middle: at stops and breakaways the motion is not linear
        # in a friction law, so no score at the base fit is a guide to where it lies
        fits.append(
            law_fit(problem, base, effect, settings, None, (limit, min_delta_bic), evidence.nu)
        )
    passing = sorted(
        (f for f in fits if f.p_value < limit and f.delta_bic > min_delta_bic),
        key=lambda f: -f.delta_bic,
    )
    out = SimulationTest(base=base, fits=fits, chosen=None, lack_of_fit_p=lof)
    for law in passing:
        if clock.over("simulation_test"):
            clock.untested("simulation_test", law.effect)
            continue
        clock.note(f"held-out check of {law.effect}")
        report = heldout_gain(problem, base, law, fraction, settings)
        if validation is not None:
            split = report
            report = second_recording_gain(validation, base, law, settings)
            report["heldout_split_improvement"] = split["heldout_improvement"]
            if "heldout_untestable" in split:
                report["heldout_split_untestable"] = split["heldout_untestable"]
        if all(gain > 0 for gain in judging_gains(report)):
            out.chosen, out.heldout = law, report
            break
        out.rejected.append((law, report))
    return out
