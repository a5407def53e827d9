"""``diagnose``: fit the base model, locate the mismatch, name and model what is missing,
and prove the gain (before/after fit, held-out check, simulation error).

Output (:func:`write_diagnosis`): ``diagnosis.json`` in the form of docs/formats.md,
``report.md`` and ``report.html`` for a test engineer with a figure per finding
(:mod:`fricjax.diagnose.report`), and ``models.h5`` with the base and final fitted models.
"""

from __future__ import annotations

import itertools
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import equinox as eqx
import h5py
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from fricjax.diagnose.catalogue import (
    candidate,
    drive_harmonic_note,
    near_drive_harmonic,
    ranges,
    simulation_candidates,
)
from fricjax.diagnose.evidence import (
    FLIP_KAPPA,
    Evidence,
    NearRest,
    near_rest_band,
    record_noise,
)
from fricjax.diagnose.locate import (
    NOISE_MODELS,
    LocateReport,
    TooShortToLocate,
    default_whitener,
    locate,
    resolve_noise,
    static_level,
)
from fricjax.diagnose.select import (
    MIN_DOF_LEFT,
    Selection,
    WhitenedResidual,
    bic,
    bic_known,
    forward_select,
    gls_fit,
    whitened_residual,
)
from fricjax.diagnose.simulation_test import (
    LawFit,
    SimulationTest,
    simulation_test,
)
from fricjax.diagnose.stages import LIMITED, Clock, OnStage
from fricjax.identify import IdentifySettings, identify
from fricjax.io.atomic import make_folder, write_hdf5_atomic, write_text_atomic
from fricjax.model.simulate import simulate
from fricjax.model.system import Model
from fricjax.params import ParamSpec
from fricjax.problem import Problem
from fricjax.refine import RefineSettings, refine

# Time limits [s] of a diagnosis (DiagnoseSettings docstring).
TIME_LIMIT = 180.0
STAGE_LIMITS = {
    "base_fit": 90.0,
    "scores": 90.0,
    "refits": 60.0,
    "heldout": 60.0,
    "locate": 60.0,
    "simulation_test": 60.0,
}


@dataclass
class DiagnoseSettings:
    """Knobs of :func:`diagnose` (``[diagnose]`` config table).

    alpha: family-wise significance level (split over the candidates, Bonferroni).
    min_delta_bic: a term must lower BIC by more than this (10 = "very strong" evidence).
    max_terms: most terms added. n_mc: Monte Carlo draws calibrating each max-score.
    heldout: fraction of the record kept out of the fit for the held-out check.
    noise: noise model of the whitening (``auto``: displacement noise, plus white force
        noise fitted to the residual when the drive is a recorded input;
        :func:`~fricjax.diagnose.locate.resolve_noise`).
    simulation_test: where equation error names nothing, test the friction laws by output
        error (:mod:`fricjax.diagnose.simulation_test`), which sees how the plant stops.
    time_limit: seconds for the whole diagnosis (``inf``: none); stage_limits: seconds per
        stage (``[diagnose.stage_limits]``, keys of
        :data:`~fricjax.diagnose.stages.LIMITED`). A limit acts only when hit, between
        units of work (a candidate's score test, a refit, a held-out check, an
        output-error fit, a map): the rest of that stage, or of the whole diagnosis, is
        skipped and recorded (``timing`` and ``not_tested`` in diagnosis.json, section Time
        of the report); a candidate left untested is never named. The base fit, its
        whitening, the maps of its residual and the report always run. Defaults: 180 s in
        all, the bound for any recording up to 30 s; 60-90 s a stage, so that a stage limit
        acts only on a stage gone far beyond the ordinary and leaves time for the stages
        after it. A limit makes findings depend on the machine's speed: a benchmark that
        compares findings sets ``time_limit = inf``.
    """

    alpha: float = 0.01
    min_delta_bic: float = 10.0
    max_terms: int = 3
    n_mc: int = 2000
    heldout: float = 0.3
    seed: int = 0
    n_bins: int = 20
    noise: str = "auto"
    simulation_test: bool = True
    time_limit: float = TIME_LIMIT
    stage_limits: dict[str, float] = field(default_factory=lambda: dict(STAGE_LIMITS))

    def clock(self, on_stage: OnStage | None = None) -> Clock:
        """A :class:`~fricjax.diagnose.stages.Clock` with these time limits."""
        return Clock(limits=dict(self.stage_limits), total=self.time_limit, on_stage=on_stage)

    @classmethod
    def from_dict(
        cls, d: dict[str, Any], source: str = "config", *, flags: bool = False
    ) -> DiagnoseSettings:
        """Settings from a ``[diagnose]`` table, each key's type and range checked: a
        mistake is one :class:`FricjaxError` line naming ``source`` and the key (as its
        command-line flag where ``flags``)."""
        from fricjax.errors import FricjaxError, where

        # key: (type, valid?, what a valid value is)
        rules: dict[str, tuple[type, Any, str]] = {
            "alpha": (float, lambda v: 0 < v < 1, "in (0, 1)"),
            "min_delta_bic": (float, lambda v: 0 <= v < math.inf, ">= 0 and finite"),
            "max_terms": (int, lambda v: v >= 1, ">= 1"),
            "n_mc": (int, lambda v: v >= 1, ">= 1"),
            "heldout": (float, lambda v: 0 < v < 0.9, "in (0, 0.9)"),
            "seed": (int, lambda v: True, "an integer"),
            "n_bins": (int, lambda v: v >= 2, ">= 2"),
            "noise": (str, lambda v: v in NOISE_MODELS, f"one of {', '.join(NOISE_MODELS)}"),
            "simulation_test": (bool, lambda v: True, "true or false"),
            "time_limit": (float, lambda v: v > 0, "> 0 seconds (inf: none)"),
            "stage_limits": (
                dict,
                lambda v: all(
                    k in LIMITED
                    and isinstance(s, int | float)
                    and not isinstance(s, bool)
                    and s > 0
                    for k, s in v.items()
                ),
                f"a table of seconds > 0 for stages among {', '.join(LIMITED)}",
            ),
        }
        values: dict[str, Any] = {}
        for key, value in d.items():
            label = f"--{key.replace('_', '-')}" if flags else f"[diagnose].{key}"
            if key not in rules:
                raise FricjaxError(
                    f"{where(source, label)}: unknown key (known: {', '.join(sorted(rules))})"
                )
            kind, valid, what = rules[key]
            # bool is an int, but `max_terms = true` is a mistake, not 1
            typed = isinstance(value, kind) and (kind is bool or not isinstance(value, bool))
            if kind is float and isinstance(value, int) and not isinstance(value, bool):
                value, typed = float(value), True
            if not typed or not valid(value):
                raise FricjaxError(f"{where(source, label)}: must be {what}, got {value!r}")
            values[key] = value
        if "stage_limits" in values:  # a table sets the stages it names, the rest keep theirs
            values["stage_limits"] = {
                **STAGE_LIMITS,
                **{k: float(v) for k, v in values["stage_limits"].items()},
            }
        return cls(**values)


