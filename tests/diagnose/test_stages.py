"""The diagnosis' stages (fricjax/diagnose/stages.py): time charged per stage, limits that act
only when hit, and a tiny budget on the bundled twin that reports what it left out."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import pytest

from fricjax.api import load
from fricjax.diagnose.catalogue import CATALOGUE
from fricjax.diagnose.run import STAGE_LIMITS, DiagnoseSettings, diagnose, write_diagnosis
from fricjax.diagnose.stages import LIMITED, STAGES, Clock, StageEvent
from fricjax.errors import FricjaxError
from fricjax.identify import IdentifySettings

ROOT = Path(__file__).resolve().parents[2]


class Ticks:
    """A clock the test moves by hand [s]."""

    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_time_is_charged_to_the_innermost_stage_and_sums_to_the_total() -> None:
    now = Ticks()
    events: list[StageEvent] = []
    clock = Clock(on_stage=events.append, now=now)
    with clock.stage("scores"):
        now.t += 2.0
        with clock.stage("refits", "refit of impact"):
            now.t += 3.0
        now.t += 1.5
    now.t += 0.25  # between stages: charged to none
    t = clock.summary()
    assert t["stages_s"] == {"scores": 3.5, "refits": 3.0}
    assert t["total_s"] == pytest.approx(6.75)
    assert [(e.stage, e.detail, e.elapsed_s) for e in events] == [
        ("scores", STAGES["scores"], 0.0),
        ("refits", "refit of impact", 2.0),
    ]


def test_a_limit_acts_only_once_its_stage_or_the_total_has_run_past_it() -> None:
    now = Ticks()
    clock = Clock(limits={"refits": 4.0}, total=10.0, now=now)
    with clock.stage("refits"):
        now.t += 4.0
        assert not clock.over("refits")  # at the limit, not past it
        now.t += 0.5
        assert clock.hit("refits") == "refits"
        assert not clock.over("scores")  # another stage keeps its own time
        clock.untested("refits", "impact")
    now.t += 6.0
    assert clock.hit("scores") == "total"
    clock.untested("scores", "impact")
    clock.untested("scores", "stribeck")
    assert clock.not_tested() == ["impact", "stribeck"]
    skipped = clock.summary()["skipped"]
    assert [(s["stage"], s["limit"], s["at_s"]) for s in skipped] == [
        ("refits", "refits", 4.5),
        ("scores", "total", 10.5),
        ("scores", "total", 10.5),
    ]
    assert skipped[0]["what"] == "impact: not tested (time limit)"


def test_time_limits_from_the_config_table() -> None:
    s = DiagnoseSettings.from_dict({"time_limit": 120, "stage_limits": {"scores": 30}})
    assert s.time_limit == 120.0
    # a table sets the stages it names; the others keep their defaults
    assert s.stage_limits == {**STAGE_LIMITS, "scores": 30}
    assert set(STAGE_LIMITS) == set(LIMITED)
    assert DiagnoseSettings.from_dict({"time_limit": math.inf}).clock().total == math.inf
    with pytest.raises(FricjaxError, match=r"\[diagnose\]\.stage_limits: must be a table"):
        DiagnoseSettings.from_dict({"stage_limits": {"report": 5}})
    with pytest.raises(FricjaxError, match=r"--time-limit: must be > 0"):
        DiagnoseSettings.from_dict({"time_limit": 0}, flags=True)


@pytest.mark.slow
def test_a_tiny_budget_on_the_twin_lists_every_candidate_it_left_untested(
    tmp_path: Path,
) -> None:
    """With a budget spent before the first score test, the base fit and its maps still run
    and every catalogue candidate is listed as not tested, none named; the maps after the
    findings are skipped and said so in diagnosis.json and the report. Slow: the base fit,
    its GLS fit and the maps compile (~20 s of CPU), which no limit cuts."""
    _, cfg, problem = load(ROOT / "data" / "paper_twin.h5", ROOT / "configs" / "paper.toml")
    ident = IdentifySettings.from_tables(cfg.tables, source=cfg.source)
    ident = replace(ident, chains=8, anneal=replace(ident.anneal, max_levels=5), fast_compile=True)
    events: list[StageEvent] = []
    diag = diagnose(
        problem,
        identify_settings=ident,
        settings=DiagnoseSettings(n_mc=50, time_limit=1e-6),
        on_stage=events.append,
    )
    paths = write_diagnosis(diag, tmp_path)
    doc = json.loads(paths["json"].read_text())
    applicable = [c.effect for c in CATALOGUE if c.applicable(problem.model, problem.spec)]
    assert doc["not_tested"] == applicable and len(applicable) >= 8
    assert [f for f in doc["findings"] if f["effect"] != "unexplained"] == []
    skipped = {(s["stage"], s["limit"]) for s in doc["timing"]["skipped"]}
    assert ("scores", "total") in skipped and ("locate", "total") in skipped
    assert doc["locate_after_skipped"] == "time limit"
    assert diag.selection.steps == []  # nothing scored, so no step
    assert set(doc["timing"]["stages_s"]) >= {"base_fit", "whitening", "locate", "report"}
    assert {e.stage for e in events} >= {"base_fit", "whitening", "scores", "locate", "report"}
    report = paths["report"].read_text()
    assert "**Not tested (time limit)**: " + ", ".join(applicable) in report
    assert "**Time limit hit**" in report
    assert "Nothing is missing" not in report  # what was not tested cannot be ruled out
