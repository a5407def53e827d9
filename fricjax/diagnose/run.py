"""``diagnose``: fit the base model, try every catalogue term by output error, name what the
one judging rule accepts, and say where the record holds what no term explains.

Stages (:mod:`fricjax.diagnose.stages`): the base fit (``identify``, then output error from
its estimate), the record's own noise (:mod:`~fricjax.diagnose.evidence`), the candidates
(:mod:`~fricjax.diagnose.judge`), the held-out checks (:mod:`~fricjax.diagnose.heldout`),
the report (:mod:`~fricjax.diagnose.report`).

The rule (:func:`decide`). Forward selection up to ``max_terms``: at each step every
applicable candidate's score test is taken at the current model (one Jacobian, no fit), those
significant at α (all of them where the current model's lack of fit is significant) are
fitted next to it (highest score first), and the best by ΔBIC of the
fits that pass ``p < α/C`` (C candidates at that step) and ``ΔBIC > min_delta_bic`` is named
when also

* the record's own EMS and open-loop simulation error do not get worse with it, and
* every held-out check that can judge it (the record's split, a second recording) shows a
  positive gain, and at least one can.

A candidate that passes the statistics but not the rest is reported as ``unexplained`` at its
place, never named. When nothing is named and the model's output-error lack of fit against
the record's noise is significant (``F(ν_r, ν)``, p < α), the finding is ``unexplained`` at
the segment of the record that misfits most.

Output (:func:`write_diagnosis`): ``diagnosis.json`` (docs/formats.md), ``report.md`` and
``report.html`` (:mod:`fricjax.diagnose.report`), ``models.h5`` with the base and final models.
"""

from __future__ import annotations

import json
import math
import threading
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from fricjax.diagnose.catalogue import candidate
from fricjax.diagnose.evidence import Evidence, NearRest, near_rest_band, record_noise
from fricjax.diagnose.heldout import Check, SecondRecording, Split, Verdict
from fricjax.diagnose.judge import (
    CandidateFit,
    Fitted,
    Score,
    Superset,
    fit_base,
    fit_candidates,
    lack_of_fit_p,
    rebased,
    record_gains,
    remaining,
    screen,
    simulation_error,
    starts,
)
from fricjax.diagnose.stages import LIMITED, TIME_LIMIT_S, Clock, OnStage
from fricjax.errors import FricjaxError, where
from fricjax.identify import IdentifySettings, identify
from fricjax.io.atomic import make_folder, write_hdf5_atomic, write_text_atomic
from fricjax.output_error import OutputErrorSettings
from fricjax.params import ParamSpec
from fricjax.problem import Problem

#: Seconds a stage may take by default (``[diagnose.stage_limits]``).
STAGE_LIMITS = dict.fromkeys(LIMITED, math.inf)


@dataclass
class DiagnoseSettings:
    """Knobs of :func:`diagnose` (``[diagnose]`` config table), each with its justification.

    alpha: family-wise false-alarm rate of a diagnosis on a record with nothing missing.
        Split over the C candidates of a step (Bonferroni, ``α/C`` each: valid whatever
        their dependence) and spent once more on the lack-of-fit test that makes a finding
        ``unexplained``; a null record thus gets any finding with probability ≤ 2α (2 % at
        the default 0.01, under the 5 % the project targets).
        It is also the level of the score screen (:func:`~fricjax.diagnose.judge.screen`):
        where the current model fits the record to its noise (lack of fit not significant
        at α), a candidate is refitted only where its score test is significant at α
        itself. The score is the likelihood ratio of the model linearised at the fit, the
        LR's local equivalent; the screen's level is α·C times the judge's, so a term is
        dropped unfitted only where its linearised evidence falls short by that factor, and
        the screen can only remove candidates, never pass one: the family-wise rate stays
        α. Where the lack of fit is significant the model is not near enough to the
        truth for a local statistic (a term the base has absorbed by bending its own
        parameters scores nothing at the base yet pays when refitted), and every candidate
        is refitted.
    min_delta_bic: a term must lower BIC by more than this: 10 is "very strong" evidence on
        Kass & Raftery's scale (posterior odds above 150:1 at equal priors). It guards the
        long records where p alone would pass effects too small to matter.
    max_terms: most terms named (forward selection stops earlier when none passes).
    n_starts: grid points per candidate's nonlinear parameters that are scored in output
        error (:func:`~fricjax.diagnose.judge.screen`): the best local maxima of the cheap
        equation-error ranking, the second guarding against a ranking bent by the equation
        error it is taken from. Where the screen applies (the current model fits to its
        noise) the refit starts from the best-scored point only: the score is the judge's
        own metric there, and the catalogue's grids are spaced so that LM from the best
        point reaches its peak; elsewhere every point starts one round and the best is
        continued.
    heldout: fraction of the record the split check holds out. 0.3 leaves the training part
        more than twice the unknowns of a 0.27 s record's model (heldout.too_short) and the
        test part long enough (≥ 80 samples at 1 kHz) for its cost to be a χ² of many
        degrees of freedom.
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
    heldout: float = 0.3
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
            "heldout": (float, lambda v: 0 < v < 0.9, "in (0, 0.9)"),
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


@dataclass(frozen=True)
class Decision:
    """What the rule made of one candidate that passed the statistics: its record gains
    (EMS, simulation error), its held-out verdicts, and whether it is named."""

    fit: CandidateFit
    ems_gain: float
    simulation_gain: float
    verdicts: tuple[Verdict, ...]

    @property
    def record_ok(self) -> bool:
        """The record's own EMS and simulation error do not get worse (NaN: no figure)."""
        return all(not g < 0 for g in (self.ems_gain, self.simulation_gain))

    @property
    def heldout_ok(self) -> bool:
        """Every check that judges gains, and at least one judges."""
        judged = [v for v in self.verdicts if v.judged]
        return bool(judged) and all(v.passed for v in judged)

    @property
    def named(self) -> bool:
        return self.record_ok and self.heldout_ok


