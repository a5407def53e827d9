"""Recordings with one concealed catalogue effect each, for the diagnosis benchmark.

Every case is the paper-twin plant (seed eq. 5, :data:`fricjax.data.twin.PAPER_MODEL`) with
its parameters varied around :data:`~fricjax.data.twin.PAPER_TRUTH` (forces, amplitudes and
vs ×U(0.85, 1.15), phases ±U(0.2) rad, ω ×U(0.95, 1.05), all inside configs/paper.toml's
bounds; δ = 1, m = 45 kg), simulated from rest at 1 kHz with the stiction-aware RK4
(:func:`fricjax.model.simulate.simulate`, 16 sub-steps), plus ONE hidden effect of the
diagnosis catalogue (``fricjax.diagnose.catalogue``), plus white noise of std σ_x = 24 µm on
x. Null cases carry no effect.

Concealment. With ``s = x_effect(t) − x_base(t)`` [m, n] the effect's signature on the
displacement (same plant, same start, noise-free) and ``J = ∂x_sim/∂θ`` [n, 26] the
output-error sensitivity of the base model's 26 free parameters at the true base values
(``jax.jacfwd`` through ``simulate``), the concealment is

    c = ‖(I − P_J)·s‖ / σ_x      (P_J the orthogonal projector onto span J)

i.e. the part of the signature the base model cannot absorb, in noise standard deviations
(a whole-record norm: ‖·‖² sums over the n samples). ``--measure equation`` scales to the
equation-error counterpart instead, ``c_ee = ‖(I − P_{J_w})·W·δr‖/σ_x`` of
:class:`EquationErrorView` (δr the effect's change of the residual m·a − F* at the truth, W
the diagnosis' whitener, J_w the whitened base Jacobian): what the diagnosis' score test
sees, evaluated on the very recording the case writes. ``--measure refit`` scales to
``c_refit_ee`` (:func:`refit_concealment`): the same whitened norm after the base's 26
parameters are actually refitted (bounded least squares on the noise-free record) instead
of linearised at the truth; recorded for every case as ``concealment_ee_refit``. Where the
two differ the linearisation was wrong: measured at the c_ee = 5 amplitudes of the
committed run, asymmetric friction (dFc = 995 N) leaves 29.9 σ_x after the refit, while a
Gaussian Stribeck drop (A = 917 N) leaves 3.2 and the presliding lag (A = 586 N) 6.3.
``c_refit_ee(a)`` is not monotone in the amplitude for effects the base's own nonlinear
parameters can follow (a Stribeck drop of another shape: vs and Fs move), so the secant is
kept inside the smallest amplitude interval where c crosses the target once it has seen one
(quadratic drag on its 1 s plant: c = 11.5 at Cd = 922, 4.2 at Cd = 3269); where no
evaluation reaches the target the case is flagged ``reached = false``. All are recorded. The
amplitude is found by secant iterations on ``c(a)`` (nearly linear in a). The raw signature
is reported as ``rms(s)/σ_x`` (below 1: nothing shows by eye in x; effects the base absorbs
by moving its parameters far need raw signatures of hundreds of σ_x), and, as a check of the
linearisation behind c, ``concealment_refit`` (:func:`refit_check`, an upper bound). The
levels of one effect and replicate share plant and shape and differ in amplitude only.

How each effect is made (catalogue term names and parameters):

* a pointwise catalogue term ``T``: ``simulate(PAPER_MODEL.with_terms([T]), base ∪ effect)``;
* ``mass_error``: the plant simulated with ``m_true = m/(1 − ε)`` while the recording says
  ``m``; the catalogue's ``mass_eps`` is that ε (``m·a = (1 − ε)·F``);
* ``presliding_hysteresis`` (stateful LuGre/Dahl bristle, which the pointwise simulator
  refuses): ``F_f += A·(z − sgn v)`` with ``dz/dt = (sgn(v) − z)·|v|/ε``, integrated exactly
  per unit of travel (``z ← s + (z − s)·exp(−|Δx|/ε)``, s the direction travelled) on a
  16× finer grid, z₀ = 0 (unloaded bristle at rest). The force reads z as a table of time
  and the trajectory is a fixed point: simulate with z(t) from the previous path, recompute
  z on the new path, repeat until x moves by < 1e-13 m (a contraction for a small A, 3–6
  passes). Same simulator and sub-step as the base, so the signature holds no integrator
  error.

Files (atomic writes): ``OUT/CASE.h5`` (recording layout v1, no ``/truth``; CASE an opaque id
so neither name nor file reveals the effect), ``OUT/truth/CASE.json`` (effect, parameters,
target and achieved c, c_ee, rms(s)/σ_x, base parameters; diagnosis never reads it) and
``OUT/manifest.json``. Deterministic: same seed, options and sources → bit-identical
recordings; each truth file names its sources (:func:`source_digest`) and commit, and a run
whose sources change under it stops (:func:`check_sources`).

Usage::

    python benchmarks/concealed/generate.py --out out/concealed --levels 3,5,7,10 \\
        --lengths 0.272,1,2 --reps 1 --nulls 6 --seed 0
"""

from __future__ import annotations

import argparse
import hashlib
import itertools
import json
import math
import os
import sys
import tempfile
import time
import zlib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any, ClassVar, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

import fricjax  # noqa: F401  (float64 on; must precede jax use)
from fricjax.config import Config, load_config
from fricjax.data.recording import Recording, read_recording, write_recording
from fricjax.data.twin import DEFAULT_NOISE_STD, PAPER_MODEL, PAPER_TRUTH
from fricjax.diagnose.catalogue import CATALOGUE, FrictionDrift, candidate, ranges
from fricjax.errors import FricjaxError, where
from fricjax.model.simulate import simulate
from fricjax.model.system import Model
from fricjax.model.term import Signals, Term, sgn
from fricjax.params import Named, Param
from fricjax.problem import Problem, build_problem

ROOT = Path(__file__).resolve().parents[2]
CONFIG = ROOT / "configs" / "paper.toml"

#: Every catalogue effect (``unexplained`` is an outcome, not an effect one can hide).
EFFECTS: tuple[str, ...] = tuple(c.effect for c in CATALOGUE)
NULL = "none"
DEFAULT_LEVELS: tuple[float, ...] = (3.0, 5.0, 7.0, 10.0)
DEFAULT_LENGTHS: tuple[float, ...] = (0.272, 1.0, 2.0)
RATE = 1000.0  # Hz, the twin's
SUBSTEPS = 16  # RK4 sub-steps per sample, the twin's
FINE = 16  # presliding: fine grid factor (fine step = one RK4 sub-step)
# v2: the equation-error measures carry the diagnosis' stick/slip rule at rest (with_rest);
# v1 scaled them in the sliding-law residual, whose bias at breakaways inflated c for the
# friction laws (a v1 "c = 5" Stribeck drop is c ≈ 1 to the diagnosis of today)
FORMAT = "fricjax-concealed-v2"
MEASURES = ("output", "equation", "refit")

