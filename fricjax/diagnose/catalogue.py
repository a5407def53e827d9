"""The catalogue of candidate physics terms that the diagnosis tries on a fitted base model.

Every effect name of ``docs/formats.md`` (except ``unexplained``, which the selection
reports when nothing here fits) is one :class:`Candidate`. A candidate is either a model
:class:`~fricjax.model.term.Term` appended to the base model, or (``mass_error``) a change of
the parameter specification. Its parameters split in two:

* **linear** amplitudes ``β`` (null value 0, ``Param.null = 0.0``) at which the added force is
  exactly zero, so ``base ⊂ base + term`` (nested models): the judge's likelihood ratio
  compares nested fits;
* **nonlinear** shape parameters ``θ`` (a location, a width, a frequency, a presliding
  distance, ...) scanned over :meth:`Candidate.grid`, built from the recording's ranges
  (:func:`ranges`), whose best points start the output-error fit of ``β`` and ``θ``.

The terms' forces (equations, roles) are in :mod:`fricjax.model.effects`; here is how the
diagnosis tries each: which parameters it frees, on which grid, within which bounds.

Scales. Amplitude bounds are ``±AMPLITUDE_FACTOR·F_ref`` (divided by ``max|v|`` or
``max|v|²`` for the viscous and drag coefficients), with the force scale
``F_ref = max(rms(m·a), rms(F_f(init)))`` [N] (:func:`force_scale`): the rms measured force,
or the rms friction of the base model at the spec's initial values when the body hardly
accelerates (e.g. constant-speed runs). ``impact`` uses ``max(F_ref, max|m·a|)`` since a shock
shows as a peak rather than in the rms. Grids hold at most ``MAX_GRID`` points.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from fricjax.errors import FricjaxError, where
from fricjax.model.effects import (
    AsymmetricFriction,
    ExtraHarmonic,
    FrictionDrift,
    GaussianStribeck,
    Impact,
    MassError,
    PositionBump,
    PositionPeriodic,
    PreslidingHysteresis,
    QuadraticDrag,
    StribeckShape,
    bristle_state,
)
from fricjax.model.system import Model
from fricjax.model.term import Term
from fricjax.params import Param, ParamSpec

if TYPE_CHECKING:
    from fricjax.problem import Problem

__all__ = [
    "AMPLITUDE_FACTOR",
    "CATALOGUE",
    "MAX_GRID",
    "Candidate",
    "Ranges",
    "candidate",
    "cutoff_hz",
    "drive_harmonic_note",
    "force_scale",
    "grid_size",
    "near_drive_harmonic",
    "ranges",
]

# Amplitude bounds are ± this many force scales: wide enough for any effect that shows in
# the residual (a missing Stribeck drop of the twin is ~0.1·F_ref), and the box only keeps
# Levenberg–Marquardt from wandering off when an amplitude is unidentifiable.
AMPLITUDE_FACTOR = 2.0
# A scan ranks every grid point by one equation-error residual per amplitude; 400 keeps
# it cheap.
MAX_GRID = 400
# Fixed grid sizes (documented in each candidate).
N_VST = 32
N_EPS = 24
N_BUMP_X0 = 51
N_BUMP_W = 3
N_IMPACT_W = 3
MIN_SPECTRAL_GRID = 16
_TINY = 1e-12
_SOURCE = "catalogue"


# -- recording ranges ---------------------------------------------------------------------
class Ranges(NamedTuple):
    """What the grids and bounds are built from (floored so that nothing divides by zero).

    dt [s] sample step; t0, t1 [s] first/last time; duration [s] = t1 − t0; x_min, x_max [m];
    x_range [m]; v_max [m/s] = max|v|; v_mean [m/s] = mean|v|; travel [m] = Σ|Δx|;
    f_cut [Hz] band edge of the preprocessing (:func:`cutoff_hz`); f_nyq [Hz].
    """

    dt: float
    t0: float
    t1: float
    duration: float
    x_min: float
    x_max: float
    x_range: float
    v_max: float
    v_mean: float
    travel: float
    f_cut: float
    f_nyq: float


def _sample_step(t: np.ndarray) -> float:
    return float(np.median(np.diff(t))) if t.size > 1 else 1.0


def cutoff_hz(problem: Problem) -> float:
    """Upper edge [Hz] of the band the preprocessing keeps in ``v`` and ``a``.

    Butterworth: its ``cutoff_hz``. Savitzky–Golay: the −3 dB frequency of its smoothing
    (degree ``savgol_polyorder``, ``savgol_window`` samples), computed from the filter
    coefficients. No settings: the Nyquist frequency. Never above Nyquist.
    """
    dt = _sample_step(np.asarray(problem.t))
    nyq = 0.5 / dt
    s = problem.preprocess
    if s is None:
        return nyq
    if s.method == "butterworth":
        return min(float(s.cutoff_hz), nyq)
    from scipy import signal  # lazily: importing scipy.signal costs ~0.6 s of CPU

    coeffs = signal.savgol_coeffs(s.savgol_window, s.savgol_polyorder)
    freq, resp = signal.freqz(coeffs, worN=4096, fs=1.0 / dt)
    below = np.nonzero(np.abs(resp) < 1.0 / math.sqrt(2.0))[0]
    return float(freq[below[0]]) if below.size else nyq


def ranges(problem: Problem) -> Ranges:
    """The recording's ranges (:class:`Ranges`) for grids and bounds."""
    t, x, v = (np.asarray(a, dtype=np.float64) for a in (problem.t, problem.x, problem.v))
    dt = _sample_step(t)
    x_min, x_max = float(np.min(x)), float(np.max(x))
    return Ranges(
        dt=dt,
        t0=float(t[0]),
        t1=float(t[-1]),
        duration=max(float(t[-1] - t[0]), dt),
        x_min=x_min,
        x_max=x_max,
        x_range=max(x_max - x_min, _TINY),
        v_max=max(float(np.max(np.abs(v))), _TINY),
        v_mean=max(float(np.mean(np.abs(v))), _TINY),
        travel=max(float(np.sum(np.abs(np.diff(x)))), _TINY),
        f_cut=cutoff_hz(problem),
        f_nyq=0.5 / dt,
    )