@dataclass
class Diagnosis:
    """Everything diagnose found, as plain data plus the fitted models."""

    recording: str
    base_model: str
    findings: list[dict[str, Any]]
    fit: dict[str, dict[str, float]]
    heldout: dict[str, float]
    selection: Selection
    locate_before: LocateReport
    locate_after: LocateReport | None  # None: too few degrees of freedom left (extra)
    problem: Problem
    base_spec: ParamSpec
    evidence: Evidence  # the record's own noise: the scale of every test
    near_rest: NearRest  # the record's near-rest band
    clock: Clock = field(default_factory=Clock)  # stages' wall times, limits, what was skipped
    extra: dict[str, Any] = field(default_factory=dict)

    def as_json(self) -> dict[str, Any]:
        return _jsonable(
            {
                "recording": self.recording,
                "base_model": self.base_model,
                "findings": self.findings,
                "fit": self.fit,
                "heldout": self.heldout,
                # what the record allows: its own noise, with its error, and the near-rest band
                "data": {
                    "sigma_x_m": self.evidence.sigma_x,
                    "sigma_x_se_m": self.evidence.noise.se,
                    "noise_model": self.evidence.noise.model,
                    "sigma_x_dof": self.evidence.nu,
                    "test_scale": "residual spectrum"
                    if self.selection.whitener.spectral
                    else "record",
                    "near_rest_speed_mps": self.near_rest.speed,
                    "near_rest_fraction": self.near_rest.share,
                },
                **{
                    k: self.extra[k]
                    for k in ("simulation_test", "locate_after_skipped")
                    if k in self.extra
                },
                # candidates a time limit left untested (never named), then every stage's
                # wall time, the limits and all that was skipped
                "not_tested": self.clock.not_tested(),
                "timing": self.clock.summary(),
            }
        )


# A parameter within this fraction of its search range from a bound is "on the bound".
BOUND_TOL = 1e-3


def on_bound(spec: ParamSpec | None, name: str, value: float) -> str:
    """``"lower"``/``"upper"`` where ``value`` sits on that bound of ``name``'s search
    range (within :data:`BOUND_TOL` of it), else ``""``."""
    if spec is None or name not in spec.names or not spec[name].free:
        return ""
    p = spec[name]
    tol = BOUND_TOL * (p.upper - p.lower)
    if value <= p.lower + tol:
        return "lower"
    if value >= p.upper - tol:
        return "upper"
    return ""


def at_bounds(spec: ParamSpec, params: dict[str, float]) -> dict[str, str]:
    """``{name: "lower"|"upper"}`` for each of a finding's ``params`` that sits on a bound
    of its search range (:func:`on_bound`): a limit the fit ran into, not a measurement."""
    return {n: side for n, v in params.items() if (side := on_bound(spec, n, float(v)))}


def _jsonable(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def with_model(problem: Problem, model: Model, spec: ParamSpec) -> Problem:
    return replace(problem, model=model, spec=spec)


def simulation_error(problem: Problem, model: Model, spec: ParamSpec, theta: np.ndarray) -> float:
    """RMS of x_sim − x [m], simulated from the recording's first preprocessed state.

    NaN for models with stateful terms (LuGre bristles), which the pointwise simulator cannot
    integrate."""
    if any(getattr(term, "stateful", False) for term in model.terms):
        return math.nan
    p = spec.unflatten(jnp.asarray(theta))
    try:
        traj = simulate(
            model,
            p,
            jnp.asarray(problem.t),
            float(problem.x[0]),
            float(problem.v[0]),
            jnp.asarray(problem.u),
        )
    except Exception:  # a model the simulator rejects: report no figure rather than fail
        return math.nan
    err = np.asarray(traj.x) - problem.x
    return float(np.sqrt(np.mean(err**2)))


def record_part(problem: Problem, start: int, stop: int) -> Problem:
    """Samples ``start … stop − 1`` of the preprocessed record, remembering where they lie in
    it (:attr:`Problem.window`): their noise continues across a cut end, and the whitener of
    the part treats a cut end as such, not as a record end."""
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
        rest=None if problem.rest is None else problem.rest[sl],
    )


def heldout_parts(problem: Problem, fraction: float) -> tuple[Problem, Problem]:
    """(training, test) parts of the record's contiguous split: the first ``1 − fraction``
    of the samples and the rest."""
    k = round(problem.n * (1 - fraction))
    return record_part(problem, 0, k), record_part(problem, k, problem.n)


def untested_place(location: dict[str, Any], test: Problem) -> str:
    """Why the held-out part cannot judge a finding that acts only at ``location`` (its
    ``position_m`` or ``time_s`` interval lies outside what ``test`` covers), or ``""``."""
    for key, signal, unit in (("position_m", test.x, "m"), ("time_s", test.t, "s")):
        if key not in location:
            continue
        lo, hi = (float(b) for b in location[key])
        s_lo, s_hi = float(np.min(signal)), float(np.max(signal))
        if hi < s_lo or lo > s_hi:
            name = "x" if key == "position_m" else "t"
            return (
                f"the held-out part ({name} {s_lo:.4g} to {s_hi:.4g} {unit}) never reaches "
                f"where this finding acts ({name} {lo:.4g} to {hi:.4g} {unit})"
            )
    return ""


def frozen(
    before: tuple[Model, ParamSpec, np.ndarray],
    after: tuple[Model, ParamSpec, np.ndarray],
    own: Sequence[str],
) -> tuple[Model, ParamSpec, np.ndarray]:
    """``after`` with every free parameter but its ``own`` fixed at ``before``'s value
    (clipped into ``after``'s bounds), started from ``after``'s own values."""
    _, b_spec, b_theta = before
    a_model, a_spec, a_theta = after
    held = b_spec.as_dict(b_theta)
    spec_f = a_spec.with_fixed(
        {
            n: float(np.clip(held[n], a_spec[n].lower, a_spec[n].upper))
            for n in a_spec.free_names
            if n in held and n not in own
        }
    )
    return a_model, spec_f, spec_f.flatten(a_spec.as_dict(a_theta))