# Base-plant variation around the paper truth (each draw stays well inside the config box,
# which is [0.5, 1.5]× the truth for forces and [-π, π] for phases).
FORCE_SPREAD = 0.15
PHASE_SPREAD = 0.2  # rad
OMEGA_SPREAD = 0.05
_VARIED_FORCES = ("F0", "Fc", "Fv", "Fs", "vs", *(f"Fp_{i}" for i in range(1, 11)))

# Amplitude search: relative tolerance on c, evaluations at most, first trial magnitude
# (a fraction of the catalogue's amplitude bound), and the largest magnitude used (a
# fraction of that bound: the diagnosis refits inside the box, so the truth stays inside).
C_RTOL = 0.01
MAX_EVALS = 8
TRIAL_FRACTION = 0.02
MAX_FRACTION = 0.95
# Fixed point of the presliding trajectory: stop when x moves by less than this [m].
FIXED_POINT_TOL = 1e-13
FIXED_POINT_ITERS = 40
# Chord Gauss–Newton iterations of the nonlinear absorption check (refit_check).
REFIT_ITERS = 8
# Function evaluations of the bounded refit of refit_concealment (trust-region reflective
# from the linear absorbing step). Most effects settle in 10-20; asymmetric friction, which
# the base absorbs by walking its Stribeck and harmonic parameters far along a curved
# valley, does not: on the session-3 c = 10 case c_refit_ee was 9.45 after 40 evaluations,
# 7.36 after 150, 4.89 after 500 and 4.33 (converged) after 2000 = 6000.
EE_REFIT_ITERS = 2000
# Singular values of the column-normalised Jacobian below this fraction of the largest
# are treated as zero (the paper model has 26 well-separated directions; nothing is cut).
RANK_RTOL = 1e-10


class CaseSpec(NamedTuple):
    """What one case is: effect (or ``"none"``), target concealment (0 for nulls), record
    length [s] and replicate index."""

    effect: str
    level: float
    duration: float
    rep: int

    def case_id(self, seed: int, measure: str = "output") -> str:
        """Opaque, deterministic file stem (reveals nothing of the effect)."""
        key = f"{FORMAT}:{seed}:{self.effect}:{self.level:g}:{self.duration:g}:{self.rep}"
        if measure != "output":
            key += f":{measure}"
        return "c" + hashlib.sha256(key.encode()).hexdigest()[:10]


def case_specs(
    effects: Sequence[str],
    levels: Sequence[float],
    lengths: Sequence[float],
    reps: int,
    nulls: int,
) -> list[CaseSpec]:
    """Every (effect, level, length, rep) combination, then ``nulls`` null cases per length.

    Ordered by length first so a runner that walks the list compiles each length once.
    """
    unknown = [e for e in effects if e not in EFFECTS]
    if unknown:
        raise FricjaxError(
            f"{where('generate', '--cases')}: unknown effect {unknown[0]!r} "
            f"(known: {', '.join(EFFECTS)}, {NULL})"
        )
    out: list[CaseSpec] = []
    for duration in lengths:
        for effect in effects:
            for level in levels:
                out.extend(CaseSpec(effect, float(level), float(duration), r) for r in range(reps))
        out.extend(CaseSpec(NULL, 0.0, float(duration), r) for r in range(nulls))
    return out


def case_rngs(spec: CaseSpec, seed: int) -> tuple[np.random.Generator, np.random.Generator]:
    """Two PCG64 generators, so a case does not depend on the list it is in:

    * the plant's: base variation and effect shape, keyed on (seed, effect, length, rep) —
      the levels of one effect and replicate share plant and shape and differ only in the
      amplitude (a dose-response), and share one Jacobian;
    * the noise's, keyed on the whole case (level included).
    """
    plant = zlib.crc32(f"plant:{spec.effect}:{spec.duration:g}:{spec.rep}".encode())
    noise = zlib.crc32(f"noise:{spec.effect}:{spec.level:g}:{spec.duration:g}:{spec.rep}".encode())
    return (
        np.random.default_rng(np.random.SeedSequence([seed, plant])),
        np.random.default_rng(np.random.SeedSequence([seed, noise])),
    )


# -- the base plant --------------------------------------------------------------------------
def vary_base(rng: np.random.Generator, config: Config) -> dict[str, float]:
    """Paper truth with forces/amplitudes/vs ×U(0.85, 1.15), phases +U(−0.2, 0.2) rad and
    ω ×U(0.95, 1.05); δ and the mass unchanged. Checked against the config's bounds."""
    base = dict(PAPER_TRUTH)
    for name in _VARIED_FORCES:
        base[name] *= rng.uniform(1.0 - FORCE_SPREAD, 1.0 + FORCE_SPREAD)
    for i in range(1, 11):
        base[f"phi_{i}"] += rng.uniform(-PHASE_SPREAD, PHASE_SPREAD)
    base["omega"] *= rng.uniform(1.0 - OMEGA_SPREAD, 1.0 + OMEGA_SPREAD)
    for q in config.spec.free:
        if not q.lower < base[q.name] < q.upper:
            raise FricjaxError(
                f"{where(config.source, f'[params].{q.name}')}: varied truth {base[q.name]:g} "
                f"outside [{q.lower:g}, {q.upper:g}]"
            )
    return {k: float(v) for k, v in base.items()}


def _jnp_params(p: Mapping[str, Any]) -> dict[str, Array]:
    return {k: jnp.asarray(v, dtype=jnp.float64) for k, v in p.items()}


def simulate_x(
    model: Model, p: Mapping[str, Any], t: Float[np.ndarray, " n"], substeps: int
) -> tuple[np.ndarray, np.ndarray]:
    """Positions and velocities [n] from rest (x = v = 0 at t[0]): jitted ``simulate``."""
    traj = simulate(model, _jnp_params(p), jnp.asarray(t), 0.0, 0.0, substeps=substeps)
    return np.asarray(traj.x), np.asarray(traj.v)


@partial(jax.jit, static_argnames=("names", "substeps"))
def _x_jacobian(
    theta: Float[Array, " d"],
    fixed: dict[str, Array],
    t: Float[Array, " n"],
    names: tuple[str, ...],
    substeps: int,
) -> Float[Array, "n d"]:
    def x_of(th: Float[Array, " d"]) -> Float[Array, " n"]:
        p = {**fixed, **{k: th[i] for i, k in enumerate(names)}}
        return simulate(PAPER_MODEL, p, t, 0.0, 0.0, substeps=substeps).x

    return jax.jacfwd(x_of)(theta)


_JACOBIANS: dict[tuple, np.ndarray] = {}


def base_jacobian(
    base: Mapping[str, float], t: Float[np.ndarray, " n"], config: Config, substeps: int
) -> np.ndarray:
    """``J = ∂x_sim/∂θ`` [n, d] at the base truth, θ the config's free parameters (d = 26).

    Cached for the last few bases (the levels of one effect share their plant)."""
    names = config.spec.free_names
    key = (tuple(sorted(base.items())), names, t.shape[0], float(t[1] - t[0]), substeps)
    if key not in _JACOBIANS:
        theta = jnp.asarray([base[k] for k in names])
        fixed = _jnp_params({k: v for k, v in base.items() if k not in names})
        if len(_JACOBIANS) >= 4:
            _JACOBIANS.pop(next(iter(_JACOBIANS)))
        _JACOBIANS[key] = np.asarray(_x_jacobian(theta, fixed, jnp.asarray(t), names, substeps))
    return _JACOBIANS[key]


