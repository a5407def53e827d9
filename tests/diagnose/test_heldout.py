"""Held-out checks of one record (fricjax.diagnose.heldout) and what the single-record report
makes of their verdicts: the record's EMS and simulation error are reported beside a term,
never a veto; the folds of the cross-validation interleave over the whole record; a held-out
cost moves no fixed parameter."""

from __future__ import annotations

import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np

from fricjax.diagnose.heldout import folds
from fricjax.diagnose.judge import EMS, SIMULATION
from fricjax.diagnose.run import _warnings
from fricjax.diagnose.select import Decision, Gain, Verdict
from fricjax.output_error import OutputErrorSettings


def test_the_folds_interleave_over_the_record_and_hold_each_sample_out_once() -> None:
    n, L, S = 1001, 50, 20
    masks = folds(np.minimum(np.arange(n) // L, S - 1), 5)
    assert len(masks) == 5
    np.testing.assert_array_equal(np.sum(masks, axis=0), np.ones(n))  # once each
    for j, m in enumerate(masks):
        held_segments = np.unique((np.arange(n)[m] // L).clip(max=S - 1))
        # whole segments, spread over the record
        assert list(held_segments) == list(range(j, S, 5))
        assert held_segments.max() - held_segments.min() >= S / 2
    # a record of fewer segments than folds holds out one segment at a time
    seg = np.minimum(np.arange(120) // 50, 2)
    assert [int(m.sum()) for m in folds(seg, 3)] == [50, 50, 20]


def _decision(ems: float, sim: float, *verdicts: Verdict) -> Decision:
    fit = SimpleNamespace(
        effect="position_bump",
        params={"bump_x0": 0.1, "bump_w": 0.01},
        delta_bic=30.0,
        p_value=1e-6,
    )
    gains = (Gain(EMS, ems), Gain(SIMULATION, sim))
    return Decision(fit, verdicts, gains)  # type: ignore[arg-type]


def test_the_record_s_ems_and_simulation_warn_but_never_refuse() -> None:
    good = Verdict("cross-validation", "5 interleaved folds", True, 0.4, 100.0, 60.0)
    worse = _decision(-0.15, -0.16, good)  # EMS 275 -> 315 N² on a real axis
    assert worse.named
    warnings = _warnings(worse)
    assert len(warnings) == 2 and "EMS gets worse" in warnings[0] and "-15.0 %" in warnings[0]
    assert _warnings(_decision(0.1, math.nan, good)) == []


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