class HeldOut:
    """One held-out check: a training and a test part (the record's first ``1 − fraction``
    and the rest, or the whole record and a second recording), and the test score of each
    model fitted on the training part (cached per model, so the models of forward selection
    are fitted once each).

    Every model is refitted (GLS in the whitened space of the base fit on the training
    part) and scored on the test part by the same statistic the fit minimises: the
    whitened RSS ``‖W_test·r(θ_train)‖²`` [m²], with ONE whitener ``W_test`` built from the
    whole record's base fit ``base`` (so every model is judged in the same metric).
    The unwhitened EMS [N²] is reported beside it but does not decide under displacement
    noise: it weighs each frequency by the noise gain of the double differentiation, so on a
    1 s record it is dominated by the high band where the noise is amplified most and where
    no catalogue term lives. Under the ``spectral`` noise model (a recorded drive
    input: the residual's noise is force noise) the EMS decides instead: there the whitener
    is the base residual's own smoothed spectrum, which counts the base's broadband misfit
    on the test part as noise and so is biased towards the base.
    """

    def __init__(
        self,
        problem: Problem,
        base: tuple[Model, ParamSpec, np.ndarray],
        fraction: float,
        validation: Problem | None = None,
        noise: str = "auto",
    ) -> None:
        self.second = validation is not None
        if validation is not None:
            self.train, self.test = problem, validation
            self.on = "second recording"
        else:
            self.train, self.test = heldout_parts(problem, fraction)
            self.on = f"last {fraction:.0%} of the record"
        self.wh = default_whitener(self.train, base[2], noise)
        base_test = with_model(self.test, base[0], base[1])
        # The test metric's noise model (damping, reversal mask) comes from the same base
        # fit as the training one, the whole record's: the base refitted on the training
        # part alone can land far from it along a weakly determined direction, and a
        # whitener built there would judge every model in another metric.
        self.wh_test = default_whitener(base_test, base[2], noise)
        self.by_ems = resolve_noise(base_test, noise) == "spectral"
        self.metric = "EMS" if self.by_ems else "whitened RSS"
        self._scores: dict[int, tuple[Model, float, float]] = {}

    def score(self, fitted: tuple[Model, ParamSpec, np.ndarray]) -> tuple[float, float]:
        """(whitened RSS [m²], EMS [N²]) on the test part of ``fitted`` refitted on the
        training part from its own parameters."""
        model, spec, theta = fitted
        hit = self._scores.get(id(model))
        if hit is not None and hit[0] is model:
            return hit[1], hit[2]
        fit_theta, _ = gls_fit(with_model(self.train, model, spec), model, spec, theta, self.wh)
        fn = whitened_residual(self.test, model, spec, self.wh_test)
        r_w = np.asarray(fn(jnp.asarray(fit_theta)))
        out = (float(r_w @ r_w), with_model(self.test, model, spec).ems(fit_theta))
        self._scores[id(model)] = (model, *out)
        return out

    def determined(self, spec: ParamSpec) -> bool:
        """Whether the training part's whitened dimensions determine a model of ``spec``
        (with :data:`~fricjax.diagnose.select.MIN_DOF_LEFT` to spare). Always, against a
        second recording: its training part is the whole first record, where every model
        is already at the fit the selection made, so its score extrapolates nothing but
        that fit, the very claim a second ram tests."""
        return self.second or self.wh.dof >= spec.n_free + MIN_DOF_LEFT

    def _test_score(self, model: Model, spec: ParamSpec, theta: np.ndarray) -> tuple[float, float]:
        fn = whitened_residual(self.test, model, spec, self.wh_test)
        r_w = np.asarray(fn(jnp.asarray(theta)))
        return float(r_w @ r_w), with_model(self.test, model, spec).ems(theta)

    def frozen_scores(
        self,
        before: tuple[Model, ParamSpec, np.ndarray],
        after: tuple[Model, ParamSpec, np.ndarray],
        own: Sequence[str],
    ) -> tuple[tuple[float, float], tuple[float, float]]:
        """(whitened RSS [m²], EMS [N²]) on the test part of ``before`` at its whole-record
        fit, as it is, and of ``after`` whose ``own`` parameters (the finding's) alone are
        fitted on the training part, every other one frozen at ``before``'s values."""
        b_model, b_spec, b_theta = before
        a_model, spec_f, start = frozen(before, after, own)
        fit_theta, _ = gls_fit(
            with_model(self.train, a_model, spec_f), a_model, spec_f, start, self.wh
        )
        return self._test_score(b_model, b_spec, b_theta), self._test_score(
            a_model, spec_f, fit_theta
        )

    def frozen_gain(
        self,
        before: tuple[Model, ParamSpec, np.ndarray],
        after: tuple[Model, ParamSpec, np.ndarray],
        own: Sequence[str],
    ) -> float:
        """Relative improvement on the test part of ``after`` over ``before`` by
        :meth:`frozen_scores`: only the finding's ``own`` parameters learn from the
        training part.

        The check of a record whose training part cannot determine the model
        (:meth:`determined` false). Refitted there, every model only extrapolates from its
        start. Here the base
        has seen the test part and the term has not, so the check leans towards the base:
        a gain means the term predicts what the base, fitted to those samples, left."""
        a, b = self.frozen_scores(before, after, own)
        k = 1 if self.by_ems else 0
        return 1 - b[k] / a[k]

    def gain(
        self,
        before: tuple[Model, ParamSpec, np.ndarray],
        after: tuple[Model, ParamSpec, np.ndarray],
        place: dict[str, Any],
        own: Sequence[str] = (),
    ) -> tuple[float, str]:
        """(relative improvement of ``after`` over ``before`` on the test part, why the
        test part cannot judge a finding at ``place`` or ``""``); by :meth:`frozen_gain`
        with the finding's ``own`` parameters where the training part does not determine
        ``after``."""
        why = untested_place(place, self.test)
        if own and not self.determined(after[1]):
            return self.frozen_gain(before, after, own), why
        a, b = self.score(before), self.score(after)
        k = 1 if self.by_ems else 0
        return 1 - b[k] / a[k], why

    def summary(
        self,
        chain: Sequence[tuple[Model, ParamSpec, np.ndarray]],
        places: Sequence[dict] = (),
        owns: Sequence[Sequence[str]] = (),
    ) -> dict[str, Any]:
        """The check of ``chain`` (base, then each model of forward selection): first
        against last, and each step against the one before it. ``owns``: each step's own
        parameters; where given and the training part does not determine the last model,
        the steps are judged by :meth:`frozen_scores` (each against the model before it as
        it is; first against last with every step's own parameters fitted, ``mode``
        ``frozen``)."""
        k = 1 if self.by_ems else 0
        frozen_mode = bool(owns) and not self.determined(chain[-1][1])
        if frozen_mode:
            pairs = [
                self.frozen_scores(a, b, own)
                for (a, b), own in zip(itertools.pairwise(chain), owns, strict=True)
            ]
            first, last = self.frozen_scores(chain[0], chain[-1], [n for own in owns for n in own])
            scores = [first, *(b for _, b in pairs[:-1]), last]
            step_gains = [1 - b[k] / a[k] for a, b in pairs]
        else:
            scores = [self.score(m) for m in chain]
            step_gains = [1 - b[k] / a[k] for a, b in itertools.pairwise(scores)]
        rss, ems = [s[0] for s in scores], [s[1] for s in scores]
        decide = ems if self.by_ems else rss
        out: dict[str, Any] = {
            "mode": "frozen" if frozen_mode else "refitted",
            "metric": self.metric,
            "rss_w_before": rss[0],
            "rss_w_after": rss[-1],
            "rss_w_improvement": 1 - rss[-1] / rss[0],
            "ems_before": ems[0],
            "ems_after": ems[-1],
            "ems_improvement": 1 - ems[-1] / ems[0],
            "improvement": 1 - decide[-1] / decide[0],
            "dof": self.wh_test.dof,
            "on": self.on,
            "step_rss_w": rss[1:],
            "step_ems": ems[1:],
            "step_improvements": step_gains,
        }
        if places:
            out["step_untestable"] = [untested_place(loc, self.test) for loc in places]
        return out


def heldout_check(
    problem: Problem,
    base: tuple[Model, ParamSpec, np.ndarray],
    final: tuple[Model, ParamSpec, np.ndarray],
    fraction: float,
    validation: Problem | None = None,
    noise: str = "auto",
    steps: Sequence[tuple[Model, ParamSpec, np.ndarray]] = (),
    places: Sequence[dict[str, Any]] = (),
) -> dict[str, Any]:
    """Fit on the first (1 − fraction) of the record, score on the rest (or on a second
    recording): the gain must survive on data the fit has not seen (:class:`HeldOut`).

    ``steps``: the intermediate models of forward selection (base + first term, base + first
    two, ...); each finding gets its own held-out improvement (``step_improvements``), not
    just the last model's. ``places``: each step's finding location; ``step_untestable``
    says, per step, why the test part cannot judge it (:func:`untested_place`) or ``""``.
    """
    judge = HeldOut(problem, base, fraction, validation, noise)
    return judge.summary([base, *steps] if steps else [base, final], places)


class FoldResidual(eqx.Module):
    """``theta -> P·W·r(theta)`` [m]: one fold's coordinates of the whitened residual, ``P``
    [m, M] orthonormal rows (:class:`CrossValidation`)."""

    inner: WhitenedResidual
    rows: Float[Array, "m M"]

    def __call__(self, theta: Float[Array, " d"]) -> Float[Array, " m"]:
        return self.rows @ self.inner(theta)