@dataclass(frozen=True)
class Step:
    """One step of forward selection: every candidate's score test, the fits of those it
    passed (``p < screen_limit``; ``inf`` where the current model's lack of fit is
    significant and every candidate is refitted), the decisions on the fits that passed
    the statistics (best first), the per-candidate limit α/C, and the model before."""

    current: Fitted
    scores: tuple[Score, ...]
    fits: tuple[CandidateFit, ...]
    decisions: tuple[Decision, ...]
    limit: float
    min_delta_bic: float
    screen_limit: float

    @property
    def chosen(self) -> Decision | None:
        return next((d for d in self.decisions if d.named), None)


@dataclass
class Diagnosis:
    """Everything diagnose found, as plain data plus the fitted models."""

    recording: str
    base_model: str
    findings: list[dict[str, Any]]
    fit: dict[str, dict[str, float]]
    problem: Problem
    base: Fitted
    final: Fitted
    steps: list[Step]
    evidence: Evidence
    near_rest: NearRest
    identify_ems: float
    clock: Clock = field(default_factory=Clock)

    def as_json(self) -> dict[str, Any]:
        return jsonable(
            {
                "recording": self.recording,
                "base_model": self.base_model,
                "findings": self.findings,
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
                        "screen_limit_p": st.screen_limit,
                        "screened": [_score_json(sc, st) for sc in st.scores],
                        "tested": [_fit_json(f) for f in st.fits],
                        "judged": [_decision_json(d) for d in st.decisions],
                    }
                    for i, st in enumerate(self.steps)
                ],
                "not_tested": self.clock.not_tested(),
                "timing": self.clock.summary(),
            }
        )


def _score_json(sc: Score, st: Step) -> dict[str, Any]:
    return {
        "effect": sc.effect,
        "score": sc.score,
        "k": sc.k,
        "p_value": sc.p_value,
        "refit": any(f.effect == sc.effect for f in st.fits),
    }


def _fit_json(f: CandidateFit) -> dict[str, Any]:
    return {
        "effect": f.effect,
        "lr": f.lr,
        "k": f.k,
        "p_value": f.p_value,
        "delta_bic": f.delta_bic,
        "cost_base": f.base.cost,
        "cost_term": f.fitted.cost,
        "params": f.params,
    }


def _decision_json(d: Decision) -> dict[str, Any]:
    return {
        "effect": d.fit.effect,
        "named": d.named,
        "record_ems_gain": d.ems_gain,
        "record_simulation_gain": d.simulation_gain,
        "heldout": [v.as_json() for v in d.verdicts],
    }


# A parameter within this fraction of its search range from a bound is "on the bound":
# LM's sine transform reaches a bound only asymptotically, 1e-3 of the range is where its
# gradient has fallen to ~6 % of its interior value.
BOUND_TOL = 1e-3


def on_bound(spec: ParamSpec | None, name: str, value: float) -> str:
    """``"lower"``/``"upper"`` where ``value`` sits on that bound of ``name``'s search
    range (within :data:`BOUND_TOL` of it), else ``""``."""
    if spec is None or name not in spec.names or not spec[name].free:
        return ""
    p = spec[name]
    tol = BOUND_TOL * (p.upper - p.lower)
    if value <= p.lower + tol:
        return "lower"
    if value >= p.upper - tol:
        return "upper"
    return ""


def at_bounds(spec: ParamSpec, params: dict[str, float]) -> dict[str, str]:
    """``{name: "lower"|"upper"}`` for each of ``params`` on a bound of its search range: a
    limit the fit ran into, not a measurement."""
    return {n: side for n, v in params.items() if (side := on_bound(spec, n, float(v)))}


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


