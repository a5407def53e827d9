"""The diagnosis' stages (fricjax/diagnose/stages.py): time charged per stage, limits that act
only when hit, and a tiny budget on the bundled twin that reports what it left out."""

from __future__ import annotations

import json
import math
import os
import signal
import threading
import time
from dataclasses import replace
from pathlib import Path

import pytest

from fricjax.api import load
from fricjax.diagnose.catalogue import CATALOGUE
from fricjax.diagnose.report import write_diagnosis
from fricjax.diagnose.run import STAGE_LIMITS, DiagnoseSettings, diagnose
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
    with clock.stage("candidates"):
        now.t += 2.0
        with clock.stage("heldout", "held-out check of impact"):
            now.t += 3.0
        now.t += 1.5
    now.t += 0.25  # between stages: charged to none
    t = clock.summary()
    assert t["stages_s"] == {"candidates": 3.5, "heldout": 3.0}
    assert t["total_s"] == pytest.approx(6.75)
    assert [(e.stage, e.detail, e.elapsed_s) for e in events] == [
        ("candidates", STAGES["candidates"], 0.0),
        ("heldout", "held-out check of impact", 2.0),
    ]


def test_a_limit_acts_only_once_its_stage_or_the_total_has_run_past_it() -> None:
    now = Ticks()
    clock = Clock(limits={"heldout": 4.0}, total=10.0, now=now)
    with clock.stage("heldout"):
        now.t += 4.0
        assert not clock.over("heldout")  # at the limit, not past it
        now.t += 0.5
        assert clock.hit("heldout") == "heldout"
        assert not clock.over("candidates")  # another stage keeps its own time
        clock.untested("heldout", "impact")
    now.t += 6.0
    assert clock.hit("candidates") == "total"
    clock.untested("candidates", "impact")
    clock.untested("candidates", "stribeck")
    assert clock.not_tested() == ["impact", "stribeck"]
    skipped = clock.summary()["skipped"]
    assert [(s["stage"], s["limit"], s["at_s"]) for s in skipped] == [
        ("heldout", "heldout", 4.5),
        ("candidates", "total", 10.5),
        ("candidates", "total", 10.5),
    ]
    assert skipped[0]["what"] == "impact: not tested (time limit)"


def test_a_unit_that_would_end_past_a_limit_is_not_started() -> None:
    now = Ticks()
    clock = Clock(limits={"candidates": 10.0}, total=20.0, now=now)
    with clock.stage("candidates"):
        now.t += 6.0
        assert not clock.over("candidates", need=4.0)  # would end at the limit
        assert clock.hit("candidates", need=4.5) == "candidates"
        clock.untested("candidates", "impact", need=4.5)
    now.t += 8.0  # 14 s in all: 7 s of a 6 s unit would pass the total
    assert not clock.over("heldout", need=6.0)
    assert clock.hit("heldout", need=7.0) == "total"
    assert clock.summary()["skipped"][0]["limit"] == "candidates"


def test_time_limits_from_the_config_table() -> None:
    s = DiagnoseSettings.from_dict({"time_limit": 120, "stage_limits": {"candidates": 30}})
    assert s.time_limit == 120.0
    # a table sets the stages it names; the others keep their defaults
    assert s.stage_limits == {**STAGE_LIMITS, "candidates": 30}
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
    """With a budget spent before the first candidate, the base fit still runs and every
    simulable catalogue candidate is listed as not tested, none named, and the report says
    the diagnosis is incomplete. Slow: the base's output-error fit compiles (~40 s)."""
    _, cfg, problem = load(ROOT / "data" / "paper_twin.h5", ROOT / "configs" / "paper.toml")
    ident = IdentifySettings.from_tables(cfg.tables, source=cfg.source)
    ident = replace(ident, chains=8, anneal=replace(ident.anneal, max_levels=5), fast_compile=True)
    events: list[StageEvent] = []
    diag = diagnose(
        problem,
        identify_settings=ident,
        settings=DiagnoseSettings(time_limit=1e-6),
        on_stage=events.append,
    )
    paths = write_diagnosis(diag, tmp_path)
    doc = json.loads(paths["json"].read_text())
    applicable = [
        c.effect for c in CATALOGUE if c.simulable and c.applicable(problem.model, problem.spec)
    ]
    assert doc["not_tested"] == applicable and len(applicable) >= 8
    assert [f for f in doc["findings"] if f["effect"] != "unexplained"] == []
    assert ("candidates", "total") in {(s["stage"], s["limit"]) for s in doc["timing"]["skipped"]}
    assert {e.stage for e in events} >= {"base_fit", "candidates", "report"}
    report = paths["report"].read_text()
    assert "**Time limit hit**" in report


def test_a_stop_request_acts_as_every_limit_hit_and_says_so_first() -> None:
    now = Ticks()
    stop = threading.Event()
    clock = Clock(total=math.inf, now=now, stop=stop)
    with clock.stage("candidates"):
        assert not clock.over("candidates", need=1e9)  # no limit: anything may start
        stop.set()
        assert clock.hit("candidates") == "interrupted" and clock.hit("heldout")
        clock.untested("candidates", "impact")
    assert clock.not_tested() == ["impact"] and "stopped" in clock.skipped[0].what
    line = clock.headline()
    assert line.startswith("Interrupted (Ctrl-C)") and "impact" in line
    assert clock.summary()["interrupted"] is True
    # a time limit's headline names the limit instead
    timed = Clock(total=5.0, now=now)
    with timed.stage("candidates"):
        now.t += 6.0
        timed.untested("candidates", "stribeck")
    assert timed.headline().startswith("Time limit (5 s in all)") and "stribeck" in timed.headline()
    assert Clock(now=now).headline() == ""
    # a stage's own limit is named as such, with what lifts it
    staged = Clock(limits={"candidates": 2.0}, total=100.0, now=now)
    with staged.stage("candidates"):
        now.t += 3.0
        staged.untested("candidates", "impact")
    line = staged.headline()
    assert line.startswith("Time limit (2 s for candidates)") and "longer stage limit" in line


def test_ctrl_c_stops_the_work_in_flight_and_keeps_what_it_returns() -> None:
    from fricjax.cli import _stoppable

    stop = threading.Event()

    def work() -> str:
        # stands for a diagnosis: it checks the stop between units of work
        for _ in range(600):
            if stop.wait(0.05):
                return "what was judged"
        return "ran to the end"

    timer = threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGINT))
    timer.start()
    began = time.perf_counter()
    assert _stoppable(work, stop) == "what was judged"
    assert stop.is_set() and time.perf_counter() - began < 5.0
    # the command line's handler is back to Python's: a later Ctrl-C is a KeyboardInterrupt
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
