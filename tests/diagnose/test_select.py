"""Forward selection, the one rule of every diagnosis (fricjax.diagnose.select), driven by a
toy judge whose fits are numbers: Bonferroni over the step's candidates, the best rank first,
a term named only where every check that judges gains, an ambiguity set where Vuong's test
cannot separate, a term no check can judge named only where the judge allows it, a time limit
that leaves candidates untested, and one ``unexplained`` group per step of refusals."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

from fricjax.diagnose.select import (
    Decision,
    Gain,
    Rule,
    Step,
    Verdict,
    refused,
    refused_by_step,
    select,
    vuong_t,
)
from fricjax.diagnose.stages import Clock


@dataclass(frozen=True)
class Fit:
    """A candidate whose statistics are given: ``rank`` is its ΔBIC."""

    name: str
    p_value: float
    rank: float
    active: tuple[str, ...] = ()

    @property
    def delta_bic(self) -> float:
        return self.rank

    def passes(self, limit: float, min_delta_bic: float) -> bool:
        return self.p_value < limit and self.delta_bic > min_delta_bic


@dataclass
class ToyJudge:
    """Candidates with fixed statistics per step (``table[len(active)]``), Vuong's t given
    per pair (``t``, default large: separated)."""

    table: list[dict[str, tuple[float, float]]]
    t: Mapping[tuple[str, str], float] = field(default_factory=dict)
    standalone: bool = False
    fitted: list[str] = field(default_factory=list)

    def candidates(self, current: tuple[str, ...]) -> list[str]:
        step = self.table[len(current)] if len(current) < len(self.table) else {}
        return [n for n in step if n not in current]

    def fit(self, current: tuple[str, ...], names: Sequence[str], clock: Clock) -> list[Fit]:
        out = []
        for n in names:
            if clock.over("candidates"):
                clock.untested("candidates", n)
                continue
            self.fitted.append(n)
            p, rank = self.table[len(current)][n]
            out.append(Fit(n, p, rank, (*current, n)))
        return out

    def confirm(self, fit: Fit) -> Fit:
        return fit

    def base(self, fit: Fit) -> tuple[str, ...]:
        return fit.active[:-1]

    def model(self, fit: Fit) -> tuple[str, ...]:
        return fit.active

    def place(self, fit: Fit) -> Mapping[str, Any]:
        return {"time_s": [0.0, 1.0]}

    def gains(self, fit: Fit) -> tuple[Gain, ...]:
        return (Gain("EMS", 0.1),)

    def vuong(self, best: Fit, other: Fit) -> tuple[float, int]:
        return self.t.get((best.name, other.name), 10.0), 20


@dataclass(frozen=True)
class Gains:
    """A check whose verdict on each term is given (``None``: cannot judge)."""

    gain: Mapping[str, float | None]

    def judge(self, before: Any, after: tuple[str, ...], place: Mapping[str, Any]) -> Verdict:
        g = self.gain.get(after[-1], 0.5)
        if g is None:
            return Verdict("toy", "nothing", False, why="cannot")
        return Verdict("toy", "the held-out part", True, g, 1.0, 1.0 - g)


def test_the_best_passing_candidate_is_named_and_the_next_step_starts_from_it() -> None:
    judge = ToyJudge(
        [
            {"a": (1e-5, 40.0), "b": (1e-6, 90.0), "c": (0.2, 50.0)},
            {"a": (1e-5, 30.0), "c": (0.5, 1.0)},
            {"c": (0.5, 1.0)},
        ]
    )
    steps = select(judge, [Gains({})], (), Rule(alpha=0.01, max_terms=3), Clock())
    assert [st.chosen.fit.name for st in steps if st.chosen] == ["b", "a"]
    # Bonferroni over the step's candidates: 0.01/3, then 0.01/2, then 0.01/1
    assert [st.limit for st in steps] == pytest.approx([0.01 / 3, 0.01 / 2, 0.01])
    assert steps[1].current == ("b",) and steps[-1].chosen is None
    # c never passes (p = 0.2): no decision is made on it
    assert all(d.fit.name != "c" for st in steps for d in st.decisions)


def test_a_term_that_loses_in_a_check_is_refused_and_the_next_is_judged() -> None:
    judge = ToyJudge([{"a": (1e-9, 80.0), "b": (1e-9, 60.0)}])
    (step,) = select(judge, [Gains({"a": -0.3})], (), Rule(max_terms=1), Clock())
    assert [d.fit.name for d in step.decisions] == ["a", "b"]
    assert not step.decisions[0].named and step.chosen is step.decisions[1]
    # one refusal at one step: one group, led by the refused one
    ((best, rest),) = refused_by_step([step])
    assert best.fit.name == "a" and rest == []


def test_candidates_the_record_cannot_separate_are_an_ambiguity_set() -> None:
    # Vuong's t of a over b 0.3 (p ≈ 0.38 one-sided, 20 dof): not separated; over c 4 (p ≈
    # 3e-4): separated
    judge = ToyJudge(
        [{"a": (1e-9, 80.0), "b": (1e-9, 79.0), "c": (1e-9, 20.0)}],
        t={("a", "b"): 0.3, ("a", "c"): 4.0},
    )
    (step,) = select(judge, [Gains({})], (), Rule(max_terms=1, ambiguity=0.05), Clock())
    chosen = step.chosen
    assert chosen is not None and chosen.fit.name == "a"
    assert [a.fit.name for a in chosen.alternatives] == ["b"]
    assert chosen.alternatives[0].p_value == pytest.approx(0.3838, abs=1e-3)


def test_a_term_no_check_can_judge_stands_on_its_statistics_only_where_the_judge_allows() -> None:
    table = [{"a": (1e-9, 80.0)}]
    blind = [Gains({"a": None})]
    (step,) = select(ToyJudge(table), blind, (), Rule(max_terms=1), Clock())
    assert step.chosen is None  # one record: a term nothing can check is not named
    (step,) = select(ToyJudge(table, standalone=True), blind, (), Rule(max_terms=1), Clock())
    assert step.chosen is not None and not step.chosen.verdicts[0].judged


def test_a_time_limit_leaves_candidates_untested_and_names_nothing_untested() -> None:
    judge = ToyJudge([{"a": (1e-9, 80.0), "b": (1e-9, 60.0)}])
    clock = Clock(total=0.0)
    (step,) = select(judge, [Gains({})], (), Rule(max_terms=1), clock)
    assert judge.fitted == [] and step.fits == () and step.chosen is None
    assert clock.not_tested() == ["a", "b"]


def _decision(name: str, rank: float, named: bool) -> Decision[Fit]:
    verdict = Verdict("toy", "held out", True, 0.5 if named else -0.5)
    return Decision(Fit(name, 1e-9, rank), (verdict,))


def _step(*decisions: Decision[Fit]) -> Step[Any, Fit]:
    return Step((), (), decisions, 0.01, 10.0)


def test_the_candidates_refused_at_one_step_make_one_finding_led_by_the_best() -> None:
    d = _decision
    steps = [
        _step(d("drift", 347, False), d("bump", 339, False), d("stribeck", 75, True)),
        _step(d("bump", 120, False), d("impact", 117, False), d("harmonic", 46, False)),
        _step(d("drift", 30, False)),
    ]

    def groups(steps: list[Step[Any, Fit]]) -> list[tuple[str, list[str]]]:
        return [(b.fit.name, [r.fit.name for r in rest]) for b, rest in refused_by_step(steps)]

    # one finding a step; bump and drift counted at the step that first refused them
    assert groups(steps) == [("drift", ["bump"]), ("impact", ["harmonic"])]
    # a term refused first and named later is a finding only
    assert groups([steps[1], _step(d("impact", 90, True))]) == [("bump", ["harmonic"])]


def test_a_reported_gain_is_read_by_its_metric_and_nan_when_absent() -> None:
    d = Decision(Fit("a", 1e-9, 50.0), (), (Gain("EMS", -0.2),))
    assert d.gain("EMS") == -0.2 and math.isnan(d.gain("simulation"))


def test_vuong_s_t_is_the_mean_block_difference_over_its_standard_error() -> None:
    t, dof = vuong_t(np.array([1.0, 2.0, 3.0, 4.0, 5.0]))
    # mean 3, sd √2.5: t = 3 / (√2.5 / √5) = 3·√2
    assert t == pytest.approx(3 * math.sqrt(2)) and dof == 4
    # two fits that are the same: no preference, never an infinite one
    assert vuong_t(np.zeros(6)) == (0.0, 5)
    assert vuong_t(np.full(4, 2.0))[0] == math.inf


def test_a_refused_candidate_is_unexplained_at_its_place_and_says_why() -> None:
    bad = Verdict("cross-validation", "5 interleaved folds", True, -0.3, 100.0, 130.0)
    best = Decision(Fit("position_bump", 1e-9, 40.0), (bad,))
    rivals = [_decision("impact", 30.0, False), _decision("friction_drift", 20.0, False)]
    place = {"position_m": [0.08, 0.12]}
    f = refused(best, rivals, place, {"effect": "position_bump"})
    assert f.effect == "unexplained" and not f.named and f.params == {}
    assert "held-out fit worse (-30.0 %)" in f.explanation
    assert "impact and friction_drift fitted it too and were refused" in f.explanation
    assert f.location == place and f.delta_bic == 40.0
    doc = f.as_json()
    assert doc["rejected_candidate"]["effect"] == "position_bump"
    assert [r["effect"] for r in doc["rejected_alternatives"]] == ["impact", "friction_drift"]
    assert "alternatives" not in doc and "heldout" not in doc  # not a named finding
