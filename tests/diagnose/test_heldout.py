"""Held-out checks and the rule that uses them (fricjax.diagnose.heldout, run.Decision): a term
is named only where it improves the record's own fit and gains in every check that can judge
it; a part that never reaches a term's place does not judge it; a record too short to split
says so."""

from __future__ import annotations

import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np

from fricjax.diagnose.heldout import Verdict, record_part, too_short, untested_place
from fricjax.diagnose.run import Decision, _refused
from fricjax.output_error import OutputErrorSettings


def _record(n: int, rate: float = 1000.0) -> SimpleNamespace:
    t = np.arange(n) / rate
    return SimpleNamespace(t=t, x=0.01 * np.sin(2 * np.pi * 5 * t), n=n)


def test_a_part_that_never_reaches_the_place_cannot_judge_and_one_that_does_can() -> None:
    part = _record(300)
    lo, hi = float(part.x.min()), float(part.x.max())
    assert untested_place({"position_m": [hi + 0.001, hi + 0.002]}, part)
    assert not untested_place({"position_m": [lo, lo + 0.001]}, part)
    assert untested_place({"time_s": [1.0, 1.1]}, part)  # the part ends at 0.299 s
    assert not untested_place({"velocity_mps": [0.0, 0.1]}, part)  # no place: any part


def test_a_training_part_with_fewer_samples_than_twice_its_unknowns_is_too_short() -> None:
    settings = OutputErrorSettings(segment_s=0.05)
    # 190 samples at 1 kHz: 4 segments (8 states) + 26 parameters = 34 unknowns, 68 needed
    assert too_short(_record(190), 26, settings) == ""
    # 60 samples: 1 segment, 2 + 26 = 28 unknowns, 56 needed: still enough; 50 is not
    assert too_short(_record(60), 26, settings) == ""
    assert "too short" in too_short(_record(50), 26, settings)


def test_a_record_part_keeps_where_it_lies_in_the_record() -> None:
    pb = SimpleNamespace(
        t=np.arange(10.0), x=np.arange(10.0), v=np.zeros(10), a=np.zeros(10), u=np.zeros(10)
    )
    from dataclasses import dataclass

    @dataclass(frozen=True)
    class P:
        t: np.ndarray
        x: np.ndarray
        v: np.ndarray
        a: np.ndarray
        u: np.ndarray
        window: tuple[int, int] | None = None
        rest: np.ndarray | None = None

        @property
        def n(self) -> int:
            return self.t.shape[0]

    part = record_part(P(pb.t, pb.x, pb.v, pb.a, pb.u), 7, 10)
    assert part.window == (7, 10) and list(part.x) == [7.0, 8.0, 9.0]


def _decision(ems: float, sim: float, *verdicts: Verdict) -> Decision:
    fit = SimpleNamespace(
        effect="position_bump",
        params={"bump_x0": 0.1, "bump_w": 0.01},
        delta_bic=30.0,
        p_value=1e-6,
    )
    return Decision(fit, ems, sim, verdicts)  # type: ignore[arg-type]


def test_a_candidate_that_worsens_the_record_s_ems_is_refused_whatever_it_gains_held_out() -> None:
    good = Verdict("split", "last 30 % of the record", True, 0.4, 100.0, 60.0)
    assert _decision(0.1, 0.05, good).named
    refused = _decision(-0.15, 0.05, good)  # EMS 275 -> 315 N² on a real axis
    assert not refused.named and not refused.record_ok and refused.heldout_ok
    assert not _decision(0.1, -0.16, good).named  # the simulated position gets worse


def test_a_term_must_gain_in_every_check_that_judges_and_one_must_judge() -> None:
    split_gain = Verdict("split", "last 30 %", True, 0.2, 10.0, 8.0)
    second_loss = Verdict("second recording", "the second recording", True, -0.1, 10.0, 11.0)
    untested = Verdict("split", "the record's split", False, why="never reaches x 0.3 m")
    assert not _decision(0.1, 0.1, split_gain, second_loss).named
    assert _decision(0.1, 0.1, untested, Verdict("second recording", "2nd", True, 0.3)).named
    assert not _decision(0.1, 0.1, untested).named  # no check judges: not named
    # the simulation error of a model the simulator cannot integrate is no veto
    assert _decision(0.1, math.nan, split_gain).named


def test_a_refused_candidate_is_unexplained_at_its_place_and_says_why() -> None:
    pb = SimpleNamespace()
    good = Verdict("split", "last 30 % of the record", True, 0.4, 100.0, 60.0)
    f = _refused(pb, _decision(-0.15, 0.05, good))  # type: ignore[arg-type]
    assert f["effect"] == "unexplained" and "EMS gets worse" in f["explanation"]
    assert f["location"]["position_m"] == [0.1 - 0.02, 0.1 + 0.02]
    assert f["rejected_candidate"]["effect"] == "position_bump"


def test_a_held_out_cost_moves_no_parameter_the_spec_fixes(twin_problem) -> None:
    # the twin's spec fixes mass (its last parameter) and delta: a held-out cost fits the
    # segment states only, so a 20 % wrong fixed mass must cost more than the right one,
    # and the right one stays near the noise level (E ≈ n_residual in units of σ_x²)
    from fricjax.data.twin import PAPER_TRUTH
    from fricjax.diagnose.evidence import record_noise
    from fricjax.diagnose.heldout import fixed_cost

    spec = twin_problem.spec
    assert spec.names[-1] == "mass" and not spec["mass"].free
    settings = OutputErrorSettings(segment_s=0.05, x_scale=record_noise(twin_problem).sigma_x)
    truth = spec.as_dict(twin_problem.theta(PAPER_TRUTH))
    right = fixed_cost(twin_problem, truth, settings)
    heavy = replace(
        twin_problem,
        spec=replace(
            spec,
            params=tuple(
                replace(q, init=q.init * 1.2, lower=q.init * 1.2, upper=q.init * 1.2)
                if q.name == "mass"
                else q
                for q in spec.params
            ),
        ),
    )
    wrong = fixed_cost(heavy, truth, settings)
    assert right < 2.0 * twin_problem.n
    assert wrong > 3.0 * right