def absorber(jac: Float[np.ndarray, "n d"]) -> np.ndarray:
    """Orthonormal basis U [n, r] of span J (columns normalised first: parameters in N and in
    rad differ by 10⁴ in scale, which must not decide the rank)."""
    norms = np.linalg.norm(jac, axis=0)
    jn = jac / np.where(norms > 0, norms, 1.0)
    u, sv, _ = np.linalg.svd(jn, full_matrices=False)
    return u[:, sv > RANK_RTOL * sv[0]]


def concealment(s: Float[np.ndarray, " n"], basis: Float[np.ndarray, "n r"], sigma: float) -> float:
    """``c = ‖(I − P_J)·s‖/σ_x`` with ``P_J = U·Uᵀ`` (``basis`` = U from :func:`absorber`)."""
    perp = s - basis @ (basis.T @ s)
    return float(np.linalg.norm(perp) / sigma)


def refit_check(
    base: Mapping[str, float],
    x_effect: Float[np.ndarray, " n"],
    jac: Float[np.ndarray, "n d"],
    t: Float[np.ndarray, " n"],
    config: Config,
    substeps: int,
    start: Float[np.ndarray, " d"] | None = None,
) -> float:
    """``min_k ‖x_effect − x_sim(θ_k)‖`` [m] over the truth θ₀, the start ``θ₀ + start``
    (the equation-error absorption of :meth:`EquationErrorView.absorbing_step`) and chord
    Gauss–Newton iterates ``θ_{k+1} = clip(θ_k + J⁺·(x_effect − x_sim(θ_k)))`` from the
    better of the two, J fixed at θ₀, clipped to the config's box (the base fit cannot
    leave it).

    A nonlinear (upper-bound) counterpart of ``c·σ_x``: close to it where the linearisation
    behind c holds, larger where the signature is too big for it, or where absorbing it
    would need parameters outside the box."""
    names = config.spec.free_names
    lower, upper = config.spec.lower, config.spec.upper
    theta = np.array([base[k] for k in names])
    pinv = np.linalg.pinv(jac, rcond=RANK_RTOL)
    x_fit, _ = simulate_x(PAPER_MODEL, base, t, substeps)
    best = float(np.linalg.norm(x_effect - x_fit))  # θ₀ itself: nothing absorbed
    if start is not None:
        moved_theta = np.clip(theta + start, lower, upper)
        moved = {**base, **dict(zip(names, map(float, moved_theta), strict=True))}
        x_moved, _ = simulate_x(PAPER_MODEL, moved, t, substeps)
        err = float(np.linalg.norm(x_effect - x_moved))
        if err < best:
            best, theta, x_fit = err, moved_theta, x_moved
    for _ in range(REFIT_ITERS):
        theta = np.clip(theta + pinv @ (x_effect - x_fit), lower, upper)
        moved = {**base, **dict(zip(names, map(float, theta), strict=True))}
        x_fit, _ = simulate_x(PAPER_MODEL, moved, t, substeps)
        err = float(np.linalg.norm(x_effect - x_fit))
        if not err < best * (1.0 - 1e-3):  # diverging or stalled
            best = min(best, err)
            break
        best = err
    return best


def with_true_term(
    problem: Problem, effect: str, base: Mapping[str, float], params: Mapping[str, float]
) -> tuple[Problem, np.ndarray]:
    """``problem`` extended by the catalogue term of ``effect`` at its shape in ``params``,
    and its parameter vector [d] at ``base`` + ``params``."""
    cand = candidate(effect)
    nl = {q.name for q in cand.nonlinear_params(problem)}
    shape = {k: float(v) for k, v in params.items() if k in nl}
    ext = cand.extend_problem(problem, shape or None)
    named = {**base, **params}
    return ext, ext.spec.flatten({k: v for k, v in named.items() if k in ext.spec})


class EquationErrorView:
    """What the diagnosis' score test sees of an effect on one recording.

    ``c_ee(params) = ‖(I − P_{J_w})·W·δr‖/σ_x`` [1]: ``δr`` [n] the change of the
    equation-error residual ``m·a − F*`` [N] that the catalogue term with ``params`` makes
    at the true base parameters on the recording's preprocessed signals, ``W`` the
    diagnosis' whitener (:func:`fricjax.diagnose.locate.default_whitener`) at the true base
    (whitened noise ~ N(0, σ_x²·I)), ``J_w`` [M, 26] the whitened base Jacobian. ``c_ee²`` is
    the noncentrality of the score test of the effect at its true shape. Exactly linear in
    the amplitude for every effect but ``stribeck_shape`` (nonlinear in dδ).
    """

    def __init__(self, problem: Problem, base: Mapping[str, float], sigma: float) -> None:
        from fricjax.diagnose.locate import default_whitener, jacobian
        from fricjax.diagnose.run import with_rest

        self.base, self.sigma = dict(base), sigma
        self.theta0 = problem.theta(self.base)
        # the diagnosis marks the samples at rest and applies the stick/slip rule there;
        # the truth stands in for the identified parameters it marks them at
        problem = with_rest(problem, self.theta0)
        self.problem = problem
        self.r0 = problem.residual(self.theta0)
        self.wh = default_whitener(problem, self.theta0)
        jw = self.wh(jacobian(problem, self.theta0))
        self.jw = jw
        norms = np.linalg.norm(jw, axis=0)
        u, sv, _ = np.linalg.svd(jw / np.where(norms > 0, norms, 1.0), full_matrices=False)
        self.u = u[:, sv > RANK_RTOL * sv[0]]

    def signature(self, effect: str, params: Mapping[str, float]) -> np.ndarray:
        """``δr`` [n] in newtons."""
        ext, theta = with_true_term(self.problem, effect, self.base, params)
        return ext.residual(theta) - self.r0

    def absorbing_step(self, effect: str, params: Mapping[str, float]) -> np.ndarray:
        """``δθ`` [26] minimising ``‖W·(δr − J·δθ)‖``: how the base parameters would absorb the
        effect in the diagnosis' fit (linear least squares, whitened)."""
        z = self.wh(self.signature(effect, params))
        delta, *_ = np.linalg.lstsq(self.jw, z, rcond=None)
        return delta

    def concealment(self, effect: str, params: Mapping[str, float]) -> float:
        z = self.wh(self.signature(effect, params))
        return float(np.linalg.norm(z - self.u @ (self.u.T @ z)) / self.sigma)


