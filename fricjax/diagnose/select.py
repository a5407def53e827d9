"""Forward selection: the one rule of every diagnosis, of one recording or of several.

A diagnosis is a :class:`Judge` (how candidates are fitted and tested against the current
model), a list of held-out :class:`Check` s (does a candidate's gain carry over to data its
fit has not seen), a :class:`Rule` (the levels) and a
:class:`~fricjax.diagnose.stages.Clock`. :func:`select` runs the same steps for every
diagnosis, up to ``max_terms``:

1. every candidate the judge offers for the current model is fitted
   (:meth:`Judge.fit`; stage ``candidates``);
2. a candidate passes where its p (the judge's calibrated one) is below ``α/C``
   (Bonferroni over the C candidates of the step: valid whatever their dependence) and its
   ΔBIC above ``min_delta_bic``;
3. the passing candidates are taken by rank (the judge's measure of how much of the record
   each explains, less its penalty), best first; each is looked at once more
   (:meth:`Judge.confirm`: a fit may have stopped short), then judged by every check
   (stage ``heldout``). The first whose every judging check gains is named, with the
   passing candidates the record cannot tell from it (:meth:`Judge.vuong` not significant
   at ``ambiguity``): an ambiguity set, the best first. Where no check can judge a
   candidate, it is named on its statistics only if the judge says a term may stand so
   (:attr:`Judge.standalone`), and the finding says that no check could judge it.
4. the named candidate's model is the next step's current model; a step that names none
   ends the selection.

What a time limit leaves out is recorded on the clock (never named); a limit is checked
between units of work (one candidate's fits, one candidate's held-out checks).

The single-record diagnosis (:mod:`fricjax.diagnose.run`) plugs in the output-error judge
with cross-validation; the diagnosis across recordings (:mod:`fricjax.diagnose.across`) the
joint judge with leaving one recording out, and run-to-run drift as one more kind of
candidate.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Generic, Protocol, TypeVar

import numpy as np
from scipy import stats

from fricjax.diagnose.stages import Clock

__all__ = [
    "Alternative",
    "Check",
    "Decision",
    "Finding",
    "Gain",
    "Judge",
    "Rule",
    "Scored",
    "Step",
    "Verdict",
    "outcome",
    "refused",
    "refused_by_step",
    "select",
    "vuong_t",
]


class Scored(Protocol):
    """A candidate fitted beside the current model, as the rule reads it."""

    @property
    def name(self) -> str: ...

    @property
    def p_value(self) -> float: ...

    @property
    def delta_bic(self) -> float: ...

    @property
    def rank(self) -> float:
        """How much of the record it explains less its penalty (larger: better)."""
        ...

    def passes(self, limit: float, min_delta_bic: float) -> bool: ...


M = TypeVar("M")
F = TypeVar("F", bound=Scored)
M_contra = TypeVar("M_contra", contravariant=True)


@dataclass(frozen=True)
class Verdict:
    """The outcome of one held-out check of one candidate.

    Attributes:
        check: which check (``"cross-validation"``, ``"leave one recording out"``).
        on: the data it judged on, in words.
        judged: whether it could judge; ``why`` says why not.
        gain: ``1 − E_term/E_base`` on the held-out data (NaN when not judged).
        cost_base, cost_term: the two held-out costs (the judge's unit).
        parts: the check's own parts (a fold each), where it reports them.
    """

    check: str
    on: str
    judged: bool
    gain: float = math.nan
    cost_base: float = math.nan
    cost_term: float = math.nan
    why: str = ""
    parts: tuple[Verdict, ...] = ()

    @property
    def passed(self) -> bool:
        """Judged, and the term gained."""
        return self.judged and self.gain > 0

    def as_json(self) -> dict[str, Any]:
        return {
            "check": self.check,
            "on": self.on,
            "judged": self.judged,
            "gain": self.gain,
            "cost_base": self.cost_base,
            "cost_term": self.cost_term,
            **({"why": self.why} if self.why else {}),
            **({"parts": [p.as_json() for p in self.parts]} if self.parts else {}),
        }


class Check(Protocol[M_contra]):
    """A held-out check: ``judge(before, after, place)``, ``place`` where the candidate acts
    (:meth:`~fricjax.diagnose.catalogue.Candidate.location`)."""

    def judge(self, before: M_contra, after: M_contra, place: Mapping[str, Any]) -> Verdict: ...


@dataclass(frozen=True)
class Gain:
    """A figure a user sees, before and after a candidate, reported beside it and never
    judged: ``1 − after/before`` of ``metric`` (NaN where it cannot be computed)."""

    metric: str
    value: float


@dataclass(frozen=True)
class Alternative(Generic[F]):
    """A passing candidate the record cannot tell from the named one: the judge's Vuong
    ``t`` of the named fit over this one (``dof`` degrees of freedom) and its one-sided p."""

    fit: F
    t: float
    dof: int
    p_value: float


@dataclass(frozen=True)
class Decision(Generic[F]):
    """What the rule made of one candidate that passed the statistics: its held-out
    verdicts (they decide), the figures reported beside it (``gains``, never judged), the
    candidates it cannot be told from, and whether it may stand on its statistics where no
    check judges (:attr:`Judge.standalone`)."""

    fit: F
    verdicts: tuple[Verdict, ...]
    gains: tuple[Gain, ...] = ()
    alternatives: tuple[Alternative[F], ...] = ()
    standalone: bool = False

    @property
    def named(self) -> bool:
        """Every held-out check that judges gains, and at least one judges (or none can
        and the candidate may stand on its statistics)."""
        judged = [v for v in self.verdicts if v.judged]
        if not judged:
            return self.standalone
        return all(v.passed for v in judged)

    def gain(self, metric: str) -> float:
        """The reported gain of ``metric`` (NaN where not reported)."""
        return next((g.value for g in self.gains if g.metric == metric), math.nan)


@dataclass(frozen=True)
class Step(Generic[M, F]):
    """One step of forward selection: every candidate's fit, the decisions on the fits
    that passed the statistics (best first, up to the named one), the per-candidate limit
    α/C, and the model before."""

    current: M
    fits: tuple[F, ...]
    decisions: tuple[Decision[F], ...]
    limit: float
    min_delta_bic: float

    @property
    def chosen(self) -> Decision[F] | None:
        return next((d for d in self.decisions if d.named), None)


@dataclass(frozen=True)
class Finding:
    """One finding of a diagnosis, of one recording or several: an entry of diagnosis.json's
    ``findings`` (docs/formats.md).

    Attributes:
        effect: the catalogue name, ``run_drift`` or ``unexplained``.
        explanation: what, where and why, in plain words.
        location: where it acts (time, position, speed, frequency, recordings).
        params: the added term's parameters [SI].
        delta_bic: BIC(base) − BIC(base + it); > 0 favours it.
        p_value: its calibrated significance.
        name: how it is called where that is not ``effect`` (``drift of Fc``).
        heldout: the held-out verdicts that judged it.
        warnings: plain warnings where it makes what a user sees worse (reported only).
        alternatives: the candidates the data cannot tell from it (an ambiguity set), each
            with its Vuong ``t`` and p under ``evidence``.
        evidence: the judge's own figures (docs/formats.md lists each).
    """

    effect: str
    explanation: str
    location: dict[str, Any]
    params: dict[str, float]
    delta_bic: float
    p_value: float
    name: str = ""
    heldout: tuple[Verdict, ...] = ()
    warnings: tuple[str, ...] = ()
    alternatives: tuple[Finding, ...] = ()
    evidence: dict[str, Any] = field(default_factory=dict)

    @property
    def label(self) -> str:
        """How the finding is called: ``name``, else ``effect``."""
        return self.name or self.effect

    @property
    def named(self) -> bool:
        """A physical explanation (not ``unexplained``)."""
        return self.effect != "unexplained"

    @property
    def members(self) -> tuple[str, ...]:
        """The labels of the finding and of its alternatives, best first."""
        return (self.label, *(a.label for a in self.alternatives))

    def as_json(self) -> dict[str, Any]:
        """The diagnosis.json entry (docs/formats.md)."""
        out: dict[str, Any] = {"effect": self.effect}
        if self.name:
            out["name"] = self.name
        out |= {
            "explanation": self.explanation,
            "location": self.location,
            "params": self.params,
            "delta_bic": self.delta_bic,
            "p_value": self.p_value,
            **self.evidence,
        }
        if self.heldout:  # a named finding (an alternative and `unexplained` have none)
            out["warnings"] = list(self.warnings)
            out["heldout"] = [v.as_json() for v in self.heldout]
            out["alternatives"] = [a.as_json() for a in self.alternatives]
        return out


class Judge(Protocol[M, F]):
    """How one diagnosis fits and compares its candidates (module docstring)."""

    #: whether a candidate that no held-out check can judge may be named on its statistics
    standalone: bool

    def candidates(self, current: M) -> list[str]:
        """The candidates' names that may be added to ``current``."""
        ...

    def fit(self, current: M, names: Sequence[str], clock: Clock) -> list[F]:
        """Each named candidate fitted beside ``current``; one a time limit leaves out is
        recorded on ``clock`` as untested and absent from the result."""
        ...

    def confirm(self, fit: F) -> F:
        """A passing candidate looked at once more before its checks."""
        ...

    def base(self, fit: F) -> M:
        """The model ``fit`` is judged against."""
        ...

    def model(self, fit: F) -> M:
        """The model with the candidate."""
        ...

    def place(self, fit: F) -> Mapping[str, Any]:
        """Where the candidate acts."""
        ...

    def gains(self, fit: F) -> tuple[Gain, ...]:
        """Figures reported beside the candidate (never judged)."""
        ...

    def vuong(self, best: F, other: F) -> tuple[float, int]:
        """Vuong's t of ``best`` over ``other`` and its degrees of freedom."""
        ...


@dataclass(frozen=True)
class Rule:
    """The levels of the rule (justified on
    :class:`~fricjax.diagnose.run.DiagnoseSettings`): family-wise ``alpha``,
    ``min_delta_bic``, ``max_terms``, and the level ``ambiguity`` of Vuong's test that tells
    a passing candidate from the named one."""

    alpha: float = 0.01
    min_delta_bic: float = 10.0
    max_terms: int = 3
    ambiguity: float = 0.05


def select(
    judge: Judge[M, F],
    checks: Sequence[Check[M]],
    start: M,
    rule: Rule,
    clock: Clock,
) -> list[Step[M, F]]:
    """Forward selection from ``start`` by the one rule (module docstring)."""
    steps: list[Step[M, F]] = []
    current = start
    for _ in range(rule.max_terms):
        names = judge.candidates(current)
        if not names:
            break
        with clock.stage("candidates", f"fits of {len(names)} candidates"):
            fits = judge.fit(current, names, clock)
        limit = rule.alpha / len(names)
        passing = sorted(
            (f for f in fits if f.passes(limit, rule.min_delta_bic)), key=lambda f: -f.rank
        )
        decisions: list[Decision[F]] = []
        with clock.stage("heldout", "held-out checks"):
            for i, f in enumerate(passing):
                if clock.over("heldout"):
                    clock.untested("heldout", f.name)
                    continue
                clock.note(f"held-out checks of {f.name}")
                f = judge.confirm(f)
                if not f.passes(limit, rule.min_delta_bic):
                    continue
                verdicts = tuple(
                    ch.judge(judge.base(f), judge.model(f), judge.place(f)) for ch in checks
                )
                others = [g for g in passing[i + 1 :] if g.name != f.name]
                decision = Decision(
                    f,
                    verdicts,
                    judge.gains(f),
                    _alternatives(judge, f, others, rule.ambiguity),
                    judge.standalone,
                )
                decisions.append(decision)
                if decision.named:
                    break
        step = Step(current, tuple(fits), tuple(decisions), limit, rule.min_delta_bic)
        steps.append(step)
        if step.chosen is None:
            break
        current = judge.model(step.chosen.fit)
    return steps


def _alternatives(
    judge: Judge[M, F], named: F, others: Sequence[F], level: float
) -> tuple[Alternative[F], ...]:
    """The passing candidates the record does not prefer ``named`` over (Vuong's test at
    ``level``, one-sided), in rank order."""
    out = []
    for g in others:
        t, dof = judge.vuong(named, g)
        p = float(stats.t.sf(t, dof))
        if p >= level:
            out.append(Alternative(g, t, dof, p))
    return tuple(out)


def refused_by_step(
    steps: Sequence[Step[Any, Any]],
) -> list[tuple[Decision[Any], list[Decision[Any]]]]:
    """``(best, others)`` for each step that refused candidates, best = the largest rank.

    The candidates refused at one step are rival descriptions of the one residual the model
    leaves there, so they make one ``unexplained`` finding, not one each. A candidate
    refused at one step and named at a later one is a finding, not both; one refused at
    several steps counts at the first."""
    seen = {st.chosen.fit.name for st in steps if st.chosen is not None}
    out = []
    for st in steps:
        rivals = [d for d in st.decisions if not d.named and d.fit.name not in seen]
        seen |= {d.fit.name for d in rivals}
        if rivals:
            best = max(rivals, key=lambda d: d.fit.rank)
            out.append(
                (best, sorted((d for d in rivals if d is not best), key=lambda d: -d.fit.rank))
            )
    return out


def outcome(step: Step[Any, Any], fit: Scored) -> str:
    """What the rule made of one candidate of a step, in words (reports, diagnosis.json); a
    NaN p is a test the data cannot make."""
    decided = {d.fit.name: d for d in step.decisions}
    chosen = step.chosen
    if fit.name in decided:
        return "named" if decided[fit.name].named else "refused (held out)"
    if chosen is not None and fit.name in {a.fit.name for a in chosen.alternatives}:
        return f"cannot be told from {chosen.fit.name}"
    if fit.passes(step.limit, step.min_delta_bic):
        return f"passes; {chosen.fit.name} explains more" if chosen is not None else "passes"
    if math.isnan(fit.p_value):
        return "not determined by these recordings"
    if not fit.p_value < step.limit:
        return "not significant"
    return "below the ΔBIC bar"


def vuong_t(blocks: np.ndarray) -> tuple[float, int]:
    """Vuong's statistic of two models on the same data from ``blocks`` [S], the sums over
    S blocks of ``d_i = r_other,i² − r_best,i²`` (blocks long against the residual's
    correlation, so that their sums are nearly independent): ``t = mean(D)/(sd(D)/√S)``,
    Student's t with S − 1 degrees of freedom where the two explain the data equally
    well. Returns (t, S − 1); t large: ``best`` is better."""
    S = blocks.shape[0]
    sd = float(np.std(blocks, ddof=1)) if S > 1 else math.inf
    total = float(np.sum(blocks))
    if sd > 0:
        t = float(np.mean(blocks) / (sd / math.sqrt(S)))
    else:  # every block alike: a sure preference, or none where the fits are the same
        t = math.copysign(math.inf, total) if total != 0 else 0.0
    return t, max(S - 1, 1)


def refused(
    best: Decision[Any],
    rivals: Sequence[Decision[Any]],
    location: dict[str, Any],
    rejected: dict[str, Any],
) -> Finding:
    """``unexplained`` at the place (``location``) of a candidate that passed the
    statistics but not the held-out checks: the data hold something there that it does not
    explain in a way that carries over to data its fit has not seen. ``rivals``: the other
    candidates refused at the same step (:func:`refused_by_step`); ``rejected``: the refused
    candidate as the judge reports it (``rejected_candidate``)."""
    f = best.fit
    judged = [v for v in best.verdicts if v.judged]
    if not judged:
        why = "no held-out check can judge it (" + "; ".join(v.why for v in best.verdicts) + ")"
    else:
        worst = min(judged, key=lambda v: v.gain)
        why = f"on the {worst.on} it makes the held-out fit worse ({100 * worst.gain:+.1f} %)"
    names = [r.fit.name for r in rivals]
    also = (
        f" {words(names)} fitted it too and {'was' if len(names) == 1 else 'were'} refused as well."
        if names
        else ""
    )
    return Finding(
        effect="unexplained",
        explanation=(
            f"The data hold structure that {f.name} lowers BIC by {f.delta_bic:.1f} on, but "
            f"{why}: it is not claimed.{also}"
        ),
        location=location,
        params={},
        delta_bic=f.delta_bic,
        p_value=f.p_value,
        evidence={
            "rejected_candidate": rejected,
            "rejected_alternatives": [
                {"effect": r.fit.name, "delta_bic": r.fit.delta_bic, "p_value": r.fit.p_value}
                for r in rivals
            ],
        },
    )


def words(names: Sequence[str]) -> str:
    """``a``, ``a and b``, ``a, b and c``."""
    return names[0] if len(names) == 1 else f"{', '.join(names[:-1])} and {names[-1]}"