# K of the cross-validation; 5 leaves a fold's fit 80 % of the coordinates.
CV_FOLDS = 5
_CV_FIT = RefineSettings(max_steps=100, rtol=1e-8, atol=1e-8)


def cv_folds(coords: int, fit_params: int, folds: int = CV_FOLDS) -> int:
    """Folds of :class:`CrossValidation` over ``coords`` whitened coordinates for a model of
    ``fit_params`` free parameters: ``folds``, or, where a fold's training coordinates would
    keep fewer than three times the fold's size beyond the parameters (and
    :data:`~fricjax.diagnose.select.MIN_DOF_LEFT`), the largest folds that do, as many as
    the coordinates hold (down to one coordinate each); unchanged where even one
    coordinate held out leaves too few.

    Why. A fold fit that is only just determined predicts its held-out coordinates with a
    variance that grows as h/(1 − h), h = parameters/training coordinates, so it leans
    against the larger model; with too few training coordinates only the term's own
    parameters could be fitted, which leans towards the base."""
    if fit_params <= 0:
        return folds
    spare = coords - fit_params - MIN_DOF_LEFT
    size = min(coords // folds, spare // 4)
    if size < 1:
        if spare < 1:
            return folds
        size = 1
    return max(folds, coords // size)


class CrossValidation:
    """K-fold cross-validation over the coordinates of the whitened residual: the judge of
    a finding that no split of the record in time reaches.

    Why it is a held-out test. Under the noise model the whitened residual of the
    displacement noise is ``W·r ~ N(0, σ_x²·(I − N·Nᵀ))`` (:class:`~fricjax.diagnose.whiten.
    Whitener`: N spans the excluded samples), so in an orthonormal basis Q [M, M − e] of
    the complement of N its coordinates are independent with equal variance. Each model is
    fitted (GLS, from its own parameters) on all coordinates but one fold and scored by
    its whitened RSS on that fold, whose noise the fit has not seen; the K folds (a seeded
    random partition, equal sizes so one compiled fit serves them all) hold every
    coordinate out once. Score = the RSS summed over the folds [m²]; gain = its relative
    fall from the model before the finding to the model with it.

    Why only as a fallback. A split in time asks the term to carry over to another part of
    the motion; this asks it to predict coordinates of the same motion, which a term that
    only imitates the missing physics on this motion also does (as a second recording of
    the same motion does, :class:`Confirm`). But a local finding acting once (a bump passed
    once, an impact) leaves the training part of every time split without the effect; its
    Fourier coordinates spread over the band, so a fit that sees 80 % of them must predict
    the rest, and a term fitted to noise does not.
    """

    def __init__(
        self,
        problem: Problem,
        base: tuple[Model, ParamSpec, np.ndarray],
        noise: str = "auto",
        folds: int = CV_FOLDS,
        seed: int = 0,
        fit_params: int = 0,
    ) -> None:
        self.problem = problem
        self.wh = default_whitener(problem, base[2], noise)
        n_ex = int(self.wh.N.shape[1])
        if n_ex:
            q = np.linalg.qr(self.wh.N, mode="complete")[0][:, n_ex:]
        else:
            q = np.eye(self.wh.M)
        self.basis = q
        folds = cv_folds(q.shape[1], fit_params, folds)
        self.k = folds
        perm = np.random.default_rng(seed).permutation(q.shape[1])
        m = q.shape[1] // folds
        self.folds = [np.sort(perm[j * m : (j + 1) * m]) for j in range(folds)]
        self._scores: dict[int, tuple[Model, float]] = {}

    def score(self, fitted: tuple[Model, ParamSpec, np.ndarray], fit: bool = True) -> float:
        """Whitened RSS [m²] of ``fitted`` on the held-out folds, each fitted without it
        (``fit``; else every fold at ``fitted``'s own parameters)."""
        model, spec, theta = fitted
        hit = self._scores.get(id(model))
        if fit and hit is not None and hit[0] is model:
            return hit[1]
        inner = whitened_residual(with_model(self.problem, model, spec), model, spec, self.wh)
        all_idx = np.arange(self.basis.shape[1])
        total = 0.0
        # One compiled LM run once per fold: vmapped, every fold would run until the
        # slowest stops.
        for test in self.folds:
            x = np.clip(theta, spec.lower, spec.upper)
            if fit:
                train = np.setdiff1d(all_idx, test)
                x = refine(
                    FoldResidual(inner, jnp.asarray(self.basis[:, train].T)),
                    x,
                    spec.lower,
                    spec.upper,
                    _CV_FIT,
                    fast_compile=True,
                ).x
            held = np.asarray(FoldResidual(inner, jnp.asarray(self.basis[:, test].T))(x))
            total += float(held @ held)
        if fit:
            self._scores[id(model)] = (model, total)
        return total

    def determined(self, spec: ParamSpec) -> bool:
        """Whether a fold's training coordinates determine a model of ``spec``."""
        m = self.basis.shape[1] - len(self.folds[0])
        return m >= spec.n_free + MIN_DOF_LEFT

    def gain(
        self,
        before: tuple[Model, ParamSpec, np.ndarray],
        after: tuple[Model, ParamSpec, np.ndarray],
        own: Sequence[str] = (),
    ) -> float:
        """Relative fall of the held-out RSS from ``before`` to ``after``. Where the folds'
        training coordinates do not determine ``after`` and its ``own`` parameters (the
        finding's) are given, as :meth:`HeldOut.frozen_gain`: only those are fitted on
        each fold, every other one frozen at ``before``'s fit, which is scored as it is."""
        if not own or self.determined(after[1]):
            return 1 - self.score(after) / self.score(before)
        return 1 - self.score(frozen(before, after, own)) / self.score(before, fit=False)


# (gain, why untestable) keys of a finding's held-out checks: the primary one (the second
# recording when given, else the record's last part), then the record's last part when a
# second recording was given too.
HELDOUT_KEYS = (
    ("heldout_improvement", "heldout_untestable"),
    ("heldout_split_improvement", "heldout_split_untestable"),
)
# the gain of :class:`CrossValidation`, present where no check of HELDOUT_KEYS reaches
CV_KEY = "heldout_cv_improvement"
# why the record's own split does not judge a finding that a second recording judges,
# where the split's training part cannot determine the model (Confirm)
SPLIT_DEFERS = (
    "its training part cannot determine the model with the finding (only the finding's own "
    "parameters could be fitted there); the second recording judges it"
)
# why the record's own split does not judge a finding where its training part cannot
# determine the model and the cross-validation's folds can (short records, no second
# recording; Confirm)
SPLIT_FROZEN = (
    "its first part cannot determine the model with the finding (only the finding's own "
    "parameters could be fitted there, the base frozen where it absorbed part of the effect)"
)
# the number of folds of the cross-validation that judged a finding (:func:`cv_folds`)
CV_FOLDS_KEY = "heldout_cv_folds"
# set where a check that judged the finding could fit only its own parameters (short
# records: HeldOut.frozen_gain); such a check leans towards the model without it
FROZEN_KEY = "heldout_frozen"


def heldout_judged(finding: dict[str, Any]) -> dict[str, float]:
    """The finding's held-out gains from the checks whose test part reaches its place; the
    cross-validation's where none does."""
    judged = {
        gain: finding[gain]
        for gain, why in HELDOUT_KEYS
        if gain in finding and finding[gain] is not None and not finding.get(why)
    }
    if not judged and finding.get(CV_KEY) is not None:
        judged = {CV_KEY: finding[CV_KEY]}
    return judged


#: A finding's relative gains on the record itself: its EMS [N²] and its simulation error
#: [m] (:func:`record_gains`).
RECORD_KEYS = ("record_ems_gain", "record_simulation_gain")


def record_gains(
    problem: Problem,
    before: tuple[Model, ParamSpec, np.ndarray],
    after: tuple[Model, ParamSpec, np.ndarray],
) -> tuple[float, float]:
    """(``1 − EMS_after/EMS_before``, ``1 − sim_after/sim_before``) on the whole record: the
    relative fall of the mean squared force residual and of the simulation error
    (:func:`simulation_error`, NaN where a model cannot be simulated; then that gain is
    NaN and does not judge)."""
    ems = [with_model(problem, m, s).ems(th) for m, s, th in (before, after)]
    sim = [simulation_error(problem, m, s, th) for m, s, th in (before, after)]
    return 1 - ems[1] / ems[0], 1 - sim[1] / sim[0]


class Confirm:
    """``confirm`` of :func:`~fricjax.diagnose.select.forward_select`: a candidate must gain
    in every held-out check whose test part reaches its place (the second recording when
    given, and the record's own last part). One that none of them can judge (a local
    finding where the test parts never go) is judged by :class:`CrossValidation` instead.
    Where a check's training data cannot determine the model with the candidate (short
    records), only the candidate's own parameters are fitted there, the rest frozen at the
    current fit (:meth:`HeldOut.frozen_gain`, and likewise for the cross-validation); such
    a split is reported but does not judge where a second recording is given
    (:data:`SPLIT_DEFERS`) or, without one, where the cross-validation's folds
    (:func:`cv_folds`) can refit every parameter (:data:`SPLIT_FROZEN`): that check judges
    instead. The checks (:attr:`judges`, in the order of :data:`HELDOUT_KEYS`) are built at the
    first call, whose ``current`` model is the fitted base; the cross-validation when first
    needed, from the same base."""

    def __init__(
        self, problem: Problem, fraction: float, validation: Problem | None, noise: str
    ) -> None:
        self.problem, self.fraction, self.noise = problem, fraction, noise
        self.seconds = [validation, None] if validation is not None else [None]
        self.judges: list[HeldOut] = []
        self.base: tuple[Model, ParamSpec, np.ndarray] | None = None
        self.cvs: dict[int, CrossValidation] = {}

    def __call__(
        self, current: tuple[Model, ParamSpec, np.ndarray], refit: Any
    ) -> tuple[bool, dict[str, Any]]:
        if not self.judges:
            self.base = current
            self.judges = [
                HeldOut(self.problem, current, self.fraction, second, self.noise)
                for second in self.seconds
            ]
        place = candidate(refit.effect).location(refit.params, self.problem)
        gains = record_gains(self.problem, current, (refit.model, refit.spec, refit.theta))
        report: dict[str, Any] = dict(zip(RECORD_KEYS, gains, strict=True))
        # the judge's rule (b): a finding must improve the fit the user sees
        record_ok = all(g > 0 for g in gains if math.isfinite(g))
        for (gain_key, why_key), judge in zip(HELDOUT_KEYS, self.judges, strict=False):
            # A local finding whose place the test part never reaches cannot be judged
            # there: its "gain" is only the base parameters' extrapolation.
            gain, why = judge.gain(
                current, (refit.model, refit.spec, refit.theta), place, own=_own(current, refit)
            )
            report[gain_key] = gain
            if why:
                report[why_key] = why
        split = self.judges[-1]
        if (
            len(self.judges) > 1
            and HELDOUT_KEYS[0][1] not in report
            and not split.determined(refit.spec)
        ):
            # The record's own split could fit only the finding's parameters, the base
            # frozen where it absorbed part of the effect: a check that leans towards the
            # base. The second recording, fitted as the selection fitted, judges alone.
            report.setdefault(HELDOUT_KEYS[1][1], SPLIT_DEFERS)
        elif (
            len(self.judges) == 1
            and HELDOUT_KEYS[0][1] not in report
            and not split.determined(refit.spec)
            and self._cv(refit.spec).determined(refit.spec)
        ):
            # The same frozen split, without a second recording: the cross-validation,
            # whose folds can refit every parameter, judges instead.
            report[HELDOUT_KEYS[0][1]] = SPLIT_FROZEN
        # which checks could fit only the finding's own parameters (the report says so)
        frozen_by = [
            k
            for (k, _), j in zip(HELDOUT_KEYS, self.judges, strict=False)
            if not j.determined(refit.spec)
        ]
        judged = heldout_judged(report)
        if not judged:
            # a local finding where no test part goes (a bump, an impact)
            cv = self._cv(refit.spec)
            report[CV_KEY] = cv.gain(
                current, (refit.model, refit.spec, refit.theta), own=_own(current, refit)
            )
            report[CV_FOLDS_KEY] = cv.k
            if not cv.determined(refit.spec):
                frozen_by.append(CV_KEY)
            judged = heldout_judged(report)
        if any(k in judged for k in frozen_by):
            report[FROZEN_KEY] = True
        held_ok = all(g > 0 for g in judged.values())
        report["heldout_confirmed"] = bool(judged) and held_ok
        return record_ok and held_ok, report

    def _cv(self, spec: ParamSpec) -> CrossValidation:
        """The cross-validation with as many folds as a model of ``spec`` needs
        (:func:`cv_folds`), built from the base once per fold count."""
        assert self.base is not None
        if CV_FOLDS not in self.cvs:
            self.cvs[CV_FOLDS] = CrossValidation(self.problem, self.base, self.noise)
        k = cv_folds(self.cvs[CV_FOLDS].basis.shape[1], spec.n_free)
        if k not in self.cvs:
            self.cvs[k] = CrossValidation(self.problem, self.base, self.noise, folds=k)
        return self.cvs[k]


def _own(current: tuple[Model, ParamSpec, np.ndarray], refit: Any) -> list[str]:
    """The free parameters of ``refit`` that are the finding's: new ones, and the mass
    where the finding frees it (mass error)."""
    base_free = set(current[1].free_names)
    return [n for n in refit.spec.free_names if n not in base_free or n in refit.params]


def _rejected(problem: Problem, refit: Any, p_value: float, report: dict) -> dict[str, Any]:
    """``unexplained`` at the place of a candidate that passed the tests on the record but
    not the judge: it worsened the record's own EMS or simulation, or the held-out check."""
    location = candidate(refit.effect).location(refit.params, problem)
    judged = heldout_judged(report)
    if judged and not all(g > 0 for g in judged.values()):
        why = (
            f"that term made the fit on held-out data worse ({100 * min(judged.values()):+.1f} "
            "%), so it is not claimed: no catalogue term explains this structure in a way "
            "that carries over to data the fit has not seen."
        )
    else:
        why = (
            "with that term the record's own "
            f"{'EMS' if report.get(RECORD_KEYS[0], 1.0) <= 0 else 'simulation error'} got "
            "worse, so it is not claimed: a term that explains the test statistic at the "
            "cost of the fit a user sees stands in for something else."
        )
    clash = _drive_clash(problem, refit)
    where_ = "; ".join(
        f"{k} [{float(v[0]):.4g}, {float(v[1]):.4g}]"
        if isinstance(v, list | tuple) and len(v) == 2
        else f"{k} {v}"
        for k, v in location.items()
    )
    return {
        "effect": "unexplained",
        "explanation": (
            f"The residual is significantly structured ({where_}). Fitted as "
            f"{refit.effect} it lowers BIC by {refit.delta_bic:.1f} on the whole record, but "
            + why
            + (drive_harmonic_note(clash) if clash else "")
        ),
        "location": location,
        "params": {},
        "delta_bic": refit.delta_bic,
        "p_value": p_value,
        **({"near_drive_harmonic": clash} if clash else {}),
        "rejected_candidate": {
            "effect": refit.effect,
            "params": refit.params,
            **{
                k: v
                for k, v in report.items()
                if (k.startswith("heldout_") and k != "heldout_confirmed") or k in RECORD_KEYS
            },
        },
    }


def _drive_clash(problem: Problem, refit: Any) -> dict[str, float] | None:
    """:func:`~fricjax.diagnose.catalogue.near_drive_harmonic` of an ``extra_harmonic``
    refit, at the ω it was refitted with; None for any other term."""
    if refit.effect != "extra_harmonic":
        return None
    r = ranges(problem)
    return near_drive_harmonic(
        float(refit.params["harm_f"]), refit.spec.as_dict(refit.theta), r.duration + r.dt
    )


def _figures(
    problem: Problem,
    model: Model,
    spec: ParamSpec,
    theta: np.ndarray,
    wh: Any,
    sigma2: float | None = None,
) -> dict[str, float]:
    """EMS [N²], BIC and whitened RSS [m²] of a fitted model; the BIC of a known variance
    ``sigma2`` [m²] where the selection used one (short records, :func:`bic_known`)."""
    fn = whitened_residual(problem, model, spec, wh)
    r_w = np.asarray(fn(jnp.asarray(theta)))
    rss = float(r_w @ r_w)
    pb = with_model(problem, model, spec)
    b = (
        bic(rss, wh.dof, spec.n_free)
        if sigma2 is None
        else bic_known(rss, wh.dof, spec.n_free, sigma2)
    )
    return {"ems": pb.ems(theta), "bic": b, "rss_whitened": rss}


def with_rest(
    problem: Problem, theta: np.ndarray, sigma_x: float, kappa: float = FLIP_KAPPA
) -> Problem:
    """``problem`` with its samples near rest marked (:attr:`Problem.rest`): ``|v| < κ·σ_v``
    with the record's own σ̂_x ``sigma_x`` [m] (:func:`~fricjax.diagnose.evidence.
    near_rest_band`), the samples the whitener leaves out of every equation-error test;
    none where the model at ``theta`` has no static friction (nothing sticks).

    Why. A plant that sticks is at rest, with zero net force, while the drive stays within
    the static limit; its filtered velocity there is noise around zero. The seed's residual
    still evaluates the sliding law ``F_f(v)`` there (``sgn`` of noise); on the marked
    samples the residual uses the stick/slip rule instead
    (:meth:`~fricjax.model.system.Model.rest_force`). What happens at those samples, how
    the plant stops and breaks away, is tested by simulation (output error,
    :mod:`fricjax.diagnose.simulation_test`), which needs no velocity.
    """
    if static_level(problem, theta) == 0.0:
        return replace(problem, rest=None)
    rest = near_rest_band(problem, sigma_x, kappa).mask
    return replace(problem, rest=rest if rest.any() else None)


def with_rest_both(
    problem: Problem, validation: Problem | None, theta: np.ndarray, sigma_x: float
) -> tuple[Problem, Problem | None]:
    """The record and its second recording (if any) with their samples near rest marked
    (:func:`with_rest`): the record by its own σ̂_x, the second by the larger of the two
    recordings' σ̂_x and a band ``1 + √2`` times as wide.

    Why. A model fitted on the record holds its sliding law only where the record slid, so
    the second recording must be held at rest wherever the record was. Of the same motion,
    the two velocities differ by their noise, ``v₂ − v₁ ~ N(0, 2σ_v²)``, which exceeds
    ``κ·√2·σ_v`` with the same per-sample probability 2·(1 − Φ(κ)) as a flip outside the
    band; so a sample the record holds (``|v₁| < κσ_v``) lies in the second's band
    ``|v₂| < κ(1 + √2)σ_v`` but with that probability."""
    if validation is None:
        return with_rest(problem, theta, sigma_x), None
    wide = max(sigma_x, record_noise(validation).sigma_x)
    second = with_rest(validation, theta, wide, FLIP_KAPPA * (1.0 + math.sqrt(2.0)))
    return with_rest(problem, theta, sigma_x), second


def _undecimated(problem: Problem | None) -> Problem | None:
    """The problem without residual decimation (``[preprocess].decimate``): the whitener
    selects the frequency band itself and needs the residual at every sample; decimation
    (the IDIM recipe's noise reduction) would only hide samples from the maps."""
    if problem is None or problem.preprocess is None or problem.preprocess.decimate == 1:
        return problem
    return replace(problem, preprocess=replace(problem.preprocess, decimate=1))


def diagnose(
    problem: Problem,
    *,
    identify_settings: IdentifySettings | None = None,
    settings: DiagnoseSettings | None = None,
    validation: Problem | None = None,
    recording: str = "",
    on_stage: OnStage | None = None,
) -> Diagnosis:
    """The whole diagnosis of ``problem``'s base model (see module docstring).

    ``on_stage``: called with a :class:`~fricjax.diagnose.stages.StageEvent` as each stage
    starts and as it moves on (progress display); the stages' wall times, the time limits
    of ``settings`` and what a limit left out are in :attr:`Diagnosis.clock`."""
    settings = settings or DiagnoseSettings()
    clock = settings.clock(on_stage)
    problem, validation = _undecimated(problem), _undecimated(validation)
    identify_settings = identify_settings or IdentifySettings()
    with clock.stage("base_fit", "base fit: search and refine"):
        run = identify(problem, identify_settings)
        # the scale of every test, from the recording itself (fricjax.diagnose.evidence)
        evidence = record_noise(problem)
        problem, validation = with_rest_both(problem, validation, run.value, evidence.sigma_x)
    # The first search fitted the sliding law on the samples at rest too; where the plant
    # sticks often its breakaway bias can hold the base in a poor minimum at the box's
    # edge. The search is run again with the rule; the GLS fit keeps the better start.
    starts: tuple[np.ndarray, ...] = ()
    if problem.rest is not None and clock.over("base_fit"):
        clock.skip("base_fit", "second base search with the stick/slip rule")
    elif problem.rest is not None:
        with clock.stage("base_fit", "base fit: second search, stick/slip rule at rest"):
            starts = (identify(problem, replace(identify_settings, objective="equation")).value,)
    # The judge (record gains, then the held-out checks) is part of the stopping rule
    # (forward_select's ``confirm``): a candidate it refuses is not named and the next one
    # that passes the tests is asked. A second recording of the same motion confirms any
    # term that captures reproducible structure, right physics or not, so with one both
    # checks run, and a term must gain in every check that reaches its place.
    confirm = Confirm(problem, settings.heldout, validation, settings.noise)
    sel = forward_select(
        problem,
        run.value,
        starts=starts,
        alpha=settings.alpha,
        min_delta_bic=settings.min_delta_bic,
        max_terms=settings.max_terms,
        n_mc=settings.n_mc,
        seed=settings.seed,
        noise=settings.noise,
        evidence=evidence,
        confirm=confirm,
        clock=clock,
    )
    wh = sel.whitener
    base = (problem.model, problem.spec, sel.base_theta)
    final = (sel.model, sel.spec, sel.theta)
    maps = {"whitener": wh, "n_bins": settings.n_bins, "alpha": settings.alpha}
    with clock.stage("locate", "residual maps of the base fit"):
        loc_before = locate(problem, sel.base_theta, **maps, n_mc=settings.n_mc, seed=settings.seed)
        fit: dict[str, dict[str, float]] = {
            "before": {
                **_figures(problem, *base, wh, sel.extra.get("bic_sigma2")),
                "whiteness_p": loc_before.ljung_box_p,
                "simulation_rms_m": simulation_error(problem, *base),
            },
        }
    band = near_rest_band(problem, evidence.sigma_x)
    chosen_steps = [step for step in sel.steps if step.chosen is not None]
    findings = [_finding(problem, step) | step.heldout for step in chosen_steps]
    heldout: dict[str, Any] = {}
    if findings:
        chain = [base, *((st.chosen.model, st.chosen.spec, st.chosen.theta) for st in chosen_steps)]
        places = [f["location"] for f in findings]
        owns = [_own(m, st.chosen) for m, st in zip(chain, chosen_steps, strict=False)]
        heldout = confirm.judges[0].summary(chain, places, owns)
        if len(confirm.judges) > 1:
            heldout["split"] = confirm.judges[1].summary(chain, places, owns)
    rejected = [
        _rejected(problem, rf, next(sc.p_value for sc in st.scores if sc.effect == rf.effect), rep)
        for st in sel.steps
        for rf, rep in st.rejected
    ]
    sim = None
    # Equation error named nothing: the motion itself is asked, by output error, which
    # needs no velocity and so sees how the plant stops and breaks away. Its own lack-of-fit
    # test against the record's noise decides whether any candidate is fitted there.
    if settings.simulation_test and not chosen_steps:
        if clock.over("simulation_test"):
            for effect in simulation_candidates():
                clock.untested("simulation_test", effect)
        else:
            with clock.stage("simulation_test", "simulation test: base by output error"):
                sim = simulation_test(
                    problem,
                    problem.spec.as_dict(sel.base_theta),
                    effects=simulation_candidates(),
                    alpha=settings.alpha,
                    min_delta_bic=settings.min_delta_bic,
                    fraction=settings.heldout,
                    validation=validation,
                    clock=clock,
                    evidence=evidence,
                )
        if sim is not None and sim.chosen is not None:
            law_sel = _with_law(problem, sel, sim.chosen)
            law_final = (law_sel.model, law_sel.spec, law_sel.theta)
            gains = record_gains(problem, base, law_final)
            if all(g > 0 for g in gains if math.isfinite(g)):
                sel, final = law_sel, law_final
                findings = [
                    _law_finding(problem, sim, band) | dict(zip(RECORD_KEYS, gains, strict=True))
                ]
            else:
                # the same rule as for equation error: not named where the fit a user
                # sees gets worse
                sim.rejected.append(
                    (sim.chosen, {**sim.heldout, **dict(zip(RECORD_KEYS, gains, strict=True))})
                )
                sim.chosen = None
    final_pb = with_model(problem, sel.model, sel.spec)
    loc_after: LocateReport | None = None
    locate_note = ""
    if clock.over("locate"):
        locate_note = "time limit"
        clock.skip("locate", "residual maps and whiteness after the findings")
    else:
        with clock.stage("locate", "residual maps after the findings"):
            try:
                loc_after = locate(
                    final_pb, sel.theta, **maps, n_mc=settings.n_mc, seed=settings.seed + 1
                )
            except TooShortToLocate as err:
                # A short record whose base fit leaves few degrees of freedom may have none
                # left for the maps once the named term is in. The finding stands on its own
                # tests; only the maps after it are missing, and the report says why.
                locate_note = str(err)
    with clock.stage("locate", "fit figures after the findings"):
        fit["after"] = {
            **_figures(problem, *final, wh, sel.extra.get("bic_sigma2")),
            "whiteness_p": loc_after.ljung_box_p if loc_after is not None else float("nan"),
            "simulation_rms_m": simulation_error(problem, *final),
        }
    if sim is not None and sim.chosen is not None:
        # what the named term was judged by: the output error of the 0.05 s segments
        # [σ_x², whole record]; the single simulation over the whole record above drifts
        # with any force error and is no measure of it
        fit["before"]["output_error_cost"] = sim.chosen.cost_base
        fit["after"]["output_error_cost"] = sim.chosen.fit.cost
    # A rejected candidate's structure is still significant on the record: reported as
    # unexplained at its place (and then the maps' own leftover would repeat it).
    leftover = _unexplained(loc_after, settings.alpha) if loc_after is not None else None
    if leftover is None and not findings and not rejected:
        leftover = _excess(problem, sel, settings.alpha)
    findings += rejected or ([leftover] if leftover is not None else [])
    extra_sim = {} if sim is None else {"simulation_test": _simulation_summary(sim)}
    return Diagnosis(
        recording=recording or problem.name,
        base_model=problem.model.name,
        findings=findings,
        fit=fit,
        heldout=heldout,
        selection=sel,
        locate_before=loc_before,
        locate_after=loc_after,
        problem=problem,
        base_spec=problem.spec,
        evidence=evidence,
        near_rest=band,
        clock=clock,
        extra={
            "base_identify_ems": run.ems,
            **extra_sim,
            **({"locate_after_skipped": locate_note} if locate_note else {}),
        },
    )


def _with_law(problem: Problem, sel: Selection, law: LawFit) -> Selection:
    """``sel`` with base + the friction-law term named by simulation as its final model,
    refitted in the selection's metric (GLS, whitener of the base fit) from the better of
    the output-error estimate and the base with the term at its null."""
    spec_e, model_e = law.problem.spec, law.problem.model
    named = {**problem.spec.as_dict(sel.base_theta), **law.params}
    at_null = {**named, **{q.name: q.null for q in spec_e.free if q.name in law.params}}
    at_null = {k: v for k, v in at_null.items() if np.isfinite(v)}
    pb = with_model(problem, model_e, spec_e)
    starts = [spec_e.flatten(law.fit.params), spec_e.flatten({**named, **at_null})]
    theta, _ = min(
        (gls_fit(pb, model_e, spec_e, th, sel.whitener) for th in starts), key=lambda f: f[1]
    )
    return replace(sel, model=model_e, spec=spec_e, theta=theta)


def _law_finding(problem: Problem, sim: SimulationTest, band: NearRest) -> dict[str, Any]:
    """The finding of a term named by simulation (diagnosis.json); ``band``: the record's
    near-rest band, which the equation error holds by the stick/slip rule."""
    law = sim.chosen
    assert law is not None
    cand = candidate(law.effect)
    gain = 1 - law.fit.cost / law.cost_base
    runner = sorted((f for f in sim.fits if f is not law), key=lambda f: -f.delta_bic)
    out: dict[str, Any] = {
        "effect": law.effect,
        "explanation": cand.explain(law.params, problem)
        + (
            " Found by simulation: with it the output error of the record's 0.05 s "
            f"simulated segments falls from {law.cost_base:.4g} to {law.fit.cost:.4g} σ_x² "
            f"({-100 * gain:+.1f} %, LR = {law.lr:.1f}); its equation-error signature "
            f"alone was not significant ({100 * band.share:.0f} % of the samples lie below "
            f"{band.speed:.3g} m/s, "
            "where equation error holds the stick/slip rule and simulation sees how the "
            "plant stops and breaks away)."
        ),
        "location": cand.location(law.params, problem),
        "params": law.params,
        "at_bound": at_bounds(law.problem.spec, law.params),
        "delta_bic": law.delta_bic,
        "p_value": law.p_value,
        "test": "output error",
        "output_error": {
            "cost_base": law.cost_base,
            "cost_term": law.fit.cost,
            "lr": law.lr,
            "runner_up": runner[0].effect if runner else "",
            "runner_up_delta_bic": runner[0].delta_bic if runner else float("nan"),
        },
        **{k: v for k, v in sim.heldout.items() if any(k in pair for pair in HELDOUT_KEYS)},
        "heldout_metric": "output error on the second recording"
        if sim.heldout.get("heldout_part") == "second recording"
        else f"output error on the {sim.heldout.get('heldout_part', 'last')} part of the record",
        "heldout_confirmed": True,
    }
    return out


def _simulation_summary(sim: SimulationTest) -> dict[str, Any]:
    """Every candidate's output-error test, for diagnosis.json and the benchmark: costs in
    units of σ_x², ``cost_base`` the base's first fit, each candidate's own ``cost_base``
    the base fit its LR was taken against (the lower where the base was refitted from the
    term's end) and ``cost_term`` its fit's."""
    return {
        "cost_base": sim.base.cost,
        "lack_of_fit_p": sim.lack_of_fit_p,
        "candidates": [
            {
                "effect": f.effect,
                "lr": f.lr,
                "p_value": f.p_value,
                "delta_bic": f.delta_bic,
                "base_refitted": f.rebased,
                "cost_base": f.cost_base,
                "cost_term": f.fit.cost,
            }
            for f in sim.fits
        ],
        "chosen": sim.chosen.effect if sim.chosen is not None else None,
        "heldout": sim.heldout,
        "rejected": [{"effect": f.effect, **r} for f, r in sim.rejected],
    }


def _finding(problem: Problem, step: Any) -> dict[str, Any]:
    """One finding of diagnosis.json, named by equation error."""
    chosen = step.chosen
    cand = candidate(chosen.effect)
    out: dict[str, Any] = {
        "effect": chosen.effect,
        "explanation": cand.explain(chosen.params, problem),
        "location": cand.location(chosen.params, problem),
        "params": chosen.params,
        "at_bound": at_bounds(chosen.spec, chosen.params),
        "delta_bic": chosen.delta_bic,
        "p_value": step.p_value,
    }
    if step.overlap > 0.9 and step.runner_up:
        out["indistinguishable_from"] = step.runner_up
        out["signature_overlap"] = step.overlap
        out["explanation"] += (
            f" On this excitation its signature overlaps that of {step.runner_up} "
            f"(|cos| = {step.overlap:.2f}): the two cannot be told apart reliably."
        )
    clash = _drive_clash(problem, chosen)
    if clash:
        out["near_drive_harmonic"] = clash
        out["explanation"] += drive_harmonic_note(clash)
    return out


def _unexplained(loc: LocateReport, alpha: float) -> dict[str, Any] | None:
    """Structure still significant after the chosen terms: say where, name nothing.

    A claim about the record, so its false-alarm rate is controlled over *all* maps: a map
    counts only when its family-wise p-value is below ``alpha / (number of maps)``
    (Bonferroni, as the candidates share ``alpha`` over the catalogue). Each map alone
    keeps its own ``alpha`` for the significance bands it draws (``locate``); six maps at
    α each would make ~6α of null records "unexplained".
    """
    limit = alpha / max(len(loc.family_p), 1)
    sig = [b for b in loc.significant if loc.family_p.get(b.variable, 1.0) <= limit]
    sig = [b for b in sig if b.variable != "frequency"] or sig
    if not sig:
        return None
    worst = max(sig, key=lambda b: b.score)
    family = loc.family_p.get(worst.variable.rstrip("+-"), loc.family_p.get(worst.variable, alpha))
    units = {
        "time": "time_s",
        "position": "position_m",
        "velocity+": "velocity_mps",
        "velocity-": "velocity_mps",
        "acceleration": "acceleration_mps2",
        "frequency": "frequency_hz",
    }
    where_ = {units.get(worst.variable, worst.variable): [worst.lo, worst.hi]}
    return {
        "effect": "unexplained",
        "explanation": (
            f"The residual is still significantly structured against {worst.variable} in "
            f"[{worst.lo:.4g}, {worst.hi:.4g}] (mean residual {worst.mean_residual:.3g} N), "
            "but no catalogue term explains it better than chance."
        ),
        "location": where_,
        "params": {"mean_residual_N": worst.mean_residual},
        "delta_bic": worst.score - math.log(max(len(loc.bins), 2)),
        "p_value": family,
    }


def _excess(problem: Problem, sel: Any, alpha: float) -> dict[str, Any] | None:
    """``unexplained`` over the whole record where a short record's base leaves an excess
    over the recording's own noise (:mod:`~fricjax.diagnose.evidence`;
    :func:`~fricjax.diagnose.select.lack_of_fit_p`
    below ``alpha``) that no candidate explains and the maps do not place: the record
    holds something the model lacks, nothing says what or where."""
    if not sel.steps or sel.steps[0].lack_of_fit_p >= alpha:
        return None
    p, excess = sel.steps[0].lack_of_fit_p, sel.steps[0].lack_of_fit_excess
    r = ranges(problem)
    return {
        "effect": "unexplained",
        "explanation": (
            "The fitted model leaves more residual than the measurement noise accounts for "
            f"({excess:.1f} σ² in excess, p = {p:.2g}, against the noise measured in the "
            "recording's own displacement), "
            "but no catalogue term explains it and no single interval, band or frequency "
            "stands out: this record is too short to say where."
        ),
        "location": {"time_s": [r.t0, r.t1]},
        "params": {},
        # a term that explained all of it would lower BIC by about this, less its own
        # parameters' penalty
        "delta_bic": excess,
        "p_value": p,
    }


# -- output --------------------------------------------------------------------------------


#: The files :func:`write_diagnosis` writes under fixed names (plus ``residual_*.png``).
OUTPUT_FILES = ("diagnosis.json", "models.h5", "report.md", "report.html")


def write_diagnosis(diag: Diagnosis, out_dir: str | Path) -> dict[str, Path]:
    """Write diagnosis.json, models.h5, report.md, report.html and its figures into
    ``out_dir``."""
    from fricjax.diagnose.report import write_reports

    out = make_folder(out_dir)
    json_name, models_name = OUTPUT_FILES[:2]
    # diagnosis.json last, so its timing holds the report stage too
    paths = {"json": out / json_name}
    with diag.clock.stage("report", "figures, models file and report"):
        paths["models"] = _write_models(diag, out / models_name)
        paths.update(write_reports(diag, out))
    write_text_atomic(paths["json"], json.dumps(diag.as_json(), indent=2) + "\n")
    return paths


def _write_models(diag: Diagnosis, path: Path) -> Path:
    sel = diag.selection

    def fill(f: h5py.File) -> None:
        f.attrs["format"] = "fricjax-diagnosis-models-v1"
        f.attrs["recording"] = diag.recording
        for label, (model, spec, theta) in (
            ("base", (diag.problem.model, diag.base_spec, sel.base_theta)),
            ("final", (sel.model, sel.spec, sel.theta)),
        ):
            g = f.create_group(label)
            g.attrs["model"] = model.name
            g.attrs["terms"] = json.dumps([t.name for t in model.terms])
            named = spec.as_dict(theta)
            g["names"] = np.array(list(named), dtype=h5py.string_dtype())
            g["values"] = np.array(list(named.values()), dtype=np.float64)
            g["free"] = np.array([spec[n].free for n in named], dtype=bool)
            g["units"] = np.array([spec[n].unit for n in named], dtype=h5py.string_dtype())

    return write_hdf5_atomic(path, fill)
