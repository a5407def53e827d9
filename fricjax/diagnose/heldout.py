"""Held-out checks: does a term's gain carry over to data its fit has not seen?

Two :class:`~fricjax.diagnose.select.Check` s of one record (``judge(before, after,
place) -> Verdict``), both in the judge's own metric (output error in units of the record's σ̂_x²):

* :class:`CrossValidation`: blocked K-fold cross-validation of the record. The segments of
  the multiple shooting are dealt to K folds in turn (segment s to fold s mod K), so the
  folds interleave over the whole record; base and base + term are refitted K times, each
  time with one fold's samples held out (their residual rows weigh nothing, while the
  segments still run through them, tied to their neighbours by the continuity defects), and
  the held-out samples' misfit of those fits is summed over the folds. Every part of the
  record is thus predicted by a fit that saw its neighbourhood and not itself, a short
  record is judged on all of its data, and a term acting in one place (a bump, an impact)
  is judged where it acts. A split of the record into a first and a last part instead asks
  a term fitted on one part to extrapolate to a part the motion reaches differently, and
  refused glaring true terms for that reason.
* :class:`SecondRecording`: both models at their whole-record parameters simulated over a
  second recording of the same plant (segment states fitted there only). A second
  recording of the same motion confirms any term that reproduces the plant there, right
  name or not, so with one both checks run and a term must gain in every check.

The gain is ``1 − E_term,held out / E_base,held out``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from fricjax.diagnose.judge import Fitted, converged_rows, fit_rows
from fricjax.diagnose.select import Verdict
from fricjax.output_error import (
    OutputError,
    OutputErrorSettings,
    output_error_residual,
    sample_residual,
)
from fricjax.problem import Problem
from fricjax.refine import refine

__all__ = ["FOLDS", "CrossValidation", "SecondRecording", "folds"]


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


#: Folds of the cross-validation. Five is the usual choice (Hastie, Tibshirani & Friedman,
#: ch. 7.10): each fit sees four fifths of the record, enough to refit every parameter it had
#: on the whole, and the held-out fifth, spread over the record, is a fifth of every kind of
#: motion. A record of fewer segments than folds holds out one segment at a time.
FOLDS = 5


def folds(segment_of: np.ndarray, k: int) -> list[np.ndarray]:
    """K held-out masks [n] over samples in the segments ``segment_of`` [n] (int): segment
    s in fold s mod K (module docstring); each sample is held out by exactly one fold."""
    return [(segment_of % k) == j for j in range(k)]


@dataclass(frozen=True)
class CrossValidation:
    """Blocked K-fold cross-validation of the record (module docstring)."""

    settings: OutputErrorSettings
    folds: int = FOLDS

    def judge(self, before: Fitted, after: Fitted, place: Mapping[str, Any]) -> Verdict:
        sup = before.superset
        f = before.fit
        S = f.n_segments
        K = min(self.folds, S)
        on = f"{K} interleaved folds of the record's {S} segments"
        if K < 2:
            return Verdict("cross-validation", on, False, why="the record is one segment long")
        held = folds(f.segment_of, K)
        samples = [(~h).astype(np.float64) for h in held]
        k = sup.n_directions(before.active)
        costs = []
        for m in (before, after):
            free = m.moving
            fits = converged_rows(
                sup.problem,
                _first_round(m, free, samples, self.settings, k),
                [free] * K,
                self.settings,
                k,
                samples,
            )
            costs.append(
                sum(
                    float(np.sum(sample_residual(sup.problem, fit, self.settings)[h] ** 2))
                    for fit, h in zip(fits, held, strict=True)
                )
            )
        return Verdict("cross-validation", on, True, 1 - costs[1] / costs[0], *costs)


def _first_round(
    m: Fitted,
    free: np.ndarray,
    samples: list[np.ndarray],
    settings: OutputErrorSettings,
    k: int,
) -> list[Any]:
    """The K fold fits' first round, all from ``m``'s optimum, as one batch."""
    spec = m.superset.problem.spec
    rows = [spec.flatten(m.fit.params)] * len(samples)
    states = [(m.fit.states_x, m.fit.states_v)] * len(samples)
    return fit_rows(m.superset.problem, rows, [free] * len(samples), settings, states, k, samples)


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
