"""``diagnose``: fit the base model, try every catalogue term by output error, name what the
one judging rule accepts, and say where the record holds what no term explains.

Stages (:mod:`fricjax.diagnose.stages`): the base fit (``identify``, then output error from
its estimate), the record's own noise (:mod:`~fricjax.diagnose.evidence`), the candidates
(:mod:`~fricjax.diagnose.judge`), the held-out checks (:mod:`~fricjax.diagnose.heldout`),
the report (:mod:`~fricjax.diagnose.report`).

The rule: forward selection up to ``max_terms`` (:func:`~fricjax.diagnose.select.select`,
the driver the diagnosis across recordings shares) with the output-error judge
(:class:`~fricjax.diagnose.judge.OutputErrorJudge`). At each step every applicable
candidate is refitted by output error from each of its starts (one batched program,
:func:`~fricjax.diagnose.judge.fit_candidates`); one metric judges, the output error in
units of the record's own noise. A candidate passes where its calibrated p (the best of
its shapes, :func:`~fricjax.diagnose.judge.looks`) is below ``α/C`` (C candidates at that
step) and its ΔBIC above ``min_delta_bic``. The passing candidates are taken by ΔBIC; the
first whose gain holds in cross-validation (every held-out check that judges it gains,
:mod:`~fricjax.diagnose.heldout`) is named, together with the passing candidates the record
cannot tell from it (Vuong's test not significant at ``ambiguity``,
:func:`~fricjax.diagnose.judge.vuong`): an ambiguity set, the best first. The record's
equation-error EMS and open-loop simulation error are reported beside each finding, with a
warning where they get worse; they decide nothing.

A candidate that passes the statistics but not cross-validation is reported as
``unexplained`` at its place, never named. When nothing is named and the model's
output-error lack of fit against the record's noise is significant (``F(ν_r, ν)``, p < α),
the finding is ``unexplained`` at the segment of the record that misfits most.

Output (:func:`fricjax.diagnose.report.write_diagnosis`): ``diagnosis.json``
(docs/formats.md), ``report.md`` and ``report.html``, ``models.h5`` with the base and final
models.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from fricjax.diagnose.catalogue import candidate
from fricjax.diagnose.evidence import Evidence, NearRest, near_rest_band, record_noise
from fricjax.diagnose.heldout import CrossValidation, SecondRecording
from fricjax.diagnose.judge import (
    EMS,
    SIMULATION,
    CandidateFit,
    Fitted,
    OutputErrorJudge,
    Superset,
    fit_base,
    lack_of_fit_p,
    simulation_error,
)
from fricjax.diagnose.select import (
    Check,
    Decision,
    Finding,
    Rule,
    Step,
    refused,
    refused_by_step,
    select,
)
from fricjax.diagnose.stages import LIMITED, TIME_LIMIT_S, Clock, OnStage
from fricjax.errors import FricjaxError, where
from fricjax.identify import IdentifySettings, identify
from fricjax.output_error import OutputErrorSettings
from fricjax.params import at_bounds
from fricjax.problem import Problem
from fricjax.report.tables import p_text

#: Seconds a stage may take by default (``[diagnose.stage_limits]``).
STAGE_LIMITS = dict.fromkeys(LIMITED, math.inf)


@dataclass
class DiagnoseSettings:
    """Knobs of :func:`diagnose` (``[diagnose]`` config table), each with its justification.

    alpha: family-wise false-alarm rate of a diagnosis on a record with nothing missing.
        Split over the C candidates of a step (Bonferroni, ``α/C`` each: valid whatever
        their dependence), each candidate's p already that of the best of its shapes
        (:func:`~fricjax.diagnose.judge.looks`), and spent once more on the lack-of-fit
        test that makes a finding ``unexplained``; a null record thus gets any finding
        with probability ≤ 2α (2 % at the default 0.01, under the 5 % the project targets).
    min_delta_bic: a term must lower BIC by more than this: 10 is "very strong" evidence on
        Kass & Raftery's scale (posterior odds above 150:1 at equal priors). It guards the
        long records where p alone would pass effects too small to matter.
    max_terms: most terms named (forward selection stops earlier when none passes).
    n_starts: grid points per candidate's nonlinear parameters that start a refit: the
        best local maxima of the cheap equation-error ranking
        (:func:`~fricjax.diagnose.judge.starts`), the second guarding against a ranking
        bent by the equation error it is taken from. Every start is refitted.
    ambiguity: level of Vuong's test (:func:`~fricjax.diagnose.judge.vuong`) that tells a
        passing candidate apart from the named one: a candidate the record does not
        prefer less at this level is named with it, as an ambiguity set. 0.05, one-sided:
        a true term left out of the set by chance one time in twenty at most, while two
        terms the record does tell apart are not both reported.
    segment_s: segment length of the multiple shooting [s]: short enough that a simulation
        from the base's first estimate, which may have absorbed the missing physics far from
        the plant's values, stays within the noise of its own start (LM then works on a
        nearly quadratic cost), long enough (50 samples at 1 kHz) that each segment carries
        the dynamics the parameters must explain (the seed's time constant m/Fv ≈ 12 ms).
    max_steps: Levenberg–Marquardt steps of each round of an output-error fit (a fit is
        restarted until its cost falls by less than ``judge.CONVERGED``).
    time_limit: seconds for the whole diagnosis; stage_limits: seconds per stage
        (``[diagnose.stage_limits]``, keys of :data:`~fricjax.diagnose.stages.LIMITED`).
        A limit acts between units of work (one candidate's fits, one held-out check); what
        it leaves out is recorded (``not_tested``, ``timing``) and never named. Default:
        180 s in all (the bound a user waits for on any recording up to 30 s), no stage
        limit; a limit makes findings depend on the machine's speed, so a benchmark that
        compares findings sets ``time_limit = inf``.
    """

    alpha: float = 0.01
    min_delta_bic: float = 10.0
    max_terms: int = 3
    n_starts: int = 2
    ambiguity: float = 0.05
    segment_s: float = 0.05
    max_steps: int = 100
    time_limit: float = TIME_LIMIT_S
    stage_limits: dict[str, float] = field(default_factory=lambda: dict(STAGE_LIMITS))

    def clock(self, on_stage: OnStage | None = None, stop: threading.Event | None = None) -> Clock:
        """A :class:`~fricjax.diagnose.stages.Clock` with these time limits (``stop``: a
        stop request, e.g. Ctrl-C)."""
        return Clock(
            limits=dict(self.stage_limits), total=self.time_limit, on_stage=on_stage, stop=stop
        )

    @property
    def rule(self) -> Rule:
        """The levels of forward selection (:func:`~fricjax.diagnose.select.select`)."""
        return Rule(self.alpha, self.min_delta_bic, self.max_terms, self.ambiguity)

    def output_error(self, evidence: Evidence) -> OutputErrorSettings:
        """The output-error settings of every fit: residual in units of the record's σ̂_x."""
        return OutputErrorSettings(
            segment_s=self.segment_s, x_scale=evidence.sigma_x, max_steps=self.max_steps
        )

    @classmethod
    def from_dict(
        cls, d: dict[str, Any], source: str = "config", *, flags: bool = False
    ) -> DiagnoseSettings:
        """Settings from a ``[diagnose]`` table, each key's type and range checked: a
        mistake is one :class:`FricjaxError` line naming ``source`` and the key (as its
        command-line flag where ``flags``)."""
        rules: dict[str, tuple[type, Any, str]] = {
            "alpha": (float, lambda v: 0 < v < 1, "in (0, 1)"),
            "min_delta_bic": (float, lambda v: 0 <= v < math.inf, ">= 0 and finite"),
            "max_terms": (int, lambda v: v >= 1, ">= 1"),
            "n_starts": (int, lambda v: v >= 1, ">= 1"),
            "ambiguity": (float, lambda v: 0 < v < 1, "in (0, 1)"),
            "segment_s": (float, lambda v: 0 < v < math.inf, "> 0 seconds and finite"),
            "max_steps": (int, lambda v: v >= 1, ">= 1"),
            "time_limit": (float, lambda v: v > 0, "> 0 seconds (inf: none)"),
            "stage_limits": (
                dict,
                lambda v: all(
                    k in LIMITED
                    and isinstance(s, int | float)
                    and not isinstance(s, bool)
                    and s > 0
                    for k, s in v.items()
                ),
                f"a table of seconds > 0 for stages among {', '.join(LIMITED)}",
            ),
        }
        values: dict[str, Any] = {}
        for key, value in d.items():
            label = f"--{key.replace('_', '-')}" if flags else f"[diagnose].{key}"
            if key not in rules:
                raise FricjaxError(
                    f"{where(source, label)}: unknown key (known: {', '.join(sorted(rules))})"
                )
            kind, valid, what = rules[key]
            # bool is an int, but `max_terms = true` is a mistake, not 1
            typed = isinstance(value, kind) and (kind is bool or not isinstance(value, bool))
            if kind is float and isinstance(value, int) and not isinstance(value, bool):
                value, typed = float(value), True
            if not typed or not valid(value):
                raise FricjaxError(f"{where(source, label)}: must be {what}, got {value!r}")
            values[key] = value
        if "stage_limits" in values:  # a table sets the stages it names, the rest keep theirs
            values["stage_limits"] = {
                **STAGE_LIMITS,
                **{k: float(v) for k, v in values["stage_limits"].items()},
            }
        return cls(**values)


@dataclass
class Diagnosis:
    """Everything diagnose found, as plain data plus the fitted models."""

    recording: str
    base_model: str
    findings: list[Finding]
    fit: dict[str, dict[str, float]]
    problem: Problem
    base: Fitted
    final: Fitted
    steps: list[Step[Fitted, CandidateFit]]
    evidence: Evidence
    near_rest: NearRest
    identify_ems: float
    clock: Clock = field(default_factory=Clock)

    def as_json(self) -> dict[str, Any]:
        return jsonable(
            {
                "recording": self.recording,
                "base_model": self.base_model,
                "findings": [f.as_json() for f in self.findings],
                "fit": self.fit,
                "data": {
                    "sigma_x_m": self.evidence.sigma_x,
                    "sigma_x_se_m": self.evidence.noise.se,
                    "noise_model": self.evidence.noise.model,
                    "sigma_x_dof": self.evidence.nu,
                    "near_rest_speed_mps": self.near_rest.speed,
                    "near_rest_fraction": self.near_rest.share,
                },
                "identify_ems": self.identify_ems,
                "candidates": [
                    {
                        "step": i + 1,
                        "limit_p": st.limit,
                        "min_delta_bic": st.min_delta_bic,
                        "tested": [_fit_json(f) for f in st.fits],
                        "judged": [_decision_json(d) for d in st.decisions],
                    }
                    for i, st in enumerate(self.steps)
                ],
                "not_tested": self.clock.not_tested(),
                "timing": self.clock.summary(),
            }
        )


def _fit_json(f: CandidateFit) -> dict[str, Any]:
    return {
        "effect": f.effect,
        "lr": f.lr,
        "k": f.k,
        "p_value": f.p_value,
        "p_raw": f.p_raw,
        "looks": f.looks,
        "delta_bic": f.delta_bic,
        "cost_base": f.base.cost,
        "cost_term": f.fitted.cost,
        "params": f.params,
    }


def _decision_json(d: Decision[CandidateFit]) -> dict[str, Any]:
    return {
        "effect": d.fit.effect,
        "named": d.named,
        "record_ems_gain": d.gain(EMS),
        "record_simulation_gain": d.gain(SIMULATION),
        "heldout": [v.as_json() for v in d.verdicts],
        "alternatives": [a.fit.effect for a in d.alternatives],
    }


def jsonable(obj: Any) -> Any:
    """JSON-safe: non-finite floats as null, numpy scalars as Python numbers."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def diagnose(
    problem: Problem,
    *,
    identify_settings: IdentifySettings | None = None,
    settings: DiagnoseSettings | None = None,
    validation: Problem | None = None,
    recording: str = "",
    on_stage: OnStage | None = None,
    stop: threading.Event | None = None,
) -> Diagnosis:
    """The whole diagnosis of ``problem``'s base model (module docstring). ``validation``: a
    second recording of the same plant, base model. ``on_stage``: called with each
    :class:`~fricjax.diagnose.stages.StageEvent` (progress display). ``stop``: once set
    (Ctrl-C, from another thread), the work in flight ends and the rest is left out, as at
    a time limit; the diagnosis then reports what it judged, marked interrupted."""
    settings = settings or DiagnoseSettings()
    clock = settings.clock(on_stage, stop)
    problem = _undecimated(problem)
    # the judge fits the base by output error itself, from the equation-error estimate
    identify_settings = replace(identify_settings or IdentifySettings(), objective="equation")
    with clock.stage("base_fit", "base fit: search and refine"):
        run = identify(problem, identify_settings)
        evidence = record_noise(problem)
        band = near_rest_band(problem, evidence.sigma_x)
        oe = settings.output_error(evidence)
        clock.note("base fit by output error")

        def more(need: float) -> bool:
            # the first round always runs (no diagnosis without a base); a further round
            # only where it would end within the limit
            if clock.over("base_fit", need):
                clock.skip("base_fit", "base fit: further Levenberg–Marquardt rounds")
                return False
            return True

        base = fit_base(Superset.build(problem), problem.spec.as_dict(run.value), oe, more)
    checks: list[Check[Fitted]] = [CrossValidation(oe)]
    if validation is not None:
        checks.append(SecondRecording(_undecimated(validation), oe))
    judge = OutputErrorJudge(oe, evidence.nu, band, settings.n_starts)
    steps = select(judge, checks, base, settings.rule, clock)
    named = [st.chosen for st in steps if st.chosen is not None]
    final = named[-1].fit.fitted if named else base
    findings = [_finding(problem, d, st) for st in steps if (d := st.chosen) is not None]
    refused_ = [
        refused(
            best,
            rest,
            candidate(best.fit.effect).location(best.fit.params, problem),
            {"effect": best.fit.effect, "params": best.fit.params, **_decision_json(best)},
        )
        for best, rest in refused_by_step(steps)
    ]
    lof_before, lof_after = lack_of_fit_p(base, evidence.nu), lack_of_fit_p(final, evidence.nu)
    if refused_:
        findings += refused_
    elif lof_after < settings.alpha and not named:
        findings.append(_unexplained(final, lof_after, evidence.nu))
    sim_before = simulation_error(base)
    sim_after = sim_before if final is base else simulation_error(final)
    fit = {
        label: {
            "ems": m.problem.ems(m.theta),
            "output_error_cost": m.cost,
            "lack_of_fit_p": lof,
            "position_rms_m": m.fit.position_rms,
            "simulation_rms_m": sim,
            "n_free": m.n_free,
        }
        for label, m, lof, sim in (
            ("before", base, lof_before, sim_before),
            ("after", final, lof_after, sim_after),
        )
    }
    return Diagnosis(
        recording=recording or problem.name,
        base_model=problem.model.name,
        findings=findings,
        fit=fit,
        problem=problem,
        base=base,
        final=final,
        steps=steps,
        evidence=evidence,
        near_rest=band,
        identify_ems=float(run.ems),
        clock=clock,
    )


def _undecimated(problem: Problem) -> Problem:
    """The problem without residual decimation (``[preprocess].decimate``): the EMS the
    judge compares is taken at every sample."""
    from dataclasses import replace

    if problem.preprocess is None or problem.preprocess.decimate == 1:
        return problem
    return replace(problem, preprocess=replace(problem.preprocess, decimate=1))


def _share(f: CandidateFit) -> float:
    """The share of the base's misfit beyond the noise that the term removes:
    ``LR / (E_base − ν_r)``, ν_r the base's residual degrees of freedom (what noise alone
    leaves), in [0, 1]. On a real record every statistic is astronomically significant;
    this says how much of what is wrong the term accounts for."""
    base = f.base.fit
    dof = max(base.n_residual - f.base.n_free - 2 * base.n_segments, 1)
    excess = float(base.cost) - dof
    return float(min(max(f.lr / excess, 0.0), 1.0)) if excess > 0 else math.nan


def _warnings(d: Decision[CandidateFit]) -> list[str]:
    """Plain warnings where the term makes what a user sees worse (reported, not judged)."""
    out = []
    for g in d.gains:
        if g.value < 0:
            out.append(f"the record's {g.metric} gets worse with it ({100 * g.value:+.1f} %)")
    return out


def _finding(
    problem: Problem, d: Decision[CandidateFit], step: Step[Fitted, CandidateFit]
) -> Finding:
    """One named finding; an ambiguity set keeps its best member as
    ``effect`` and the others under ``alternatives``."""
    f = d.fit
    cand = candidate(f.effect)
    runner = sorted((g for g in step.fits if g is not f), key=lambda g: -g.delta_bic)
    share = _share(f)
    explanation = cand.explain(f.params, problem) + (
        f" With it the output error of the record falls from {f.base.cost:.4g} to "
        f"{f.fitted.cost:.4g} σ_x² (LR = {f.lr:.1f}, {f.k} parameters)"
        + (
            f", {100 * share:.0f} % of the misfit beyond the noise."
            if math.isfinite(share)
            else "."
        )
    )
    if d.alternatives:
        names = ", ".join(a.fit.effect for a in d.alternatives)
        explanation += (
            f" The record cannot tell it from {names}: each explains it about as well "
            "(Vuong's test not significant); a test that moves the body differently would "
            "separate them (`fricjax design` finds one within the rig's limits)."
        )
    return Finding(
        effect=f.effect,
        explanation=explanation,
        location=cand.location(f.params, problem),
        params=f.params,
        delta_bic=f.delta_bic,
        p_value=f.p_value,
        heldout=d.verdicts,
        warnings=tuple(_warnings(d)),
        alternatives=tuple(
            Finding(
                effect=a.fit.effect,
                explanation="",
                location=candidate(a.fit.effect).location(a.fit.params, problem),
                params=a.fit.params,
                delta_bic=a.fit.delta_bic,
                p_value=a.fit.p_value,
                evidence={"vuong_t": a.t, "vuong_p": a.p_value},
            )
            for a in d.alternatives
        ),
        evidence={
            "at_bound": at_bounds(f.fitted.problem.spec, f.params),
            "lr": f.lr,
            "misfit_share": share,
            "test": "output error",
            "record_ems_gain": d.gain(EMS),
            "record_simulation_gain": d.gain(SIMULATION),
            "runner_up": runner[0].effect if runner else "",
            "runner_up_delta_bic": runner[0].delta_bic if runner else math.nan,
        },
    )


def _unexplained(model: Fitted, p: float, nu: int) -> Finding:
    """``unexplained`` where the model misfits the record's noise and no candidate passes:
    located at the segment of the multiple shooting whose samples misfit most (its share of
    the cost over its share of the samples)."""
    pb, f = model.problem, model.fit
    r = (f.x_sim - pb.x) / f.x_scale
    seg = f.segment_of
    per = np.bincount(seg, weights=r**2) / np.bincount(seg)
    s = int(np.argmax(per))
    idx = np.flatnonzero(seg == s)
    dof = max(f.n_residual - model.n_free - 2 * f.n_segments, 1)
    excess = float(f.cost - dof)
    return Finding(
        effect="unexplained",
        explanation=(
            f"The model leaves more output error than the record's noise accounts for "
            f"({f.cost:.4g} σ_x² over {dof} degrees of freedom, {p_text(p)}), and no catalogue "
            f"term explains it. It misfits most over t = {pb.t[idx[0]]:.4g} to "
            f"{pb.t[idx[-1]]:.4g} s ({per[s]:.3g} σ_x² per sample there; the record is "
            f"{float(pb.t[-1] - pb.t[0]):.3g} s long)."
        ),
        location={
            "time_s": [float(pb.t[idx[0]]), float(pb.t[idx[-1]])],
            "position_m": [float(np.min(pb.x[idx])), float(np.max(pb.x[idx]))],
        },
        params={},
        # a term that explained all of it would lower BIC by about this, less its penalty
        delta_bic=excess,
        p_value=p,
    )