def refit_concealment(
    view: EquationErrorView,
    problem_effect: Problem,
    floor: Float[np.ndarray, " n"],
    start: Float[np.ndarray, " d"],
) -> tuple[float, np.ndarray]:
    """``c_refit_ee = min_{θ ∈ box} ‖W·(r_e(θ) − r_floor)‖/σ_x`` [1], and θ̂ [d].

    ``r_e`` [n] the equation-error residual of the *base* model on the noise-free effect
    record (``problem_effect``), ``r_floor`` [n] the same residual of the noise-free base
    record at the truth (the preprocessing's own bias, present in nulls too), W the
    diagnosis' whitener (``view.wh``), the box the config's (the diagnosis' base fit cannot
    leave it). This is :meth:`EquationErrorView.concealment` with the base parameters
    actually refitted instead of linearised at the truth: what the base model cannot absorb,
    in the diagnosis' metric. The two agree for small signatures; for larger ones the linear
    projection often "absorbs" by moving parameters out of the box or far into the
    nonlinear range (a 10 N presliding lag on the paper twin asks Fc to move by +52 N, out
    of its box), and then only this one tells what the diagnosis will face. Bounded
    least squares (scipy ``least_squares``, trust-region reflective, Jacobian by
    ``jax.jacfwd``) from the better of θ₀ and ``θ₀ + start`` (the linear absorbing step,
    clipped into the box).
    """
    return bounded_refit(view, problem_effect, floor, [view.theta0, view.theta0 + start])


class RecordConcealment(NamedTuple):
    """A written case's refit concealment, recomputed from its record alone."""

    c: float  # [1] c_refit_ee
    theta: np.ndarray  # [26] the base refitted to the noise-free record
    view: EquationErrorView  # at the true base, rest mask of the noisy recording
    problem: Problem  # the noise-free record, samples at rest marked as in ``view``
    floor: np.ndarray  # [n] N, the noise-free base record's residual at the truth


def record_concealment(
    truth: Mapping[str, Any], recording: Recording, config: Config
) -> RecordConcealment:
    """c_refit_ee of a written case (:func:`refit_concealment`) from its record alone: the
    noise regenerated from the case's seed and subtracted, the base record simulated from
    the truth, both with the samples at rest that the noisy recording marks. Equals the
    truth file's ``concealment`` when the record is the one :func:`make_case` wrote."""
    spec = CaseSpec(truth["effect"], truth["level"], truth["duration_s"], truth["rep"])
    if spec.case_id(truth["seed"], truth["measure"]) != truth["case"]:
        # the noise is regenerated from the spec; another spec would subtract other noise
        raise ValueError(f"truth of {truth['case']}: its fields give another case id")
    _, rng_noise = case_rngs(spec, truth["seed"])
    noise = rng_noise.normal(0.0, truth["noise_std_m"], truth["n"])
    t = np.asarray(recording.t)
    x_base, _ = simulate_x(PAPER_MODEL, truth["base"], t, truth["substeps"])
    view = EquationErrorView(build_problem(recording, config), truth["base"], truth["noise_std_m"])

    def marked(x: np.ndarray) -> Problem:
        rec = Recording(t=t, x=x, mass=recording.mass)
        return replace(build_problem(rec, config), rest=view.problem.rest)

    floor = np.asarray(marked(x_base).residual(view.theta0))
    clean = marked(np.asarray(recording.x) - noise)
    step = view.absorbing_step(truth["effect"], truth["params"])
    c, theta = refit_concealment(view, clean, floor, step)
    return RecordConcealment(c, theta, view, clean, floor)


def bounded_refit(
    view: EquationErrorView,
    problem: Problem,
    floor: Float[np.ndarray, " n"],
    starts: Sequence[Float[np.ndarray, " d"]],
) -> tuple[float, np.ndarray]:
    """``min_{θ ∈ box} ‖W·(r(θ) − r_floor)‖/σ_x`` [1] and θ̂ [d] for ``problem``'s residual
    ``r`` [n] in newtons (W, σ_x: ``view``'s; the box: ``problem``'s), by bounded least
    squares from the best of ``starts`` (clipped into the box)."""
    from scipy.optimize import least_squares

    from fricjax.diagnose.locate import jacobian

    lower, upper = problem.spec.lower, problem.spec.upper
    width = upper - lower
    inner_lo, inner_hi = lower + 1e-9 * width, upper - 1e-9 * width

    def whitened(theta: np.ndarray) -> np.ndarray:
        return view.wh(np.asarray(problem.residual(theta)) - floor) / view.sigma

    def jac(theta: np.ndarray) -> np.ndarray:
        return view.wh(jacobian(problem, theta)) / view.sigma

    points = [np.clip(np.asarray(x, dtype=np.float64), inner_lo, inner_hi) for x in starts]
    # ties go to the earlier start (the refit concealment lists θ₀ before its step)
    sizes = [float(z @ z) for z in map(whitened, points)]
    x0 = points[int(np.argmin(sizes))]
    sol = least_squares(
        whitened,
        x0,
        jac=jac,
        bounds=(lower, upper),
        method="trf",
        x_scale="jac",
        max_nfev=EE_REFIT_ITERS,
    )
    return float(np.linalg.norm(sol.fun)), np.asarray(sol.x)


# -- presliding: the stateful bristle by fixed point ------------------------------------------
@dataclass(frozen=True)
class TabulatedBristle(Term):
    """``F_f = A·(z(t) − sgn v)`` [N], z read from a table of time (linear interpolation).

    The catalogue's :class:`~fricjax.diagnose.catalogue.PreslidingHysteresis` with the bristle
    state given as a function of time, so the pointwise simulator can integrate it; the
    generator makes z consistent with the path by fixed-point iteration. Parameters in p:
    ``presl_A`` [N], ``presl_tgrid`` [s] and ``presl_ztab`` [1], both arrays [N_tab].
    """

    name: ClassVar[str] = "tabulated_bristle"
    role: ClassVar = "friction"

    def parameters(self) -> tuple[Param, ...]:
        return (
            Param("presl_A", "N", -1e4, 1e4, 0.0, null=0.0),
            Param("presl_tgrid", "s", -1e9, 1e9, 0.0),
            Param("presl_ztab", "1", -1.0, 1.0, 0.0),
        )

    def _z(self, p: Named, s: Signals) -> Float[Array, "..."]:
        return jnp.interp(s.t, p["presl_tgrid"], p["presl_ztab"])

    def force(self, p: Named, s: Signals) -> Float[Array, "..."]:
        return p["presl_A"] * (self._z(p, s) - sgn(s.v))

    def static(self, p: Named, s: Signals, direction: Float[Array, "..."]) -> Float[Array, "..."]:
        return p["presl_A"] * (self._z(p, s) - direction) + jnp.zeros_like(s.t * direction)


@jax.jit
def bristle_path(x: Float[Array, " n"], eps: Float[Array, ""]) -> Float[Array, " n"]:
    """Bristle state along a path: ``dz/dx = (s − z)/ε`` per unit of travel, exact per step,
    ``z_{k+1} = s_k + (z_k − s_k)·exp(−|x_{k+1} − x_k|/ε)``, ``s_k = sgn(x_{k+1} − x_k)``,
    ``z_0 = 0``. x [m] shape [n]; ε [m]; returns z [n] in [−1, 1]."""
    dx = jnp.diff(x)

    def step(z: Float[Array, ""], d: Float[Array, ""]) -> tuple[Array, Array]:
        s = jnp.sign(d)
        z_next = s + (z - s) * jnp.exp(-jnp.abs(d) / eps)
        return z_next, z_next

    _, zs = jax.lax.scan(step, jnp.zeros((), dtype=x.dtype), dx)
    return jnp.concatenate([jnp.zeros((1,), dtype=x.dtype), zs])