def _mass(problem: Problem) -> float:
    return float(problem.spec["mass"].init) if "mass" in problem.spec else 1.0


def force_scale(problem: Problem) -> float:
    """``F_ref = max(rms(m·a), rms(F_f(init)))`` [N] (1 N if both vanish).

    ``rms(m·a)``: the measured force; ``F_f(init)``: the base model's friction at the spec's
    initial (or fitted, if the spec carries them) values, which dominates when the body
    moves at nearly constant speed.
    """
    rms_ma = float(np.sqrt(np.mean((_mass(problem) * np.asarray(problem.a)) ** 2)))
    # Bounds are host-side metadata: evaluate eagerly even when called inside a jax trace.
    with jax.ensure_compile_time_eval():
        ff = problem.model.friction(problem.spec.as_dict(), problem.signals)
        rms_ff = float(jnp.sqrt(jnp.mean(ff**2)))
    scale = max(rms_ma if math.isfinite(rms_ma) else 0.0, rms_ff if math.isfinite(rms_ff) else 0.0)
    return scale if scale > 0 else 1.0


def _amplitude(name: str, unit: str, bound: float) -> Param:
    return Param(name, unit, -bound, bound, 0.0, null=0.0)


def _product(axes: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Cartesian product of 1-D axes, flattened row-major (first axis slowest), each [G]."""
    if not axes:
        return {}
    mesh = np.meshgrid(*axes.values(), indexing="ij")
    return {k: np.asarray(m, dtype=np.float64).ravel() for k, m in zip(axes, mesh, strict=True)}


def grid_size(grid: Mapping[str, np.ndarray]) -> int:
    """Number of grid points G; an empty grid (no nonlinear parameters) is one point."""
    return int(next(iter(grid.values())).shape[0]) if grid else 1


def _has_friction(model: Model) -> bool:
    return any(term.role == "friction" for term in model.terms)


def _value(params: Mapping[str, float], problem: Problem, name: str, default: float) -> float:
    """A parameter from the reported mapping, else the problem's spec, else ``default``."""
    if name in params:
        return float(params[name])
    if name in problem.spec:
        return float(problem.spec[name].init)
    return default


def _g(value: float) -> str:
    return f"{value:.3g}"


# -- candidates ---------------------------------------------------------------------------
@dataclass(frozen=True)
class Candidate:
    """One catalogue effect: a term appended to the base model (or a spec change).

    The judge (:mod:`fricjax.diagnose.judge`) tests every entry whose force is pointwise
    (:attr:`simulable`) by output error; its nonlinear parameters start at points of
    :meth:`grid`.
    """

    effect: str = ""

    # structure ----------------------------------------------------------------------------
    @property
    def simulable(self) -> bool:
        """Whether the simulator integrates this effect's force (no bristle state)."""
        return True

    def term(self, problem: Problem) -> Term | None:
        """The term this effect appends (``None`` for a pure spec change)."""
        raise NotImplementedError

    def applicable(self, model: Model, spec: ParamSpec) -> bool:
        """Whether the effect can be added to this base (not already there, needs met)."""
        raise NotImplementedError

    def _axes(self, problem: Problem) -> tuple[tuple[Param, np.ndarray], ...]:
        """(nonlinear parameter with bounds, its 1-D grid axis) pairs."""
        return ()

    # parameters ---------------------------------------------------------------------------
    def linear_params(self, problem: Problem) -> tuple[Param, ...]:
        """Amplitude parameters (null 0, init 0), bounds scaled to the problem."""
        raise NotImplementedError

    def nonlinear_params(self, problem: Problem) -> tuple[Param, ...]:
        """Shape parameters, bounds from the recording's ranges, init at the middle of the
        grid axis."""
        return tuple(
            replace(p, init=float(axis[(axis.size - 1) // 2])) for p, axis in self._axes(problem)
        )

    def grid(self, problem: Problem) -> dict[str, np.ndarray]:
        """Nonlinear values to scan: ``{name: [G]}``, the flattened Cartesian product of the
        axes (first parameter slowest); ``{}`` means one point (no nonlinear parameters)."""
        return _product({p.name: axis for p, axis in self._axes(problem)})

    def extend(
        self,
        model: Model,
        spec: ParamSpec,
        problem: Problem,
        nonlinear: Mapping[str, float] | None = None,
    ) -> tuple[Model, ParamSpec]:
        """Base + this effect: the term appended to ``model``; its parameters appended to
        ``spec`` after the base ones, linear first (init 0) then nonlinear (free in their
        bounds, init at ``nonlinear[name]`` clipped into the bounds, else the grid middle).
        """
        if not self.applicable(model, spec):
            raise FricjaxError(
                f"{where(_SOURCE, self.effect)}: not applicable to base model {model.name}"
            )
        nl = self.nonlinear_params(problem)
        values = dict(nonlinear or {})
        unknown = sorted(set(values) - {p.name for p in nl})
        if unknown:
            raise FricjaxError(
                f"{where(_SOURCE, self.effect)}: unknown nonlinear parameter {unknown[0]!r} "
                f"(it takes: {', '.join(p.name for p in nl) or 'none'})"
            )
        nl = tuple(
            replace(p, init=float(np.clip(values[p.name], p.lower, p.upper)))
            if p.name in values
            else p
            for p in nl
        )
        lin = tuple(replace(p, init=0.0, free=True) for p in self.linear_params(problem))
        term = self.term(problem)
        assert term is not None
        return model.with_terms([term]), spec.extended(lin + nl)

    def extend_problem(
        self, problem: Problem, nonlinear: Mapping[str, float] | None = None
    ) -> Problem:
        """``problem`` with its model and spec extended by this effect (same signals)."""
        model, spec = self.extend(problem.model, problem.spec, problem, nonlinear)
        return replace(problem, model=model, spec=spec)

    # reporting ----------------------------------------------------------------------------
    def location(self, params: Mapping[str, float], problem: Problem) -> dict:
        """Where the effect acts, for diagnosis.json (SI units, plain floats)."""
        raise NotImplementedError

    def explain(self, params: Mapping[str, float], problem: Problem) -> str:
        """One or two plain sentences: what physics, where, why (numbers with units)."""
        raise NotImplementedError


@dataclass(frozen=True)
class _TermCandidate(Candidate):
    """A candidate made of one term; applicable when that term is not in the base yet."""

    needs_friction: ClassVar[bool] = False
    term_class: ClassVar[type[Term]] = Term

    def term(self, problem: Problem) -> Term | None:
        return self.term_class()

    def applicable(self, model: Model, spec: ParamSpec) -> bool:
        if any(t.name == self.term_class.name for t in model.terms):
            return False
        if any(q in spec for q in self.term_class().param_names):
            return False
        return _has_friction(model) or not self.needs_friction


@dataclass(frozen=True)
class StribeckCandidate(_TermCandidate):
    """``stribeck``: :class:`GaussianStribeck`; needs a friction term in the base.

    Grid: ``N_VST`` = 32 values of vst log-spaced over [1 %, 50 %] of max|v| (G = 32);
    bounds vst ∈ [0.5 %, 100 %] of max|v|, A ∈ ±2·F_ref.
    """

    effect: str = "stribeck"
    needs_friction: ClassVar[bool] = True
    term_class: ClassVar[type[Term]] = GaussianStribeck

    def linear_params(self, problem: Problem) -> tuple[Param, ...]:
        return (_amplitude("stribeck_A", "N", AMPLITUDE_FACTOR * force_scale(problem)),)

    def _axes(self, problem: Problem) -> tuple[tuple[Param, np.ndarray], ...]:
        vmax = ranges(problem).v_max
        axis = np.geomspace(0.01 * vmax, 0.5 * vmax, N_VST)
        return ((Param("stribeck_vst", "m/s", 0.005 * vmax, vmax, float(axis[0])), axis),)

    def location(self, params: Mapping[str, float], problem: Problem) -> dict:
        vst = float(params["stribeck_vst"])
        return {"velocity_mps": [0.0, 2.0 * vst]}

    def explain(self, params: Mapping[str, float], problem: Problem) -> str:
        a, vst = float(params["stribeck_A"]), float(params["stribeck_vst"])
        word = "higher" if a >= 0 else "lower"
        return (
            f"Friction is {_g(abs(a))} N {word} near rest than in sliding and the difference "
            f"fades out by |v| ≈ {_g(2 * vst)} m/s (Stribeck drop, Gaussian shape, "
            f"vst = {_g(vst)} m/s). The base friction law has no such low-speed change."
        )


_STRIBECK_BASE = ("Fs", "Fc", "vs", "delta")


@dataclass(frozen=True)
class StribeckShapeCandidate(_TermCandidate):
    """``stribeck_shape``: :class:`StribeckShape`; local parameter dδ (``local = True``).

    Applicable when a base friction term reads ``Fs, Fc, vs, delta`` and δ is fixed (a free
    δ already absorbs dδ). Bounds dδ ∈ [max(−0.8, 0.1 − δ), 2] so that δ + dδ ≥ 0.1;
    no grid (G = 1).
    """

    effect: str = "stribeck_shape"
    needs_friction: ClassVar[bool] = True
    term_class: ClassVar[type[Term]] = StribeckShape

    def applicable(self, model: Model, spec: ParamSpec) -> bool:
        if not super().applicable(model, spec):
            return False
        reads = any(
            t.role == "friction" and set(_STRIBECK_BASE) <= set(t.param_names) for t in model.terms
        )
        return reads and all(q in spec for q in _STRIBECK_BASE) and not spec["delta"].free

    def linear_params(self, problem: Problem) -> tuple[Param, ...]:
        delta = _value({}, problem, "delta", 1.0)
        return (Param("shape_ddelta", "1", min(max(-0.8, 0.1 - delta), 0.0), 2.0, 0.0, null=0.0),)

    def location(self, params: Mapping[str, float], problem: Problem) -> dict:
        vs = _value(params, problem, "vs", ranges(problem).v_max)
        return {"velocity_mps": [0.0, 3.0 * vs]}

    def explain(self, params: Mapping[str, float], problem: Problem) -> str:
        delta = _value(params, problem, "delta", 1.0)
        new = delta + float(params["shape_ddelta"])
        vs = _value(params, problem, "vs", ranges(problem).v_max)
        return (
            f"The Stribeck drop has another shape: exponent δ ≈ {_g(new)} instead of the "
            f"model's {_g(delta)}, which changes how friction falls from the static to the "
            f"Coulomb level at speeds below about {_g(3 * vs)} m/s."
        )


@dataclass(frozen=True)
class AsymmetricCandidate(_TermCandidate):
    """``asymmetric_friction``: :class:`AsymmetricFriction`; needs a friction term.

    Bounds dFc ∈ ±2·F_ref [N], dFv ∈ ±2·F_ref/max|v| [N·s/m]; no grid (G = 1).
    """

    effect: str = "asymmetric_friction"
    needs_friction: ClassVar[bool] = True
    term_class: ClassVar[type[Term]] = AsymmetricFriction

    def linear_params(self, problem: Problem) -> tuple[Param, ...]:
        bound = AMPLITUDE_FACTOR * force_scale(problem)
        return (
            _amplitude("asym_dFc", "N", bound),
            _amplitude("asym_dFv", "N*s/m", bound / ranges(problem).v_max),
        )

    def _excess(self, params: Mapping[str, float], problem: Problem) -> float:
        """Friction excess of forward over backward motion at the mean speed [N]."""
        r = ranges(problem)
        return 2.0 * (float(params["asym_dFc"]) + float(params["asym_dFv"]) * r.v_mean)

    def location(self, params: Mapping[str, float], problem: Problem) -> dict:
        return {"direction": "positive" if self._excess(params, problem) >= 0 else "negative"}

    def explain(self, params: Mapping[str, float], problem: Problem) -> str:
        dfc, dfv = float(params["asym_dFc"]), float(params["asym_dFv"])
        excess = self._excess(params, problem)
        side = "forward (v > 0)" if excess >= 0 else "backward (v < 0)"
        return (
            f"Friction depends on the direction of motion: it is {_g(abs(excess))} N higher "
            f"moving {side} at the mean speed {_g(ranges(problem).v_mean)} m/s (Coulomb level "
            f"Fc ± {_g(dfc)} N, viscous Fv ± {_g(dfv)} N·s/m)."
        )


@dataclass(frozen=True)
class QuadraticDragCandidate(_TermCandidate):
    """``quadratic_drag``: :class:`QuadraticDrag`. Bounds Cd ∈ ±2·F_ref/max|v|²; G = 1."""

    effect: str = "quadratic_drag"
    term_class: ClassVar[type[Term]] = QuadraticDrag

    def linear_params(self, problem: Problem) -> tuple[Param, ...]:
        bound = AMPLITUDE_FACTOR * force_scale(problem) / ranges(problem).v_max ** 2
        return (_amplitude("drag_Cd", "N*s^2/m^2", bound),)

    def location(self, params: Mapping[str, float], problem: Problem) -> dict:
        vmax = ranges(problem).v_max
        return {"velocity_mps": [0.5 * vmax, vmax]}

    def explain(self, params: Mapping[str, float], problem: Problem) -> str:
        cd, vmax = float(params["drag_Cd"]), ranges(problem).v_max
        return (
            f"A resisting force growing with the square of speed (fluid or air drag), "
            f"Cd = {_g(cd)} N·s²/m², reaching {_g(abs(cd) * vmax**2)} N at the top speed "
            f"{_g(vmax)} m/s; it shows most at high speed."
        )


@dataclass(frozen=True)
class PreslidingCandidate(_TermCandidate):
    """``presliding_hysteresis``: :class:`PreslidingHysteresis` (stateful); needs friction.

    Grid: ``N_EPS`` = 24 values of ε log-spaced over [min(1e-5, hi/100), hi] m with
    ``hi = min(1e-2 m, x range)`` (G = 24); bounds ε ∈ [lo/2, 2·hi], A ∈ ±2·F_ref.
    """

    effect: str = "presliding_hysteresis"
    needs_friction: ClassVar[bool] = True
    term_class: ClassVar[type[Term]] = PreslidingHysteresis

    @property
    def simulable(self) -> bool:
        """The bristle state ``z`` is integrated by no simulator of fricjax yet."""
        return False

    def linear_params(self, problem: Problem) -> tuple[Param, ...]:
        return (_amplitude("presl_A", "N", AMPLITUDE_FACTOR * force_scale(problem)),)

    def _axes(self, problem: Problem) -> tuple[tuple[Param, np.ndarray], ...]:
        hi = min(1e-2, ranges(problem).x_range)
        lo = min(1e-5, hi / 100.0)
        axis = np.geomspace(lo, hi, N_EPS)
        return ((Param("presl_eps", "m", lo / 2.0, 2.0 * hi, lo), axis),)

    def _lag(self, params: Mapping[str, float], problem: Problem) -> np.ndarray:
        with jax.ensure_compile_time_eval():
            z = bristle_state(
                jnp.asarray(problem.x), jnp.asarray(problem.v), float(params["presl_eps"])
            )
        return np.abs(np.asarray(z) - np.sign(np.asarray(problem.v)))

    def location(self, params: Mapping[str, float], problem: Problem) -> dict:
        t = np.asarray(problem.t)
        lag = self._lag(params, problem)
        s = np.sign(np.asarray(problem.v))
        nz = np.nonzero(s)[0]
        flips = nz[1:][s[nz[1:]] != s[nz[:-1]]]
        out: dict = {
            "presliding_distance_m": 3.0 * float(params["presl_eps"]),
            "reversals_s": [float(t[k]) for k in flips[:20]],
        }
        hit = np.nonzero(lag > 0.05 * lag.max())[0] if lag.max() > 0 else np.array([], int)
        if hit.size:
            out["time_s"] = [float(t[hit[0]]), float(t[hit[-1]])]
        return out

    def explain(self, params: Mapping[str, float], problem: Problem) -> str:
        a, eps = float(params["presl_A"]), float(params["presl_eps"])
        n_rev = len(self.location(params, problem)["reversals_s"])
        return (
            f"Friction has memory (Dahl/LuGre bristles): after each of the {n_rev} reversals "
            f"it lags behind the Coulomb law by up to {_g(2 * abs(a))} N over a presliding "
            f"travel of about {_g(3 * eps)} m (ε = {_g(eps)} m)."
        )


@dataclass(frozen=True)
class PositionBumpCandidate(_TermCandidate):
    """``position_bump``: :class:`PositionBump`.

    Grid: x0 on ``N_BUMP_X0`` = 51 points spanning the x range (spacing 2 % of it, the
    smallest width) × w on ``N_BUMP_W`` = 3 widths log-spaced over [2 %, 20 %] of the x
    range (G = 153). Bounds: x0 ∈ [x_min, x_max], w ∈ [0.5 %, 50 %] of the x range,
    A ∈ ±2·F_ref.
    """

    effect: str = "position_bump"
    term_class: ClassVar[type[Term]] = PositionBump

    def linear_params(self, problem: Problem) -> tuple[Param, ...]:
        return (_amplitude("bump_A", "N", AMPLITUDE_FACTOR * force_scale(problem)),)

    def _axes(self, problem: Problem) -> tuple[tuple[Param, np.ndarray], ...]:
        r = ranges(problem)
        x0 = np.linspace(r.x_min, r.x_max, N_BUMP_X0)
        w = np.geomspace(0.02 * r.x_range, 0.2 * r.x_range, N_BUMP_W)
        return (
            (Param("bump_x0", "m", r.x_min, r.x_min + r.x_range, r.x_min), x0),
            (Param("bump_w", "m", 0.005 * r.x_range, 0.5 * r.x_range, float(w[0])), w),
        )

    def location(self, params: Mapping[str, float], problem: Problem) -> dict:
        x0, w = float(params["bump_x0"]), abs(float(params["bump_w"]))
        return {"position_m": [x0 - 2.0 * w, x0 + 2.0 * w]}

    def explain(self, params: Mapping[str, float], problem: Problem) -> str:
        a, x0, w = (float(params[k]) for k in ("bump_A", "bump_x0", "bump_w"))
        word = "extra" if a >= 0 else "less"
        return (
            f"There is {_g(abs(a))} N {word} friction over positions {_g(x0 - 2 * w)} to "
            f"{_g(x0 + 2 * w)} m (centre {_g(x0)} m): a local obstacle such as a burr, an "
            f"engraving or a seal that the base friction law, the same everywhere, misses."
        )


@dataclass(frozen=True)
class PositionPeriodicCandidate(_TermCandidate):
    """``position_periodic``: :class:`PositionPeriodic`.

    Resolvable periods: ``λ_hi = min(x range, travel/3)`` (one period fits in the visited
    positions and is traversed at least three times); ``λ_lo = max(max|v|/f_cut,
    20·dt·mean|v|)`` (the spatial period at top speed stays below the preprocessing cut-off,
    and spans ~20 samples of travel), kept ≤ λ_hi/2. The grid is uniform in spatial
    frequency 1/λ (not log-spaced) with step ``1/(4·travel)``: the phase ``2πx/λ`` of the
    column then moves by at most π/2 between grid points over the whole travel, so no peak
    falls between points. G = clip(⌈(1/λ_lo − 1/λ_hi)·4·travel⌉ + 1, 16, 400); beyond 400
    the step grows. Bounds λ ∈ [λ_lo/1.5, 1.5·λ_hi], A, B ∈ ±2·F_ref.
    """

    effect: str = "position_periodic"
    term_class: ClassVar[type[Term]] = PositionPeriodic

    def linear_params(self, problem: Problem) -> tuple[Param, ...]:
        bound = AMPLITUDE_FACTOR * force_scale(problem)
        return (_amplitude("per_A", "N", bound), _amplitude("per_B", "N", bound))

    def _axes(self, problem: Problem) -> tuple[tuple[Param, np.ndarray], ...]:
        r = ranges(problem)
        lam_hi = min(r.x_range, r.travel / 3.0)
        lam_lo = min(max(r.v_max / r.f_cut, 20.0 * r.dt * r.v_mean), 0.5 * lam_hi)
        k_lo, k_hi = 1.0 / lam_hi, 1.0 / lam_lo
        g = int(np.clip(math.ceil((k_hi - k_lo) * 4.0 * r.travel) + 1, MIN_SPECTRAL_GRID, MAX_GRID))
        axis = np.sort(1.0 / np.linspace(k_lo, k_hi, g))
        axis = np.clip(axis, lam_lo, lam_hi)  # 1/(1/λ) may round off by an ulp
        return ((Param("per_lambda", "m", lam_lo / 1.5, 1.5 * lam_hi, lam_lo), axis),)

    def location(self, params: Mapping[str, float], problem: Problem) -> dict:
        r = ranges(problem)
        return {"period_m": float(params["per_lambda"]), "position_m": [r.x_min, r.x_max]}

    def explain(self, params: Mapping[str, float], problem: Problem) -> str:
        amp = math.hypot(float(params["per_A"]), float(params["per_B"]))
        lam = float(params["per_lambda"])
        return (
            f"A force of amplitude {_g(amp)} N repeats every {_g(lam)} m of travel "
            f"(cogging, a screw pitch or rollers): it follows position, not time, so the "
            f"drive harmonics cannot absorb it."
        )


@dataclass(frozen=True)
class ImpactCandidate(_TermCandidate):
    """``impact``: :class:`Impact`.

    Widths: the low-pass smears any shock to at least ``w_lo = max(2·dt, 1/(2π·f_cut))``
    (a Gaussian of std w has spectral std 1/(2πw)). Grid: t0 on
    ``n_t0 = min(⌊MAX_GRID/3⌋, ⌈T/w_lo⌉ + 1)`` points spanning the record × 3 widths
    log-spaced over [w1, max(10·dt, 2.5·w1)], ``w1 = max(w_lo, t0 spacing)`` — on long
    records the t0 spacing exceeds w_lo and the widths grow with it so that no impact falls
    between grid points (the refit then narrows w). G = 3·n_t0 ≤ 399. Bounds t0 ∈ [t_first,
    t_last], w ∈ [w_lo, 2·max grid width], A ∈ ±2·max(F_ref, max|m·a|).
    """

    effect: str = "impact"
    term_class: ClassVar[type[Term]] = Impact

    def linear_params(self, problem: Problem) -> tuple[Param, ...]:
        peak = float(np.max(np.abs(_mass(problem) * np.asarray(problem.a))))
        scale = max(force_scale(problem), peak if math.isfinite(peak) else 0.0)
        return (_amplitude("impact_A", "N", AMPLITUDE_FACTOR * scale),)

    def _axes(self, problem: Problem) -> tuple[tuple[Param, np.ndarray], ...]:
        r = ranges(problem)
        w_lo = max(2.0 * r.dt, 1.0 / (2.0 * math.pi * r.f_cut))
        n_t0 = max(2, min(MAX_GRID // N_IMPACT_W, math.ceil(r.duration / w_lo) + 1))
        t0 = np.linspace(r.t0, r.t1, n_t0)
        w1 = max(w_lo, r.duration / (n_t0 - 1))
        w = np.geomspace(w1, max(10.0 * r.dt, 2.5 * w1), N_IMPACT_W)
        return (
            (Param("impact_t0", "s", r.t0, r.t0 + r.duration, r.t0), t0),
            (Param("impact_w", "s", w_lo, 2.0 * float(w[-1]), w_lo), w),
        )

    def location(self, params: Mapping[str, float], problem: Problem) -> dict:
        t0, w = float(params["impact_t0"]), abs(float(params["impact_w"]))
        return {"time_s": [t0 - 2.0 * w, t0 + 2.0 * w]}

    def explain(self, params: Mapping[str, float], problem: Problem) -> str:
        a, t0, w = (float(params[k]) for k in ("impact_A", "impact_t0", "impact_w"))
        return (
            f"A short force pulse of {_g(a)} N at t = {_g(t0)} s lasting about "
            f"{_g(4 * abs(w) * 1e3)} ms (a collision or shock): the residual has a spike "
            f"there that no smooth drive or friction term produces."
        )


@dataclass(frozen=True)
class ExtraHarmonicCandidate(_TermCandidate):
    """``extra_harmonic``: :class:`ExtraHarmonic`.

    Grid: f uniform from ``f_lo = min(1/T, f_cut/2)`` (at least one period in the record) to
    the cut-off f_cut, step ``1/(4·T)`` (a quarter of the Fourier resolution, so a peak is
    never missed), G = clip(⌊(f_cut − f_lo)·4T⌋ + 1, 16, 400); beyond 400 the step grows.
    Bounds f ∈ [f_lo/2, Nyquist], A, B ∈ ±2·F_ref.
    """

    effect: str = "extra_harmonic"
    term_class: ClassVar[type[Term]] = ExtraHarmonic

    def linear_params(self, problem: Problem) -> tuple[Param, ...]:
        bound = AMPLITUDE_FACTOR * force_scale(problem)
        return (_amplitude("harm_A", "N", bound), _amplitude("harm_B", "N", bound))

    def _axes(self, problem: Problem) -> tuple[tuple[Param, np.ndarray], ...]:
        r = ranges(problem)
        f_hi = r.f_cut
        f_lo = min(1.0 / r.duration, 0.5 * f_hi)
        g = int(
            np.clip(math.floor((f_hi - f_lo) * 4.0 * r.duration) + 1, MIN_SPECTRAL_GRID, MAX_GRID)
        )
        axis = np.linspace(f_lo, f_hi, g)
        return ((Param("harm_f", "Hz", 0.5 * f_lo, max(r.f_nyq, f_hi), f_lo), axis),)

    def location(self, params: Mapping[str, float], problem: Problem) -> dict:
        return {"frequency_hz": float(params["harm_f"])}

    def explain(self, params: Mapping[str, float], problem: Problem) -> str:
        amp = math.hypot(float(params["harm_A"]), float(params["harm_B"]))
        f = float(params["harm_f"])
        return (
            f"A vibration of {_g(amp)} N at {_g(f)} Hz that the drive model does not contain "
            f"(a resonance, an unbalance or another excitation) runs through the whole record."
        )


def near_drive_harmonic(
    f_hz: float, named: Mapping[str, float], span_s: float
) -> dict[str, float] | None:
    """The drive harmonic ``f_i = i·ω/2π`` (seed eq. 5, i = 1..N over the model's ``Fp_i``)
    nearest to a frequency ``f`` [Hz], when ``|f − f_i| < 1/T`` (T = ``span_s`` [s], the
    record's span): over the record a sinusoid at f then drifts by less than one cycle
    against the i-th harmonic, so the fit can move it into ``(Fp_i, φ_i)`` and back, and
    the two cannot be told apart; a record longer than ``1/|f − f_i|`` separates them.

    ``named``: the fitted parameters by name (needs ``omega`` [rad/s]); None when the model
    has no drive or no harmonic is that close. Returns ``harmonic`` i,
    ``harmonic_hz`` f_i, ``separation_hz`` |f − f_i| and ``resolution_hz`` 1/T.
    """
    omega = named.get("omega")
    n = sum(1 for k in named if k.startswith("Fp_"))
    if omega is None or n == 0 or not span_s > 0:
        return None
    f0 = float(omega) / (2.0 * math.pi)
    i = int(np.clip(round(f_hz / f0), 1, n))
    gap = abs(f_hz - i * f0)
    if gap >= 1.0 / span_s:
        return None
    return {
        "harmonic": float(i),
        "harmonic_hz": i * f0,
        "separation_hz": gap,
        "resolution_hz": 1.0 / span_s,
    }


def drive_harmonic_note(clash: Mapping[str, float]) -> str:
    """One sentence for a finding whose frequency is that close to a drive harmonic."""
    i = int(clash["harmonic"])
    return (
        f" Its frequency lies {_g(clash['separation_hz'])} Hz from the drive's harmonic "
        f"{i} ({_g(clash['harmonic_hz'])} Hz), within this record's frequency resolution "
        f"(1/T = {_g(clash['resolution_hz'])} Hz): here it cannot be told apart from a "
        f"change of that harmonic's amplitude and phase (Fp_{i}, phi_{i})."
    )


@dataclass(frozen=True)
class FrictionDriftCandidate(_TermCandidate):
    """``friction_drift``: :class:`FrictionDrift` with ``t_mid``, ``T`` of the recording;
    needs a friction term. Bounds β ∈ ±2·F_ref; G = 1."""

    effect: str = "friction_drift"
    needs_friction: ClassVar[bool] = True
    term_class: ClassVar[type[Term]] = FrictionDrift

    def term(self, problem: Problem) -> Term | None:
        r = ranges(problem)
        return FrictionDrift(t_mid=0.5 * (r.t0 + r.t1), duration=r.duration)

    def linear_params(self, problem: Problem) -> tuple[Param, ...]:
        return (_amplitude("drift_beta", "N", AMPLITUDE_FACTOR * force_scale(problem)),)

    def location(self, params: Mapping[str, float], problem: Problem) -> dict:
        r = ranges(problem)
        return {"time_s": [r.t0, r.t1]}

    def explain(self, params: Mapping[str, float], problem: Problem) -> str:
        beta = float(params["drift_beta"])
        r = ranges(problem)
        word = "rises" if beta >= 0 else "falls"
        return (
            f"The friction level {word} by {_g(abs(beta))} N from the start to the end of the "
            f"{_g(r.duration)} s run (heating, lubricant or wear), so one fixed Coulomb level "
            f"cannot fit both ends."
        )


@dataclass(frozen=True)
class MassErrorCandidate(Candidate):
    """``mass_error``: the base model force scaled by ``1 − ε`` (:class:`MassError`), i.e. a
    moving mass of ``m/(1 − ε)`` instead of the given m. Linear ε (null 0), G = 1.
    Applicable when the spec has a fixed ``mass`` and no mass_error term yet."""

    effect: str = "mass_error"

    def term(self, problem: Problem) -> Term | None:
        return MassError(problem.model)

    def applicable(self, model: Model, spec: ParamSpec) -> bool:
        return (
            "mass" in spec
            and not spec["mass"].free
            and all(t.name != MassError.name for t in model.terms)
        )

    def linear_params(self, problem: Problem) -> tuple[Param, ...]:
        return MassError().parameters()

    def extend(
        self,
        model: Model,
        spec: ParamSpec,
        problem: Problem,
        nonlinear: Mapping[str, float] | None = None,
    ) -> tuple[Model, ParamSpec]:
        if not self.applicable(model, spec):
            raise FricjaxError(
                f"{where(_SOURCE, self.effect)}: needs a fixed 'mass' parameter in the spec"
            )
        if nonlinear:
            raise FricjaxError(
                f"{where(_SOURCE, self.effect)}: takes no nonlinear parameters, got "
                f"{sorted(nonlinear)[0]!r}"
            )
        term = MassError(model)
        return model.with_terms([term]), spec.extended(term.parameters())

    def location(self, params: Mapping[str, float], problem: Problem) -> dict:
        r = ranges(problem)
        return {"time_s": [r.t0, r.t1]}

    def explain(self, params: Mapping[str, float], problem: Problem) -> str:
        given = _mass(problem)
        m = given / (1.0 - float(params["mass_eps"]))
        return (
            f"The moving mass appears to be {_g(m)} kg rather than the given {_g(given)} kg "
            f"({100 * (m - given) / given:+.1f} %): the residual follows the acceleration "
            f"throughout the run."
        )


CATALOGUE: tuple[Candidate, ...] = (
    StribeckCandidate(),
    StribeckShapeCandidate(),
    AsymmetricCandidate(),
    QuadraticDragCandidate(),
    PreslidingCandidate(),
    PositionBumpCandidate(),
    PositionPeriodicCandidate(),
    ImpactCandidate(),
    ExtraHarmonicCandidate(),
    FrictionDriftCandidate(),
    MassErrorCandidate(),
)


def candidate(effect: str) -> Candidate:
    """The catalogue entry for ``effect`` (a name from the conventions)."""
    for c in CATALOGUE:
        if c.effect == effect:
            return c
    raise FricjaxError(
        f"{where(_SOURCE, 'effect')}: unknown effect {effect!r} "
        f"(known: {', '.join(c.effect for c in CATALOGUE)})"
    )