def decide(
    problem: Problem,
    base: Fitted,
    settings: DiagnoseSettings,
    evidence: Evidence,
    band: NearRest,
    checks: list[Check],
    clock: Clock,
) -> list[Step]:
    """Forward selection by the one rule (module docstring)."""
    oe = settings.output_error(evidence)
    steps: list[Step] = []
    current = base
    for _ in range(settings.max_terms):
        cands = remaining(current)
        if not cands:
            break
        todo = []
        with clock.stage("candidates", "ranking the candidates' starts"):
            for effect in cands:
                if clock.over("candidates"):
                    clock.untested("candidates", effect)
                    continue
                todo.append((effect, starts(current, effect, band, settings.n_starts)))
        with clock.stage("candidates", "score test of every candidate"):
            scores = screen(current, todo, oe, evidence.nu)
        # the score stands for the LR only near the current model: where that model's own lack
        # of fit is significant, the term may pay far from it, so every candidate is refitted
        local = lack_of_fit_p(current, evidence.nu) >= settings.alpha
        screen_limit = settings.alpha if local else math.inf
        refit = sorted((s for s in scores if s.p_value < screen_limit), key=lambda s: -s.score)
        fits: list[CandidateFit] = []
        # a candidate is started only if the longest one so far would still end within the
        # limits: the budget is then overrun by a misjudged length, not by a whole candidate
        longest = 0.0
        with clock.stage("candidates", "output-error fits of the candidates"):
            for sc in refit:
                if clock.over("candidates", longest):
                    clock.untested("candidates", sc.effect, longest)
                    continue
                clock.note(f"output-error fit of {sc.effect}")
                began = clock.elapsed()
                # near the model the score ranks the starts in the judge's metric; far from
                # it the ranking says little, and each start is fitted
                st = sc.starts[:1] if local else sc.starts
                fits += fit_candidates(current, [(sc.effect, st)], oe, evidence.nu)
                longest = max(longest, clock.elapsed() - began)
        limit = settings.alpha / len(cands)
        passing = sorted(
            (f for f in fits if f.passes(limit, settings.min_delta_bic)),
            key=lambda f: -f.delta_bic,
        )
        decisions: list[Decision] = []
        with clock.stage("heldout", "record gains and held-out checks"):
            for f in passing:
                if clock.over("heldout"):
                    clock.untested("heldout", f.effect)
                    continue
                clock.note(f"judging {f.effect}")
                f = rebased(f, oe, evidence.nu)
                if not f.passes(limit, settings.min_delta_bic):
                    continue
                gains = record_gains(f.base, f.fitted)
                place = candidate(f.effect).location(f.params, problem)
                verdicts = tuple(ch.judge(f.base, f.fitted, place) for ch in checks)
                decisions.append(Decision(f, *gains, verdicts))
                if decisions[-1].named:
                    break
        step = Step(
            current,
            tuple(scores),
            tuple(fits),
            tuple(decisions),
            limit,
            settings.min_delta_bic,
            screen_limit,
        )
        steps.append(step)
        if step.chosen is None:
            break
        current = step.chosen.fit.fitted
    return steps


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
    checks: list[Check] = [Split(settings.heldout, oe)]
    if validation is not None:
        checks.append(SecondRecording(_undecimated(validation), oe))
    steps = decide(problem, base, settings, evidence, band, checks, clock)
    named = [st.chosen for st in steps if st.chosen is not None]
    final = named[-1].fit.fitted if named else base
    findings = [_finding(problem, d, st) for st in steps if (d := st.chosen) is not None]
    refused = [_refused(problem, d) for st in steps for d in st.decisions if not d.named]
    lof_before, lof_after = lack_of_fit_p(base, evidence.nu), lack_of_fit_p(final, evidence.nu)
    if refused:
        findings += refused
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


def _finding(problem: Problem, d: Decision, step: Step) -> dict[str, Any]:
    """One named finding of diagnosis.json."""
    f = d.fit
    cand = candidate(f.effect)
    runner = sorted((g for g in step.fits if g is not f), key=lambda g: -g.delta_bic)
    return {
        "effect": f.effect,
        "explanation": cand.explain(f.params, problem)
        + (
            f" With it the output error of the record falls from {f.base.cost:.4g} to "
            f"{f.fitted.cost:.4g} σ_x² (LR = {f.lr:.1f}, {f.k} parameters)."
        ),
        "location": cand.location(f.params, problem),
        "params": f.params,
        "at_bound": at_bounds(f.fitted.problem.spec, f.params),
        "delta_bic": f.delta_bic,
        "p_value": f.p_value,
        "lr": f.lr,
        "test": "output error",
        "record_ems_gain": d.ems_gain,
        "record_simulation_gain": d.simulation_gain,
        "heldout": [v.as_json() for v in d.verdicts],
        "runner_up": runner[0].effect if runner else "",
        "runner_up_delta_bic": runner[0].delta_bic if runner else math.nan,
    }