_PRESLIDING: dict[str, Any] = {}  # the base path and the last fixed point of one plant


def presliding_x(
    base: Mapping[str, float],
    amp: float,
    eps: float,
    t: Float[np.ndarray, " n"],
    substeps: int,
) -> tuple[np.ndarray, np.ndarray]:
    """(x_base, x_effect) [n] of the plant with the LuGre lag ``A·(z − sgn v)``, both
    simulated on the fine grid (``FINE``× the rate, one RK4 sub-step per fine sample, the
    same step h as the base) and sampled back onto ``t``."""
    fine = max(1, min(FINE, substeps))
    sub = max(1, substeps // fine)
    n = t.shape[0]
    dt = float(t[1] - t[0])
    tf = t[0] + np.arange((n - 1) * fine + 1, dtype=np.float64) * (dt / fine)
    key = (tuple(sorted(base.items())), eps, n, dt, substeps)
    if _PRESLIDING.get("key") != key:
        xb, _ = simulate_x(PAPER_MODEL, base, tf, sub)
        _PRESLIDING.update(key=key, base=xb, last=xb)
    xb = _PRESLIDING["base"]
    model = PAPER_MODEL.with_terms([TabulatedBristle()])
    # warm start from the last amplitude's path (the secant calls this repeatedly)
    xf = _PRESLIDING["last"]
    for _ in range(FIXED_POINT_ITERS):
        z = np.asarray(bristle_path(jnp.asarray(xf), jnp.asarray(eps)))
        p = {**base, "presl_A": amp, "presl_tgrid": tf, "presl_ztab": z}
        x_new, _ = simulate_x(model, p, tf, sub)
        moved = float(np.max(np.abs(x_new - xf)))
        xf = x_new
        if moved < FIXED_POINT_TOL:
            break
    else:
        raise FricjaxError(
            f"{where('generate', 'presliding_hysteresis')}: fixed point did not converge "
            f"(A = {amp:g} N, eps = {eps:g} m; last move {moved:g} m)"
        )
    _PRESLIDING["last"] = xf
    return xb[::fine], xf[::fine]


# -- effect draws ----------------------------------------------------------------------------
@dataclass(frozen=True)
class EffectDraw:
    """One hidden effect: its shape (nonlinear) parameters and the direction of its linear
    parameters; ``params(a)`` scales the direction by the magnitude ``a`` (≥ 0).

    term: the catalogue term appended to the base (None for mass_error and presliding,
    which are simulated specially). a_max: the largest magnitude inside the catalogue's
    amplitude bounds for this recording (see ``MAX_FRACTION``).
    """

    effect: str
    term: Term | None
    shape: dict[str, float]
    direction: dict[str, float]
    a_max: float

    def params(self, a: float) -> dict[str, float]:
        return {**self.shape, **{k: a * v for k, v in self.direction.items()}}


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _sign(rng: np.random.Generator) -> float:
    return 1.0 if rng.uniform() < 0.5 else -1.0


def _a_max(effect: str, problem: Problem, direction: Mapping[str, float]) -> float:
    """Largest ``a`` with every ``a·direction`` inside the candidate's amplitude bounds."""
    limit = math.inf
    for q in candidate(effect).linear_params(problem):
        d = direction.get(q.name, 0.0)
        if d > 0:
            limit = min(limit, q.upper / d)
        elif d < 0:
            limit = min(limit, q.lower / d)
    return MAX_FRACTION * limit


def draw_effect(
    effect: str, rng: np.random.Generator, problem: Problem, base: Mapping[str, float]
) -> EffectDraw:
    """Random but sensible shape of ``effect`` on this recording (inside the catalogue's
    grid ranges, ``candidate(effect).nonlinear_params(problem)``)."""
    r = ranges(problem)
    bounds = {q.name: (q.lower, q.upper) for q in candidate(effect).nonlinear_params(problem)}

    def inside(name: str, value: float) -> float:
        lo, hi = bounds[name]
        if not lo <= value <= hi:
            raise FricjaxError(
                f"{where('generate', effect)}: drawn {name} = {value:g} outside the "
                f"catalogue's range [{lo:g}, {hi:g}]"
            )
        return value

    term: Term | None
    shape: dict[str, float] = {}
    if effect == "stribeck":
        shape["stribeck_vst"] = inside("stribeck_vst", _log_uniform(rng, 0.03, 0.3) * r.v_max)
        direction = {"stribeck_A": 1.0}
    elif effect == "stribeck_shape":
        direction = {"shape_ddelta": _sign(rng)}
    elif effect == "asymmetric_friction":
        sign, ratio = _sign(rng), rng.uniform(-0.5, 1.0)
        # ratio: viscous excess at the mean speed relative to the Coulomb excess
        direction = {"asym_dFc": sign, "asym_dFv": sign * ratio / r.v_mean}
    elif effect == "quadratic_drag":
        direction = {"drag_Cd": 1.0}
    elif effect == "presliding_hysteresis":
        lo, hi = bounds["presl_eps"]
        eps = _log_uniform(rng, max(1e-4, 2.0 * lo), min(2e-3, 0.5 * hi))
        shape["presl_eps"] = inside("presl_eps", eps)
        direction = {"presl_A": 1.0}
    elif effect == "position_bump":
        x0 = rng.uniform(r.x_min + 0.15 * r.x_range, r.x_max - 0.15 * r.x_range)
        shape["bump_x0"] = inside("bump_x0", x0)
        shape["bump_w"] = inside("bump_w", _log_uniform(rng, 0.02, 0.1) * r.x_range)
        direction = {"bump_A": 1.0}
    elif effect == "position_periodic":
        lo, hi = bounds["per_lambda"]  # [λ_lo/1.5, 1.5·λ_hi]: stay inside [λ_lo, λ_hi]
        shape["per_lambda"] = inside("per_lambda", _log_uniform(rng, 1.8 * lo, hi / 1.8))
        phase = rng.uniform(0.0, 2.0 * math.pi)
        direction = {"per_A": math.cos(phase), "per_B": math.sin(phase)}
    elif effect == "impact":
        shape["impact_t0"] = inside(
            "impact_t0", rng.uniform(r.t0 + 0.1 * r.duration, r.t1 - 0.1 * r.duration)
        )
        w_lo = max(2.0 * r.dt, 1.0 / (2.0 * math.pi * r.f_cut))
        shape["impact_w"] = inside("impact_w", _log_uniform(rng, w_lo, 3.0 * w_lo))
        direction = {"impact_A": _sign(rng)}
    elif effect == "extra_harmonic":
        f_drive = base["omega"] / (2.0 * math.pi)
        gap = max(1.0 / r.duration, 1.0)  # Hz away from every drive harmonic
        f_lo, f_hi = max(2.0, 1.0 / r.duration), 0.8 * r.f_cut
        for _ in range(1000):
            f = rng.uniform(f_lo, f_hi)
            if min(abs(f - k * f_drive) for k in range(1, 11)) > gap:
                break
        shape["harm_f"] = inside("harm_f", f)
        phase = rng.uniform(0.0, 2.0 * math.pi)
        direction = {"harm_A": math.cos(phase), "harm_B": math.sin(phase)}
    elif effect == "friction_drift":
        direction = {"drift_beta": _sign(rng)}
    elif effect == "mass_error":
        direction = {"mass_eps": _sign(rng)}
    else:
        raise FricjaxError(f"{where('generate', 'effect')}: unknown effect {effect!r}")
    if effect == "friction_drift":
        term = FrictionDrift(t_mid=0.5 * (r.t0 + r.t1), duration=r.duration)
    elif effect in ("mass_error", "presliding_hysteresis"):
        term = None
    else:
        term = candidate(effect).term(problem)
    return EffectDraw(effect, term, shape, direction, _a_max(effect, problem, direction))


def effect_x(
    draw: EffectDraw,
    base: Mapping[str, float],
    a: float,
    t: Float[np.ndarray, " n"],
    x_base: Float[np.ndarray, " n"],
    substeps: int,
) -> tuple[np.ndarray, np.ndarray]:
    """(x_base, x_effect) [n], noise-free, for magnitude ``a``; x_base is the caller's
    except for presliding, whose base comes from the same fine grid as its effect."""
    p = draw.params(a)
    if draw.effect == "mass_error":
        truth = {**base, "mass": base["mass"] / (1.0 - p["mass_eps"])}
        return x_base, simulate_x(PAPER_MODEL, truth, t, substeps)[0]
    if draw.effect == "presliding_hysteresis":
        return presliding_x(base, p["presl_A"], p["presl_eps"], t, substeps)
    assert draw.term is not None
    model = PAPER_MODEL.with_terms([draw.term])
    return x_base, simulate_x(model, {**base, **p}, t, substeps)[0]


class Scaled(NamedTuple):
    """Outcome of :func:`scale_to`: magnitude, achieved c, the signature s [n] and x_effect,
    evaluations used, whether the target was reached within ``C_RTOL``."""

    a: float
    c: float
    s: np.ndarray
    x: np.ndarray
    evals: int
    reached: bool


def _bracket(
    pts: Sequence[tuple[float, float]], target: float
) -> tuple[tuple[float, float] | None, tuple[float, float] | None]:
    """The smallest-amplitude pair of neighbouring evaluations (a, c), sorted by a, whose c
    straddle ``target`` (below, above), or (None, None)."""
    ordered = sorted(pts)
    for lo, hi in itertools.pairwise(ordered):
        if lo[1] < target < hi[1]:
            return lo, hi
    return None, None


def scale_to(target: float, a0: float, a_max: float, c_of: Callable[[float], tuple]) -> Scaled:
    """Secant iterations on ``c(a) = target`` from ``(0, 0)`` and ``a0``, a ∈ (0, a_max].

    ``c_of(a)`` returns (c, s, x_effect). The first step is the linear guess a0·target/c(a0);
    later ones the secant through the last two evaluations, clipped to (0, a_max] — unless
    the evaluations already bracket the target and the secant step leaves the
    smallest-amplitude bracket: then regula falsi inside it (:func:`_bracket`).
    """
    pts: list[tuple[float, float]] = [(0.0, 0.0)]
    a = a0
    best: Scaled | None = None
    for k in range(1, MAX_EVALS + 1):
        c, s, x = c_of(a)
        cand = Scaled(a, c, s, x, k, abs(c - target) <= C_RTOL * target)
        if best is None or abs(c - target) < abs(best.c - target):
            best = cand
        if cand.reached:
            return cand
        pts.append((a, c))
        (a1, c1), (a2, c2) = pts[-2], pts[-1]
        a_next = math.nan if c2 == c1 else a2 + (target - c2) * (a2 - a1) / (c2 - c1)
        lo, hi = _bracket(pts, target)
        if lo is not None and hi is not None and not lo[0] < a_next < hi[0]:
            # c(a) is not monotone for effects the base's nonlinear parameters follow: a
            # secant step may leave the smallest amplitude interval where c crosses the
            # target and never come back; regula falsi inside that interval cannot
            a_next = lo[0] + (target - lo[1]) * (hi[0] - lo[0]) / (hi[1] - lo[1])
        elif c2 == c1:
            break
        if not math.isfinite(a_next) or a_next <= 0:
            a_next = 0.5 * a2
        if a_next > a_max:
            if a2 >= a_max:
                break  # the largest allowed magnitude does not reach the target
            a_next = a_max
        a = a_next
    assert best is not None
    return best


# -- one case --------------------------------------------------------------------------------
@dataclass
class Case:
    """A generated case: the recording (no truth inside) and its truth (separate file)."""

    case_id: str
    spec: CaseSpec
    recording: Recording
    truth: dict[str, Any]


def make_case(
    spec: CaseSpec,
    seed: int,
    config: Config,
    *,
    noise_std: float = DEFAULT_NOISE_STD,
    substeps: int = SUBSTEPS,
    measure: str = "output",
) -> Case:
    """Simulate one case (see the module docstring). Deterministic in (spec, seed, measure).

    ``measure`` picks the concealment the amplitude is scaled to: ``"output"`` (c of the
    module docstring, on the displacement) or ``"equation"`` (``c_ee`` of
    :class:`EquationErrorView`, what the diagnosis' score test sees). Both are recorded.
    """
    if measure not in MEASURES:
        raise FricjaxError(
            f"{where('generate', '--measure')}: unknown {measure!r} (known: {', '.join(MEASURES)})"
        )
    t_start = time.perf_counter()
    _PRESLIDING.clear()  # warm starts only within a case, so a case never depends on the list
    rng, rng_noise = case_rngs(spec, seed)
    case_id = spec.case_id(seed, measure)
    base = vary_base(rng, config)
    n = round(spec.duration * RATE)
    t = np.arange(n, dtype=np.float64) / RATE
    noise = rng_noise.normal(0.0, noise_std, n)
    x_base, _ = simulate_x(PAPER_MODEL, base, t, substeps)
    given_mass = float(base["mass"])
    truth: dict[str, Any] = {
        "format": FORMAT,
        "case": case_id,
        "effect": spec.effect,
        "level": spec.level,
        "duration_s": spec.duration,
        "rep": spec.rep,
        "seed": seed,
        "n": n,
        "rate_hz": RATE,
        "noise_std_m": noise_std,
        "substeps": substeps,
        "measure": measure,
        "base": base,
        "config": str(CONFIG.relative_to(ROOT)) if CONFIG.is_relative_to(ROOT) else str(CONFIG),
        # which code made the record: a case is reproducible from these and its spec
        "sources": source_digest(),
        "git_commit": git_commit(),
    }
    if spec.effect == NULL:
        x_clean = x_base
        truth.update(
            params={},
            concealment=0.0,
            concealment_output=0.0,
            concealment_ee=0.0,
            raw_rms_over_sigma=0.0,
            reached=True,
        )
    else:
        rec_base = Recording(t=t, x=x_base + noise, mass=given_mass, name=case_id)
        problem = build_problem(rec_base, config)
        draw = draw_effect(spec.effect, rng, problem, base)
        jac = base_jacobian(base, t, config, substeps)
        basis = absorber(jac)
        a0 = TRIAL_FRACTION * draw.a_max / MAX_FRACTION

        def c_output(a: float) -> tuple[float, np.ndarray, np.ndarray]:
            xb, xe = effect_x(draw, base, a, t, x_base, substeps)
            s = xe - xb
            return concealment(s, basis, noise_std), s, xe

        views: dict[float, EquationErrorView] = {}

        def view_at(a: float, x_effect: np.ndarray) -> EquationErrorView:
            """The diagnosis' view of the recording the effect of magnitude a makes."""
            if a not in views:
                rec = Recording(t=t, x=x_effect + noise, mass=given_mass, name=case_id)
                views.clear()
                views[a] = EquationErrorView(build_problem(rec, config), base, noise_std)
            return views[a]

        def c_equation(a: float) -> tuple[float, np.ndarray, np.ndarray]:
            xb, xe = effect_x(draw, base, a, t, x_base, substeps)
            return view_at(a, xe).concealment(spec.effect, draw.params(a)), xe - xb, xe

        def c_refit(a: float) -> tuple[float, np.ndarray, np.ndarray]:
            xb, xe = effect_x(draw, base, a, t, x_base, substeps)
            view = view_at(a, xe)
            # The floor with this magnitude's own rest mask: the mask moves with the effect
            # (a 1 s quadratic drag: 143 samples at rest at the first trial, 714 at its
            # level), and a floor kept from the first trial put the stick/slip rule's bias
            # at the samples whose mask changed into c (4.33 there against 1.88).
            rest = view.problem.rest
            clean = Recording(t=t, x=xb, mass=given_mass, name=case_id)
            floor = np.asarray(
                replace(build_problem(clean, config), rest=rest).residual(view.theta0)
            )
            clean_effect = Recording(t=t, x=xe, mass=given_mass, name=case_id)
            c, _ = refit_concealment(
                view,
                replace(build_problem(clean_effect, config), rest=rest),
                floor,
                view.absorbing_step(spec.effect, draw.params(a)),
            )
            return c, xe - xb, xe

        if measure == "output":
            out = scale_to(spec.level, a0, draw.a_max, c_output)
            c_out = out.c
        elif measure == "equation":
            out = scale_to(spec.level, a0, draw.a_max, c_equation)
            c_out = concealment(out.s, basis, noise_std)
        else:
            out = scale_to(spec.level, a0, draw.a_max, c_refit)
            c_out = concealment(out.s, basis, noise_std)
        sig, x_clean = out.s, out.x
        params = draw.params(out.a)
        final_view = view_at(out.a, x_clean)
        truth.update(
            params=params,
            concealment=out.c,
            concealment_output=c_out,
            concealment_ee=final_view.concealment(spec.effect, params),
            concealment_ee_refit=out.c if measure == "refit" else c_refit(out.a)[0],
            reached=out.reached,
            raw_rms_over_sigma=float(np.sqrt(np.mean(sig**2)) / noise_std),
            absorbed_fraction=float(1.0 - (c_out * noise_std) ** 2 / max(float(sig @ sig), 1e-300)),
            peak_signature_m=float(np.max(np.abs(sig))),
            magnitude=out.a,
            magnitude_max=draw.a_max,
            secant_evals=out.evals,
            absorber_rank=int(basis.shape[1]),
            concealment_refit=refit_check(
                base,
                x_clean,
                jac,
                t,
                config,
                substeps,
                final_view.absorbing_step(spec.effect, params),
            )
            / noise_std,
        )
        if spec.effect == "friction_drift":
            assert isinstance(draw.term, FrictionDrift)
            truth["term"] = {"t_mid": draw.term.t_mid, "duration": draw.term.duration}
        if spec.effect == "mass_error":
            truth["mass_true_kg"] = given_mass / (1.0 - params["mass_eps"])
    x = x_clean + noise
    rec = Recording(
        t=t,
        x=x,
        mass=given_mass,
        name=case_id,
        source="benchmarks/concealed/generate.py (paper-twin plant, varied)",
        notes=f"concealed-effect benchmark case; noise_std={noise_std:g} m",
    )
    truth["recording_sha256"] = rec.sha256()
    truth["generate_s"] = time.perf_counter() - t_start
    return Case(case_id, spec, rec, truth)


# -- files -----------------------------------------------------------------------------------
def write_json_atomic(path: Path, data: Any) -> Path:
    """JSON to ``path`` via a temporary file in the same directory and ``os.replace``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            json.dump(data, fh, indent=2, sort_keys=True)
            fh.write("\n")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_case(case: Case, out: Path) -> dict[str, Any]:
    """``out/CASE.h5`` (no /truth) and ``out/truth/CASE.json``; returns the manifest row."""
    out.mkdir(parents=True, exist_ok=True)
    rec_path = write_recording(case.recording, out / f"{case.case_id}.h5")
    write_json_atomic(out / "truth" / f"{case.case_id}.json", case.truth)
    return {
        "case": case.case_id,
        "recording": rec_path.name,
        "truth": f"truth/{case.case_id}.json",
        "duration_s": case.spec.duration,
        "sha256": case.truth["recording_sha256"],
    }


def repeat_recording(rec: Recording, truth: Mapping[str, Any]) -> Recording:
    """A second ram of the same case: the same plant, drive and hidden effect (the same
    noise-free motion), a fresh draw of the displacement noise.

    The case's noise generator (:func:`case_rngs`) drew the recorded noise first; the repeat
    takes its next ``n`` draws, so the case's own recording is unchanged and the repeat is
    deterministic in (spec, seed). ``x_clean`` is recovered as ``x − noise`` (exact to the
    rounding of one addition). What a test engineer has when a rig is rammed twice: the
    diagnosis' held-out check scores the first recording's fit on it (``validation``),
    which also judges local findings (a bump, an impact) whose place a split of one record
    would leave out of the training or the test part.
    """
    spec = CaseSpec(
        str(truth["effect"]), float(truth["level"]), float(truth["duration_s"]), int(truth["rep"])
    )
    _, rng_noise = case_rngs(spec, int(truth["seed"]))
    n, std = int(truth["n"]), float(truth["noise_std_m"])
    noise = rng_noise.normal(0.0, std, n)
    again = rng_noise.normal(0.0, std, n)
    return Recording(
        t=rec.t,
        x=(rec.x - noise) + again,
        mass=rec.mass,
        name=f"{rec.name}-repeat",
        source=rec.source,
        notes=f"second recording of {rec.name} (same plant and motion, new noise)",
    )


def repeat_path(data: Path, case_id: str) -> Path:
    """Where the second recording of case ``case_id`` lives: ``data/repeat/CASE.h5``."""
    return Path(data) / "repeat" / f"{case_id}.h5"


def write_repeat(data: Path, case_id: str) -> Path:
    """:func:`repeat_path` from ``data/CASE.h5`` and its truth (written once)."""
    path = repeat_path(data, case_id)
    if not path.is_file():
        truth = json.loads((data / "truth" / f"{case_id}.json").read_text())
        path.parent.mkdir(parents=True, exist_ok=True)
        write_recording(repeat_recording(read_recording(data / f"{case_id}.h5"), truth), path)
    return path


def _progress_line(i: int, total: int, case: Case) -> str:
    tr, spec = case.truth, case.spec
    return (
        f"[{i + 1}/{total}] {case.case_id} {spec.effect} c={spec.level:g} "
        f"T={spec.duration:g}s: c={tr['concealment']:.3f} "
        f"(output {tr['concealment_output']:.3g}, ee {tr['concealment_ee']:.3g}, "
        f"refit {tr.get('concealment_refit', 0.0):.3g}) "
        f"rms/σ={tr['raw_rms_over_sigma']:.3f} ({tr['generate_s']:.1f} s)"
    )


#: What a case's numbers depend on besides its spec and the seed: the package, this
#: benchmark's modules and the configs.
SOURCE_DIRS: tuple[Path, ...] = (
    ROOT / "fricjax",
    Path(__file__).resolve().parent,
    ROOT / "configs",
)


def source_digest(dirs: Sequence[Path] = SOURCE_DIRS) -> str:
    """SHA-256 (first 16 hex digits) over the ``.py`` and ``.toml`` files under ``dirs``,
    their paths included: the source state that generates or diagnoses a case."""
    h = hashlib.sha256()
    for d in dirs:
        for f in sorted(d.rglob("*")):
            if f.suffix in (".py", ".toml") and f.is_file() and "__pycache__" not in f.parts:
                h.update(f"{d.name}/{f.relative_to(d).as_posix()}".encode() + b"\0")
                h.update(f.read_bytes() + b"\0")
    return h.hexdigest()[:16]


def check_sources(expected: str, what: str) -> None:
    """Raise if the sources differ from ``expected`` (:func:`source_digest` when the run
    began). Worker processes are spawned, so each imports the package from disk: an edit
    made during a run would otherwise give cases of two versions under one commit."""
    now = source_digest()
    if now != expected:
        raise FricjaxError(
            f"{where('sources', what)}: fricjax, the benchmark or configs changed during the run "
            f"(digest {expected} at the start, {now} now); run again on an unchanged tree"
        )


def _generate_chunk(
    indexed: Sequence[tuple[int, CaseSpec]],
    total: int,
    out: str,
    seed: int,
    noise_std: float,
    substeps: int,
    measure: str,
    config: Config,
    sources: str,
    progress: Callable[[str], None] | None,
) -> list[tuple[int, dict[str, Any]]]:
    """Write the cases ``indexed`` [(position in the list, spec)]; return (position, row):
    all of :func:`generate` with one process, one worker's share with several. ``sources``:
    the run's :func:`source_digest`, checked before and after each case (package modules
    imported lazily load during a case)."""
    rows = []
    for i, spec in indexed:
        check_sources(sources, spec.effect)
        case = make_case(
            spec, seed, config, noise_std=noise_std, substeps=substeps, measure=measure
        )
        check_sources(sources, spec.effect)
        rows.append((i, write_case(case, Path(out))))
        if progress is not None:
            progress(_progress_line(i, total, case))
    return rows


def _print_flush(line: str) -> None:
    print(line, flush=True)


def generate(
    out: str | Path,
    specs: Sequence[CaseSpec],
    *,
    seed: int = 0,
    noise_std: float = DEFAULT_NOISE_STD,
    substeps: int = SUBSTEPS,
    measure: str = "output",
    config: Config | None = None,
    progress: Callable[[str], None] | None = None,
    jobs: int = 1,
) -> dict[str, Any]:
    """Write every case of ``specs`` and ``out/manifest.json``; returns the manifest.

    ``jobs`` > 1 deals the cases out round robin to that many worker processes (``spawn``:
    jax must not be forked); a case depends only on its spec and the seed, so the files are
    the same as with one process."""
    out = Path(out)
    config = config or load_config(CONFIG)
    indexed = list(enumerate(specs))
    sources = source_digest()
    common = (len(specs), str(out), seed, noise_std, substeps, measure, config, sources)
    if jobs > 1 and len(specs) > 1:
        from concurrent.futures import ProcessPoolExecutor
        from multiprocessing import get_context

        # workers print their own progress (a callable from here need not pickle)
        with ProcessPoolExecutor(max_workers=jobs, mp_context=get_context("spawn")) as pool:
            futures = [
                pool.submit(_generate_chunk, indexed[k::jobs], *common, _print_flush)
                for k in range(jobs)
            ]
            by_index = dict(itertools.chain.from_iterable(f.result() for f in futures))
    else:
        by_index = dict(_generate_chunk(indexed, *common, progress))
    rows = [by_index[i] for i in range(len(specs))]
    manifest = {
        "format": FORMAT,
        "seed": seed,
        "noise_std_m": noise_std,
        "rate_hz": RATE,
        "substeps": substeps,
        "measure": measure,
        "config": str(CONFIG),
        "cases": rows,
    }
    write_json_atomic(out / "manifest.json", manifest)
    return manifest


def git_commit() -> str | None:
    """HEAD of the checkout the benchmark runs from (None outside a git checkout)."""
    import subprocess

    try:
        done = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True, check=True
        )
    except (OSError, subprocess.CalledProcessError):
        return None
    return done.stdout.strip()


def parse_floats(text: str) -> tuple[float, ...]:
    return tuple(float(v) for v in text.split(",") if v.strip())


def parse_effects(text: str) -> tuple[list[str], bool]:
    """``--cases`` as (effects, include nulls): ``all``, or names incl. ``none``."""
    names = [v.strip() for v in text.split(",") if v.strip()]
    if not names or names == ["all"]:
        return list(EFFECTS), True
    return [n for n in names if n != NULL], NULL in names


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(ROOT / "out" / "concealed"))
    ap.add_argument("--cases", default="all", help="effects, comma-separated (none = nulls)")
    ap.add_argument("--levels", default=",".join(f"{v:g}" for v in DEFAULT_LEVELS))
    ap.add_argument("--lengths", default=",".join(f"{v:g}" for v in DEFAULT_LENGTHS))
    ap.add_argument("--reps", type=int, default=1)
    ap.add_argument("--nulls", type=int, default=6, help="null cases per length")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--substeps", type=int, default=SUBSTEPS)
    ap.add_argument("--measure", choices=MEASURES, default="output", help="concealment scaled to")
    ap.add_argument("--jobs", type=int, default=1, help="worker processes (1: this one)")
    args = ap.parse_args(argv)
    try:
        effects, with_nulls = parse_effects(args.cases)
        specs = case_specs(
            effects,
            parse_floats(args.levels),
            parse_floats(args.lengths),
            args.reps,
            args.nulls if with_nulls else 0,
        )
        generate(
            args.out,
            specs,
            seed=args.seed,
            substeps=args.substeps,
            measure=args.measure,
            progress=lambda m: print(m, flush=True),
            jobs=args.jobs,
        )
    except FricjaxError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
