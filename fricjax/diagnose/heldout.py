"""Held-out checks: does a term's gain carry over to data its fit has not seen?

One interface, :class:`Check` (``judge(before, after, place) -> Verdict``), two checks, both
in the judge's own metric (output error in units of the record's σ̂_x²):

* :class:`Split`: base and base + term are refitted on a training part of the record and
  simulated over the rest with their parameters fixed (only the segment states are fitted
  there: a simulation, not a refit). The test part is the record's last ``fraction``, or its
  first where only that one reaches the term's place (a bump, an impact: a part that never
  goes there "judges" the base's extrapolation alone); where neither reaches it, the check
  does not judge and says why.
* :class:`SecondRecording`: both models at their whole-record parameters simulated over a
  second recording of the same plant (segment states fitted there only). Nothing of the
  record is set aside, so it judges terms acting anywhere; but a second recording of the same
  motion confirms any term that reproduces the plant there, right name or not, so with one
  both checks run and a term must gain in every check that judges it.

The gain is ``1 − E_term,test / E_base,test``. Whether a record is too short to split is
decided here alone (:func:`too_short`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any, Protocol

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from fricjax.diagnose.judge import Fitted, converged
from fricjax.output_error import (
    OutputError,
    OutputErrorSettings,
    output_error_residual,
)
from fricjax.problem import Problem
from fricjax.refine import refine

__all__ = ["Check", "SecondRecording", "Split", "Verdict", "record_part", "too_short"]


@dataclass(frozen=True)
class Verdict:
    """The outcome of one held-out check of one term.

    Attributes:
        check: which check (``"split"``, ``"second recording"``).
        on: the data it judged on, in words (``"last 30 % of the record"``).
        judged: whether it could judge; ``why`` says why not.
        gain: ``1 − E_term/E_base`` on the held-out data (NaN when not judged).
        cost_base, cost_term: the two held-out costs [σ_x²].
    """

    check: str
    on: str
    judged: bool
    gain: float = math.nan
    cost_base: float = math.nan
    cost_term: float = math.nan
    why: str = ""

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
        }


class Check(Protocol):
    """A held-out check: ``judge(before, after, place)`` with ``place`` where the term acts
    (:meth:`~fricjax.diagnose.catalogue.Candidate.location`)."""

    def judge(self, before: Fitted, after: Fitted, place: Mapping[str, Any]) -> Verdict: ...


class _StatesOnly(eqx.Module):
    """The output-error residual with θ held at ``theta`` (an array leaf, so one compiled
    program serves every parameter value): a function of the segment states alone."""

    residual: OutputError
    theta: Float[Array, " P"]

    def __call__(self, states: Float[Array, " s"]) -> Float[Array, " m"]:
        return self.residual(jnp.concatenate([self.theta, states]))


def fixed_cost(
    problem: Problem, params: Mapping[str, float], settings: OutputErrorSettings
) -> float:
    """Output-error cost [σ_x²] of ``problem``'s model at ``params``, every model parameter
    fixed: only the segment states are fitted (a held-out simulation, not a refit)."""
    setup = output_error_residual(problem, dict(params), settings)
    # θ_aug holds every parameter of the model, the fixed ones included, then the states
    P = len(problem.spec.names)
    fn = _StatesOnly(setup.residual, jnp.asarray(setup.x0[:P]))
    out = refine(fn, setup.x0[P:], setup.lower[P:], setup.upper[P:], settings.refine_settings())
    return float(out.cost_after)


def record_part(problem: Problem, start: int, stop: int) -> Problem:
    """Samples ``start … stop − 1`` of the preprocessed record, remembering where they lie
    in it (:attr:`Problem.window`)."""
    sl = slice(start, stop)
    offset, n_parent = problem.window or (0, problem.n)
    return replace(
        problem,
        t=problem.t[sl],
        x=problem.x[sl],
        v=problem.v[sl],
        a=problem.a[sl],
        u=problem.u[sl],
        window=(offset + start, n_parent),
        rest=None,
    )


def untested_place(location: Mapping[str, Any], test: Problem) -> str:
    """Why ``test`` cannot judge a term acting only at ``location`` (its ``position_m`` or
    ``time_s`` interval lies outside what ``test`` covers), or ``""``."""
    for key, signal, unit in (("position_m", test.x, "m"), ("time_s", test.t, "s")):
        if key not in location:
            continue
        lo, hi = (float(b) for b in location[key])
        s_lo, s_hi = float(np.min(signal)), float(np.max(signal))
        if hi < s_lo or lo > s_hi:
            name = "x" if key == "position_m" else "t"
            return (
                f"the held-out part ({name} {s_lo:.4g} to {s_hi:.4g} {unit}) never reaches "
                f"where this term acts ({name} {lo:.4g} to {hi:.4g} {unit})"
            )
    return ""


def too_short(train: Problem, n_free: int, settings: OutputErrorSettings) -> str:
    """Why ``train`` is too short to fit a model of ``n_free`` parameters by output error,
    or ``""``: its samples must exceed the unknowns (parameters and two states per segment)
    at least twice, so that the fit has as many residual degrees of freedom as unknowns and
    its test-part prediction is not dominated by estimation variance (variance inflation
    ``h/(1 − h)`` ≤ 1 at ``h`` = unknowns/samples ≤ ½)."""
    dt = float(train.t[1] - train.t[0])
    segments = max(1, round((train.n - 1) * dt / settings.segment_s))
    unknowns = n_free + 2 * segments
    if train.n < 2 * unknowns:
        return (
            f"the training part ({train.n} samples) is too short for {unknowns} unknowns "
            f"({n_free} parameters, {segments} segments' states)"
        )
    return ""


@dataclass(frozen=True)
class Split:
    """The record's own split (module docstring): the test part is ``fraction`` of it."""

    fraction: float
    settings: OutputErrorSettings

    def judge(self, before: Fitted, after: Fitted, place: Mapping[str, Any]) -> Verdict:
        n = before.problem.n
        n_test = round(n * self.fraction)
        cuts = {"last": (0, n - n_test, n - n_test, n), "first": (n_test, n, 0, n_test)}
        why: dict[str, str] = {}
        for part, (a, b, c, d) in cuts.items():
            on = f"{part} {self.fraction:.0%} of the record"
            why[part] = untested_place(place, record_part(before.problem, c, d))
            if why[part]:
                continue
            short = too_short(record_part(after.problem, a, b), after.n_free, self.settings)
            if short:
                return Verdict("split", on, False, why=short)
            costs = []
            for m in (before, after):
                train = record_part(m.problem, a, b)
                fit = converged(
                    train,
                    m.fit.params,
                    self.settings,
                    n_directions=m.superset.n_directions(before.active),
                )
                costs.append(fixed_cost(record_part(m.problem, c, d), fit.params, self.settings))
            return Verdict("split", on, True, 1 - costs[1] / costs[0], costs[0], costs[1])
        return Verdict(
            "split", "the record's split", False, why="; ".join(dict.fromkeys(why.values()))
        )


@dataclass(frozen=True)
class SecondRecording:
    """A second recording of the same plant (module docstring)."""

    validation: Problem
    settings: OutputErrorSettings

    def judge(self, before: Fitted, after: Fitted, place: Mapping[str, Any]) -> Verdict:
        costs = [
            fixed_cost(
                replace(self.validation, model=m.problem.model, spec=m.problem.spec),
                m.fit.params,
                self.settings,
            )
            for m in (before, after)
        ]
        return Verdict(
            "second recording", "the second recording", True, 1 - costs[1] / costs[0], *costs
        )