def _refused(problem: Problem, d: Decision) -> dict[str, Any]:
    """``unexplained`` at the place of a candidate that passed the statistics but not the
    rest of the rule: the record holds something there that this term does not explain in a
    way that carries over."""
    f = d.fit
    location = candidate(f.effect).location(f.params, problem)
    if not d.record_ok:
        which = "EMS" if d.ems_gain < 0 else "simulation error"
        why = f"with it the record's own {which} gets worse"
    elif not any(v.judged for v in d.verdicts):
        why = "no held-out check can judge it (" + "; ".join(v.why for v in d.verdicts) + ")"
    else:
        worst = min((v for v in d.verdicts if v.judged), key=lambda v: v.gain)
        why = f"on the {worst.on} it makes the fit worse ({100 * worst.gain:+.1f} %)"
    return {
        "effect": "unexplained",
        "explanation": (
            f"The record holds structure that {f.effect} lowers BIC by {f.delta_bic:.1f} "
            f"on, but {why}: it is not claimed."
        ),
        "location": location,
        "params": {},
        "delta_bic": f.delta_bic,
        "p_value": f.p_value,
        "rejected_candidate": {"effect": f.effect, "params": f.params, **_decision_json(d)},
    }


def _unexplained(model: Fitted, p: float, nu: int) -> dict[str, Any]:
    """``unexplained`` where the model misfits the record's noise and no candidate passes:
    located at the segment of the multiple shooting whose samples misfit most (its share of
    the cost over its share of the samples)."""
    pb, f = model.problem, model.fit
    r = (f.x_sim - pb.x) / f.x_scale
    seg = np.minimum(np.arange(pb.n) // f.segment_samples, f.n_segments - 1)
    per = np.bincount(seg, weights=r**2) / np.bincount(seg)
    s = int(np.argmax(per))
    idx = np.flatnonzero(seg == s)
    dof = max(f.n_residual - model.n_free - 2 * f.n_segments, 1)
    excess = float(f.cost - dof)
    return {
        "effect": "unexplained",
        "explanation": (
            f"The model leaves more output error than the record's noise accounts for "
            f"({f.cost:.4g} σ_x² over {dof} degrees of freedom, p = {p:.2g}), and no catalogue "
            f"term explains it. It misfits most over t = {pb.t[idx[0]]:.4g} to "
            f"{pb.t[idx[-1]]:.4g} s ({per[s]:.3g} σ_x² per sample there; the record is "
            f"{float(pb.t[-1] - pb.t[0]):.3g} s long)."
        ),
        "location": {
            "time_s": [float(pb.t[idx[0]]), float(pb.t[idx[-1]])],
            "position_m": [float(np.min(pb.x[idx])), float(np.max(pb.x[idx]))],
        },
        "params": {},
        # a term that explained all of it would lower BIC by about this, less its penalty
        "delta_bic": excess,
        "p_value": p,
    }


# -- output --------------------------------------------------------------------------------

#: The files :func:`write_diagnosis` writes under fixed names (plus its figures).
OUTPUT_FILES = ("diagnosis.json", "models.h5", "report.md", "report.html")


def write_diagnosis(diag: Diagnosis, out_dir: str | Path) -> dict[str, Path]:
    """Write diagnosis.json, models.h5, report.md, report.html and its figures into
    ``out_dir``."""
    from fricjax.diagnose.report import write_reports

    out = make_folder(out_dir)
    json_name, models_name = OUTPUT_FILES[:2]
    paths = {"json": out / json_name}
    with diag.clock.stage("report", "figures, models file and report"):
        paths["models"] = _write_models(diag, out / models_name)
        paths.update(write_reports(diag, out))
    # diagnosis.json last, so its timing holds the report stage too
    write_text_atomic(paths["json"], json.dumps(diag.as_json(), indent=2) + "\n")
    return paths


def _write_models(diag: Diagnosis, path: Path) -> Path:
    def fill(f: h5py.File) -> None:
        f.attrs["format"] = "fricjax-diagnosis-models-v1"
        f.attrs["recording"] = diag.recording
        for label, m in (("base", diag.base), ("final", diag.final)):
            model, spec, theta = m.reduced()
            g = f.create_group(label)
            g.attrs["model"] = model.name
            g.attrs["terms"] = json.dumps([t.name for t in model.terms])
            named = spec.as_dict(theta)
            g["names"] = np.array(list(named), dtype=h5py.string_dtype())
            g["values"] = np.array(list(named.values()), dtype=np.float64)
            g["free"] = np.array([spec[n].free for n in named], dtype=bool)
            g["units"] = np.array([spec[n].unit for n in named], dtype=h5py.string_dtype())

    return write_hdf5_atomic(path, fill)
