"""The diagnosis as named stages: their wall time, live progress events and hard time limits.

A :class:`Clock` is handed down the diagnosis of one recording or several
(:func:`~fricjax.diagnose.run.diagnose`, :func:`~fricjax.diagnose.across.diagnose_across`,
and the forward selection both run, :func:`~fricjax.diagnose.select.select`). Each stage is
entered with :meth:`Clock.stage` (time charged to the innermost open stage, so nested
stages are not counted twice); work that a limit may cut asks :meth:`Clock.over` first and, when the
answer is yes, records what it leaves out with :meth:`Clock.skip`. A limit acts only
when hit: below every limit the diagnosis runs exactly as without a clock.

A limit is checked between units of work (one candidate's output-error fits, one
candidate's held-out checks), so a stage overruns its limit by at most one unit. A stop
request (``stop``, set by Ctrl-C in the command line) acts as a limit hit everywhere at
once: the work in flight ends, the rest is recorded as left out, and what was judged is
reported, marked interrupted.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

# name: what the stage does (the progress display and the report's timing table)
STAGES: dict[str, str] = {
    "base_fit": "base fit (identify, then output error from its estimate)",
    "candidates": "every candidate's fits (output error; joint fits across recordings)",
    "heldout": "record gains and held-out checks of the candidates that pass",
    "report": "report, plots and models file",
}
# the stages whose work a limit can cut (the others are a single step the diagnosis needs)
LIMITED = ("candidates", "heldout")
#: Default seconds for a whole diagnosis (``DiagnoseSettings.time_limit``): the bound a
#: user waits for on any recording up to 30 s. Here, beside the clock, so that the
#: command line can show it without importing the diagnosis.
TIME_LIMIT_S = 180.0


@dataclass(frozen=True)
class StageEvent:
    """One progress event: ``stage`` (a key of :data:`STAGES`), what it is doing, and the
    seconds since the diagnosis started."""

    stage: str
    detail: str
    elapsed_s: float


OnStage = Callable[[StageEvent], None]


@dataclass(frozen=True)
class Skipped:
    """Work left out at ``stage`` because a time limit was hit ``at_s`` seconds in."""

    stage: str
    what: str
    at_s: float
    limit: str  # which limit: "total" or the stage's own
    effect: str = ""  # the candidate left untested, if the work was testing one


@dataclass
class Clock:
    """Wall time per stage, progress events and the time limits of one diagnosis.

    ``limits``: seconds per stage (keys of :data:`LIMITED`; a missing key is no limit);
    ``total``: seconds for the whole diagnosis (``inf``: none); ``on_stage``: called with
    every :class:`StageEvent`; ``now``: the clock [s] (a test may drive it); ``stop``: set
    from another thread to stop the diagnosis as if every limit were hit."""

    limits: Mapping[str, float] = field(default_factory=dict)
    total: float = math.inf
    on_stage: OnStage | None = None
    now: Callable[[], float] = time.perf_counter
    stop: threading.Event | None = None
    spent: dict[str, float] = field(default_factory=dict)
    skipped: list[Skipped] = field(default_factory=list)
    _open: list[str] = field(default_factory=list)
    _mark: float = 0.0
    _start: float = math.nan

    def __post_init__(self) -> None:
        self._start = self._mark = self.now()

    def elapsed(self) -> float:
        """Seconds since the clock started."""
        return self.now() - self._start

    def _charge(self) -> None:
        t = self.now()
        if self._open:
            name = self._open[-1]
            self.spent[name] = self.spent.get(name, 0.0) + t - self._mark
        self._mark = t

    @contextmanager
    def stage(self, name: str, detail: str = "") -> Iterator[None]:
        """Time the block as stage ``name`` (nested: the outer stage pauses)."""
        if name not in STAGES:
            raise ValueError(f"unknown stage {name!r}")
        self._charge()
        self._open.append(name)
        self.note(detail or STAGES[name])
        try:
            yield
        finally:
            self._charge()
            self._open.pop()

    def note(self, detail: str) -> None:
        """Tell the progress display what the current stage is doing."""
        if self.on_stage is not None:
            stage = self._open[-1] if self._open else ""
            self.on_stage(StageEvent(stage, detail, self.elapsed()))

    def used(self, name: str) -> float:
        """Seconds charged to stage ``name`` so far, the running part included."""
        running = self.now() - self._mark if self._open and self._open[-1] == name else 0.0
        return self.spent.get(name, 0.0) + running

    def hit(self, name: str, need: float = 0.0) -> str:
        """Which limit stops more work at stage ``name``: ``"total"``, the stage's own
        (``name``), or ``""`` (none hit). ``need`` [s]: the expected length of the unit of
        work about to start; a unit that would end past a limit is not started, so a limit
        is overrun by at most the error of that expectation, not by a whole unit.
        ``"interrupted"`` once :attr:`stop` is set."""
        if self.interrupted:
            return "interrupted"
        if self.elapsed() + need > self.total:
            return "total"
        if self.used(name) + need > self.limits.get(name, math.inf):
            return name
        return ""

    @property
    def interrupted(self) -> bool:
        """Whether a stop was requested (Ctrl-C)."""
        return self.stop is not None and self.stop.is_set()

    def over(self, name: str, need: float = 0.0) -> bool:
        """Whether a limit stops more work at stage ``name`` (``need``: as in :meth:`hit`)."""
        return bool(self.hit(name, need))

    def skip(self, name: str, what: str, effect: str = "", need: float = 0.0) -> None:
        """Record ``what`` as left out at stage ``name`` for lack of time (``effect``: the
        candidate it leaves untested; ``need``: as in :meth:`hit`)."""
        item = Skipped(name, what, self.elapsed(), self.hit(name, need) or "total", effect)
        self.skipped.append(item)
        self.note(f"{'stopped' if item.limit == 'interrupted' else 'time limit'}: {what}")

    def untested(self, name: str, effect: str, need: float = 0.0) -> None:
        """Record candidate ``effect`` as not tested at stage ``name`` (time limit)."""
        why = "stopped" if self.interrupted else "time limit"
        self.skip(name, f"{effect}: not tested ({why})", effect, need)

    def headline(self) -> str:
        """One sentence for the first lines of a verdict when work was left out (a limit
        hit, or Ctrl-C), naming the limit and the candidates left untested; "" when none."""
        if not self.skipped:
            return ""
        left = self.not_tested()
        untested = (
            f"{len(left)} candidate(s) not tested: {', '.join(left)}"
            if left
            else "some checks were not run"
        )
        if self.interrupted:
            return f"Interrupted (Ctrl-C) at {self.skipped[0].at_s:.0f} s: incomplete, {untested}."
        first = self.skipped[0]
        if first.limit in self.limits:  # a stage's own limit ([diagnose.stage_limits])
            which, longer = f"{self.limits[first.limit]:g} s for {first.limit}", "stage limit"
        else:
            which, longer = f"{self.total:g} s in all", "--time-limit"
        return (
            f"Time limit ({which}) hit at {first.at_s:.0f} s: incomplete, {untested}; a "
            f"longer {longer} tests them."
        )

    def not_tested(self) -> list[str]:
        """The candidates a limit left untested, each once, in the order they were met."""
        return list(dict.fromkeys(s.effect for s in self.skipped if s.effect))

    def summary(self) -> dict[str, Any]:
        """The ``timing`` section of diagnosis.json: seconds per stage (in
        :data:`STAGES` order), the limits, and what was skipped."""
        self._charge()
        return {
            "interrupted": self.interrupted,
            "total_s": self.elapsed(),
            "stages_s": {k: self.spent[k] for k in STAGES if k in self.spent},
            "limits_s": {"total": self.total, **dict(self.limits)},
            "skipped": [
                {"stage": s.stage, "what": s.what, "at_s": s.at_s, "limit": s.limit}
                for s in self.skipped
            ],
        }
