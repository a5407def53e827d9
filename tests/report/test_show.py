"""The identify summary says in plain words what the record does not determine."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from fricjax.config import Config
from fricjax.data.twin import read_truth
from fricjax.identify import IdentifySettings, identify
from fricjax.io.results import RunResult
from fricjax.problem import Problem
from fricjax.report.show import determination, run_summary, undetermined


@pytest.fixture(scope="module")
def twin_run(twin_problem: Problem, paper_config: Config) -> RunResult:
    """``fricjax identify data/paper_twin.h5 --config configs/paper.toml`` (its settings)."""
    settings = IdentifySettings.from_tables(paper_config.tables, source=paper_config.source)
    # as the CLI runs it: compiled for compile speed (one identification)
    return identify(twin_problem, dataclasses.replace(settings, fast_compile=True))


def test_the_twin_summary_names_the_friction_parameters_the_record_leaves_open(
    twin_run: RunResult, twin_path: Path
) -> None:
    # The physical fact first: on the 0.27 s twin F0, Fc, Fs, Fv land 40-50 % off the truth
    # (the fit's EMS is below the truth's, so the data prefer the wrong values).
    truth = read_truth(twin_path)
    est = twin_run.params
    for name in ("F0", "Fc", "Fs", "Fv"):
        assert abs(est[name] / truth[name] - 1) > 0.4, name
    # ... and the summary must say so, naming each and what would fix it.
    loose = undetermined(twin_run)
    assert {"F0", "Fc", "Fs", "Fv"} <= set(loose)
    assert "lower bound" in loose["Fc"] and "lower bound" in loose["Fs"]
    text = run_summary(twin_run)
    assert determination(twin_run) in text
    assert f"does NOT determine {len(loose)} of 26 parameters" in text
    for cure in ("longer record", "richer excitation", "fix a parameter"):
        assert cure in text
    # the well-determined large harmonics and omega are not accused
    assert "omega" not in loose and "Fp_9" not in loose


def test_a_huge_uncertainty_reads_as_a_multiple_not_sixteen_digits() -> None:
    from fricjax.report.show import share

    assert share(0.353) == "35 % of it"
    assert share(9.9) == "990 % of it"
    assert share(96239682103748.58) == "9.6e+13 times it"


def test_a_signed_parameter_near_zero_is_not_both_flagged_and_called_determined() -> None:
    # the rotary load-cell axis of tests/test_scaffold.py: offset 0.0063 ± 0.0067 N·m in a
    # box of ±38.6 N·m; the table flags it (σ against the value), the verdict judges it
    # against its box, and the summary says why the two differ
    import numpy as np

    run = RunResult(
        label="csaa", method="csaa", names=["offset", "Fc"], units=["N·m", "N·m"],
        value=np.array([0.0063, 14.83]), lower=np.array([-38.6, 0.0]),
        upper=np.array([38.6, 38.6]), fixed={}, cost=1.0, ems=1.0, cost_search=1.0,
        ems_search=1.0, std=np.array([0.0067, 0.017]), rel_std=np.array([1.06, 0.0012]),
        corr=np.eye(2), flags=[["weakly determined (rel. σ = 1.06 > 1)"], []],
        chain_x=np.zeros((1, 2)), chain_cost=np.zeros(1), traces={},
        minima_x=np.zeros((1, 2)), minima_cost=np.zeros(1), minima_count=np.ones(1),
    )  # fmt: skip
    assert undetermined(run) == {}
    words = determination(run)
    assert words.startswith("Every parameter is determined by this record")
    assert "offset: flagged because the value is near zero" in words
