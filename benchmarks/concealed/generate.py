"""Recordings with one concealed effect each (or none), made without fricjax's model.

Every case is a plant of :mod:`plant` (scipy ``solve_ivp``, event-located stick/slip),
sampled at 1 kHz from rest, with ONE hidden effect, plus white noise of std σ_x on x:

* families (:data:`FAMILIES`): ``ram`` — the seed's harmonic ram (eq. 5, δ = 1), the CSAA
  values of Tables 1–3 each ×U(0.85, 1.15), ω = 2π·U(4, 6) rad/s, 45 kg; diagnosed with
  ``configs/paper.toml``. ``force`` — a 10–30 kg axis whose drive force is measured and
  recorded in ``/u`` [N] (half of the cases reversing, half one-direction strokes);
  ``slow`` — a 50–150 kg carriage pulled through a spring at 1–3 cm/s, the classic
  stick-slip rig, its spring force recorded in ``/u``. Both force families are diagnosed
  with ``benchmarks/concealed/configs/force_axis.toml`` (measured input + Stribeck).
* effects: the catalogue's (:data:`CATALOGUE_EFFECTS`, the names of
  ``fricjax/diagnose/catalogue.py``), whose right answer is their name, and three outside
  it (:data:`OUTSIDE_EFFECTS`: drive saturation, a quadratic sensor nonlinearity, sensor
  backlash), whose right answer is ``unexplained``; nulls (``none``) carry none.
* σ_x ∈ :data:`SIGMAS` (1–100 µm), lengths :data:`LENGTHS` (0.272–4 s), concealment
  levels :data:`LEVELS`.

Concealment (:func:`concealment`): with ``x_e`` the noise-free recorded x of the plant with
the effect and ``x_b(θ)`` the base plant's (the effect left out), the base parameters θ
(26 for the ram: F0, ω, Fc, Fs, vs, Fv, Fp_i, φ_i; 5 for the force families: offset, Fc,
Fs, vs, Fv) are refitted to ``x_e`` in output error (:func:`refit`), and

    c = rms(x_e − x_b(θ̂)) / σ_x

is what no refit of the base can absorb, in noise standard deviations per sample. Each
effect's amplitude is scaled until c is within :data:`C_RTOL` of its level (log-secant on
c(a), at most :data:`MAX_EVALS` evaluations; cases that cannot reach it are flagged
``reached = false``).

Oracle (:func:`oracle`): on the noisy recording y, the base (θ) and base + the true term
(θ, φ; the effect's own parameters free, from the truth) are refitted in output error; with
σ_x known, ``LR = (RSS_base − RSS_full)/σ_x²`` and the true term pays where
``LR − k·ln n`` exceeds the diagnosis' bar (``min_delta_bic`` of
:class:`fricjax.diagnose.run.DiagnoseSettings`, 10): "does the true term pay on this
noisy record", asked in displacement, of the right term at its true place.

Draws: :func:`plan` lays out one draw's cases from its seed (:data:`DRAWS`: ``A`` may be
looked at when choosing thresholds, ``B`` never). A case depends only on (draw seed, its
spec): the same seed writes the same bits. Files: ``DATA/draw<A|B>/CASE.h5`` (layout v1;
``/truth`` holds the truth as one JSON attr, which only the scorer reads) and
``DATA/draw<A|B>/plan.json``.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import sys
import time
import zlib
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

# this checkout's fricjax (not another one installed in the environment), and plant.py
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from plant import Drive, Effect, Plant

ROOT = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent
FORMAT = "fricjax-concealed-v3"
RATE = 1000.0  # Hz
SIGMAS: tuple[float, ...] = (1e-6, 5e-6, 24e-6, 100e-6)  # m
LENGTHS: tuple[float, ...] = (0.272, 1.0, 4.0)  # s
LEVELS: tuple[float, ...] = (5.0, 7.0, 12.0)  # c, rms in σ_x
FAMILIES: tuple[str, ...] = ("ram", "force", "slow")
CATALOGUE_EFFECTS: tuple[str, ...] = (
    "stribeck",
    "stribeck_shape",
    "asymmetric_friction",
    "quadratic_drag",
    "presliding_hysteresis",
    "position_bump",
    "position_periodic",
    "impact",
    "extra_harmonic",
    "friction_drift",
    "mass_error",
)
OUTSIDE_EFFECTS: tuple[str, ...] = ("drive_saturation", "sensor_quadratic", "sensor_backlash")
NULL = "none"
UNEXPLAINED = "unexplained"
DRAWS: dict[str, int] = {"A": 20261125, "B": 97531}
CONFIGS: dict[str, Path] = {
    "ram": ROOT / "configs" / "paper.toml",
    "force": HERE / "configs" / "force_axis.toml",
    "slow": HERE / "configs" / "force_axis.toml",
}
# 4 s records take the diagnosis 5-10 min: this many effect cases of that length per draw
# (and one null), the rest split evenly between 0.272 s and 1 s.
LONG_EFFECT_CASES = 2
# Planning figures of today's diagnosis per case [min] (1 s: 0.5-2 min measured; 4 s: the
# scorer's 5 min timeout), for the estimate printed with the plan.
DIAGNOSE_MINUTES: dict[float, float] = {0.272: 0.5, 1.0: 1.5, 4.0: 5.0}
C_RTOL = 0.03
# a case counts at its level where its achieved c is within this factor of it, either way
REACHED = 0.75
MAX_EVALS = 8
SHAPE_TRIES = 2
LM_ITERS = 36
# Records longer than LONG_RECORD [s] get a smaller budget (a 4 s ram simulation takes ~3 s,
# and a case must stay within minutes): fewer refit iterations and evaluations, one shape.
LONG_RECORD = 2.0
LM_ITERS_LONG = 15
MAX_EVALS_LONG = 5
FD_STEP = 1e-5  # relative finite-difference step of the refit's first Jacobian

# Seed Tables 1-3, CSAA column (eq. 5 with N = 10, δ = 1); ω is drawn (the paper gives none).
CSAA: dict[str, float] = {
    "F0": 432.7,
    "Fc": 30.00,
    "Fv": 3749.9,
    "Fs": 189.99,
    "vs": 0.121,
    **{
        f"Fp_{i}": a
        for i, a in enumerate(
            (667.5, 998.1, 1118.9, 879.9, 559.9, 49.99, 279.9, 139.9, 413.0, 9.99), 1
        )
    },
    **{
        f"phi_{i}": a
        for i, a in enumerate((0.71, 0.96, 1.24, 1.49, 1.57, 0.499, 0.001, 0.001, 0.001, 1.00), 1)
    },
}
RAM_MASS = 45.0
RAM_FREE: tuple[str, ...] = (
    "F0",
    "omega",
    "Fc",
    "Fs",
    "vs",
    "Fv",
    *(f"Fp_{i}" for i in range(1, 11)),
    *(f"phi_{i}" for i in range(1, 11)),
)
AXIS_FREE: tuple[str, ...] = ("offset", "Fc", "Fs", "vs", "Fv")
# The effect's own parameters the oracle frees (shape and amplitude; fixed ones are not).
TERM_FREE: dict[str, tuple[str, ...]] = {
    "stribeck": ("stribeck_A", "stribeck_vst"),
    "stribeck_shape": ("shape_ddelta",),
    "asymmetric_friction": ("asym_dFc",),
    "quadratic_drag": ("drag_Cd",),
    "presliding_hysteresis": ("presl_A", "presl_eps"),
    "position_bump": ("bump_A", "bump_x0", "bump_w"),
    "position_periodic": ("per_A", "per_B", "per_lambda"),
    "impact": ("impact_A", "impact_t0", "impact_w"),
    "extra_harmonic": ("harm_A", "harm_B", "harm_f"),
    "friction_drift": ("drift_beta",),
    "mass_error": ("mass_eps",),
}


# effects whose shape (a place, a width, a frequency) is drawn: drawn again where the base
# absorbs the first one
SHAPED = frozenset(
    {
        "stribeck",
        "stribeck_shape",
        "presliding_hysteresis",
        "position_bump",
        "position_periodic",
        "impact",
        "extra_harmonic",
    }
)


class CaseSpec(NamedTuple):
    """One case: plant family, effect (or ``none``), σ_x [m], length [s], level (0: null),
    and its index in the draw's plan."""

    family: str
    effect: str
    sigma: float
    duration: float
    level: float
    index: int

    def case_id(self, seed: int) -> str:
        """Opaque, deterministic file stem (reveals nothing of the effect)."""
        key = f"{FORMAT}:{seed}:{self.family}:{self.effect}:{self.sigma:g}:{self.duration:g}"
        key += f":{self.level:g}:{self.index}"
        return "c" + hashlib.sha256(key.encode()).hexdigest()[:10]

    def rng(self, seed: int, what: str) -> np.random.Generator:
        """A PCG64 generator keyed on the draw seed, the case id and ``what`` (plant, noise)."""
        key = zlib.crc32(f"{what}:{self.case_id(seed)}".encode())
        return np.random.default_rng(np.random.SeedSequence([seed, key]))


# -- the plan of a draw ----------------------------------------------------------------------
def plan(seed: int) -> list[CaseSpec]:
    """One draw: every effect once per family (41 cases; no drive saturation on the spring
    rig) with σ_x, length and level dealt
    out balanced and shuffled by the seed, and a null per family and σ_x (12).

    Lengths: :data:`LONG_EFFECT_CASES` effect cases and one null at 4 s, the others half
    0.272 s and half 1 s. Listed shortest first."""
    rng = np.random.default_rng(seed)
    effects = [
        (f, e)
        for e in CATALOGUE_EFFECTS + OUTSIDE_EFFECTS
        for f in FAMILIES
        if not (e == "drive_saturation" and f == "slow")  # a spring does not saturate
    ]
    n = len(effects)

    def dealt(values: Sequence[float], k: int) -> list[float]:
        out = [values[i % len(values)] for i in range(k)]
        return [out[i] for i in rng.permutation(k)]

    sig = dealt(SIGMAS, n)
    lev = dealt(LEVELS, n)
    short = [LENGTHS[i % 2] for i in range(n - LONG_EFFECT_CASES)]
    dur = [short[i] for i in rng.permutation(len(short))] + [LENGTHS[2]] * LONG_EFFECT_CASES
    dur = [dur[i] for i in rng.permutation(n)]
    specs = [
        CaseSpec(f, e, s, d, lv, i)
        for i, ((f, e), s, d, lv) in enumerate(zip(effects, sig, dur, lev, strict=True))
    ]
    nulls = [(f, s) for f in FAMILIES for s in SIGMAS]
    ndur = [LENGTHS[i % 2] for i in range(len(nulls) - 1)] + [LENGTHS[2]]
    ndur = [ndur[i] for i in rng.permutation(len(nulls))]
    specs += [
        CaseSpec(f, NULL, s, d, 0.0, n + j)
        for j, ((f, s), d) in enumerate(zip(nulls, ndur, strict=True))
    ]
    # shortest records first (a --limit run is quick), nulls among them
    return sorted(specs, key=lambda s: (s.duration, s.index % 7, s.index))


def plan_table(specs: Sequence[CaseSpec]) -> str:
    """How many cases per family, kind, σ_x, length and level (printed before a run)."""
    from collections import Counter

    def kind(s: CaseSpec) -> str:
        return (
            "null"
            if s.effect == NULL
            else "outside"
            if s.effect in OUTSIDE_EFFECTS
            else "catalogue"
        )

    lines = [f"{len(specs)} cases"]
    for title, key in (
        ("family", lambda s: s.family),
        ("kind", kind),
        ("sigma_x [um]", lambda s: f"{s.sigma * 1e6:g}"),
        ("length [s]", lambda s: f"{s.duration:g}"),
        ("level c", lambda s: f"{s.level:g}" if s.level else "null"),
    ):
        counts = Counter(key(s) for s in specs)
        lines.append(f"  {title}: " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items())))
    minutes = sum(DIAGNOSE_MINUTES[s.duration] for s in specs)
    lines.append(
        f"  diagnosis: about {minutes:.0f} worker-minutes at "
        + ", ".join(f"{m:g} min per {d:g} s case" for d, m in DIAGNOSE_MINUTES.items())
    )
    return "\n".join(lines)


# -- plants ----------------------------------------------------------------------------------
def base_plant(spec: CaseSpec, rng: np.random.Generator) -> tuple[dict[str, float], Drive, float]:
    """The base parameters, the drive and the mass [kg] of the case's family, drawn."""
    if spec.family == "ram":
        p = {k: v * rng.uniform(0.85, 1.15) for k, v in CSAA.items()}
        p["omega"] = 2.0 * math.pi * rng.uniform(4.0, 6.0)
        return p, Drive("harmonic"), RAM_MASS
    if spec.family == "force":
        mass = rng.uniform(10.0, 30.0)
        fc = rng.uniform(5.0, 20.0)
        p = {
            "Fc": fc,
            "Fs": fc * rng.uniform(1.3, 2.0),
            "vs": rng.uniform(0.005, 0.03),
            "Fv": rng.uniform(20.0, 80.0),
            "offset": rng.uniform(-3.0, 3.0),
        }
        if rng.uniform() < 0.5:  # reversing: two sines
            f, a1 = rng.uniform(1.0, 3.0), p["Fs"] * rng.uniform(2.0, 4.0)
            a2, ph1, ph2 = a1 * rng.uniform(0.1, 0.3), rng.uniform(0, 6.283), rng.uniform(0, 6.283)
            prof = _sines(f, a1, a2, ph1, ph2)
        else:  # one-direction strokes: raised-sine pushes, the body stops between them
            prof = _strokes(
                rng.choice([-1.0, 1.0]) * p["Fs"] * rng.uniform(2.5, 4.0),
                rng.uniform(0.25, 0.5),
                rng.uniform(0.1, 0.2),
            )
        return p, Drive("input", profile=prof), mass
    mass = rng.uniform(50.0, 150.0)
    fc = rng.uniform(20.0, 50.0)
    p = {
        "Fc": fc,
        "Fs": fc * rng.uniform(1.5, 2.5),
        "vs": rng.uniform(0.002, 0.01),
        "Fv": rng.uniform(100.0, 400.0),
        "offset": rng.uniform(-3.0, 3.0),
    }
    k = rng.uniform(3e3, 1.5e4)
    return (
        p,
        Drive("spring", k=k, vd=rng.uniform(0.01, 0.03), d0=rng.uniform(0.9, 0.98) * p["Fs"] / k),
        mass,
    )


def _sines(f: float, a1: float, a2: float, ph1: float, ph2: float) -> Callable:
    def u(t: float | np.ndarray) -> float | np.ndarray:
        w = 2.0 * math.pi * f
        return a1 * np.sin(w * t + ph1) + a2 * np.sin(2.7 * w * t + ph2)

    return u


def _strokes(amp: float, period: float, width: float) -> Callable:
    def u(t: float | np.ndarray) -> float | np.ndarray:
        phase = np.mod(np.asarray(t, dtype=float) - 0.01, period)
        inside = (phase < width) & (np.asarray(t) >= 0.01)
        return amp * np.where(inside, np.sin(math.pi * phase / width) ** 2, 0.0)

    return u


# -- effects ---------------------------------------------------------------------------------
class Shape(NamedTuple):
    """An effect with its shape drawn: ``params(a)`` for amplitude ``a`` ≥ 0, the first trial
    amplitude and the largest allowed."""

    name: str
    params: Callable[[float], dict[str, float]]
    a0: float
    a_max: float


def draw_shape(
    name: str, rng: np.random.Generator, p: dict[str, float], x: np.ndarray, v: np.ndarray, T: float
) -> Shape:
    """The effect's shape (where, how wide, which sign) drawn from the base motion; its
    amplitude left to the concealment search."""
    f_ref = p["Fs"]
    x_lo, x_hi = float(np.min(x)), float(np.max(x))
    span = max(x_hi - x_lo, 1e-6)
    v_max = max(float(np.max(np.abs(v))), 1e-4)
    sign = float(rng.choice([-1.0, 1.0]))
    if name == "stribeck":
        # a Gaussian hump wider than the base's exponential drop, or the base absorbs it
        vst = min(p["vs"] * rng.uniform(2.5, 5.0), 0.5 * v_max)
        return Shape(name, lambda a: {"stribeck_A": a, "stribeck_vst": vst}, 0.02 * f_ref, f_ref)
    if name == "stribeck_shape":
        s = float(rng.choice([-0.5, 1.0]))  # δ = 1 + dδ, in (0.5, 2]
        return Shape(name, lambda a: {"shape_ddelta": s * a}, 0.05, 1.0)
    if name == "asymmetric_friction":
        return Shape(
            name, lambda a: {"asym_dFc": sign * a, "asym_dFv": 0.0}, 0.02 * f_ref, 0.9 * p["Fc"]
        )
    if name == "quadratic_drag":
        return Shape(name, lambda a: {"drag_Cd": a}, 0.02 * f_ref / v_max**2, 5 * f_ref / v_max**2)
    if name == "presliding_hysteresis":
        eps = rng.uniform(0.005, 0.03) * span
        return Shape(name, lambda a: {"presl_A": a, "presl_eps": eps}, 0.02 * f_ref, 0.9 * p["Fc"])
    if name == "position_bump":
        x0, w = x_lo + rng.uniform(0.25, 0.75) * span, rng.uniform(0.03, 0.1) * span
        return Shape(
            name, lambda a: {"bump_A": a, "bump_x0": x0, "bump_w": w}, 0.05 * f_ref, 5 * f_ref
        )
    if name == "position_periodic":
        lam, th = span / rng.uniform(3.0, 8.0), rng.uniform(0.0, 2.0 * math.pi)
        return Shape(
            name,
            lambda a: {"per_A": a * math.cos(th), "per_B": a * math.sin(th), "per_lambda": lam},
            0.02 * f_ref,
            5 * f_ref,
        )
    if name == "impact":
        t0, w = rng.uniform(0.2, 0.8) * T, rng.uniform(0.002, 0.005)
        return Shape(
            name,
            lambda a: {"impact_A": sign * a, "impact_t0": t0, "impact_w": w},
            0.5 * f_ref,
            50 * f_ref,
        )
    if name == "extra_harmonic":
        f, th = rng.uniform(8.0, 45.0), rng.uniform(0.0, 2.0 * math.pi)
        return Shape(
            name,
            lambda a: {"harm_A": a * math.cos(th), "harm_B": a * math.sin(th), "harm_f": f},
            0.02 * f_ref,
            5 * f_ref,
        )
    if name == "friction_drift":
        return Shape(
            name,
            lambda a: {"drift_beta": sign * a, "drift_tmid": T / 2, "drift_T": T},
            0.02 * f_ref,
            1.6 * p["Fc"],
        )
    if name == "mass_error":
        return Shape(name, lambda a: {"mass_eps": sign * a}, 0.005, 0.3)
    if name == "drive_saturation":
        return Shape(name, lambda a: {"sat_fraction": a}, 0.01, 0.8)
    if name == "sensor_quadratic":
        return Shape(name, lambda a: {"sensor_kappa": sign * a / span}, 1e-4, 0.3)
    if name == "sensor_backlash":
        return Shape(name, lambda a: {"backlash_b": a}, 1e-3 * span, 0.2 * span)
    raise ValueError(f"unknown effect {name!r}")


def play(x: np.ndarray, b: float) -> np.ndarray:
    """A backlash (play) of total width ``b`` [m] between the body and its sensor: the sensor
    moves only once the body has taken up the play, and starts centred."""
    out = np.empty_like(x)
    y = x[0]
    for i, xi in enumerate(x):
        y = min(max(y, xi - b / 2), xi + b / 2)
        out[i] = y
    return out


class Setup(NamedTuple):
    """What one case simulates: base parameters, drive, the given mass and the times."""

    p: dict[str, float]
    drive: Drive
    mass: float
    t: np.ndarray
    free: tuple[str, ...]


def recorded(
    setup: Setup, effect: Effect, p: dict[str, float] | None = None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Noise-free recorded ``(x, u)`` [m, N] of the plant with ``effect`` (base parameters
    ``p``, default the setup's); u is None for the ram. Sensor effects act on x only, drive
    saturation on the force the body feels (``u`` records the command)."""
    p = dict(setup.p if p is None else p)
    name, e = effect.name, dict(effect.params)
    if name == "drive_saturation":
        x0, _ = _plain(setup, p)
        full = Plant(p, setup.drive, setup.mass, Effect("none", {}))
        peak = float(np.max(np.abs(full.drive_force(setup.t, x0))))
        e = {"sat_F": (1.0 - e["sat_fraction"]) * peak}
    plant_effect = effect.name if name not in ("sensor_quadratic", "sensor_backlash") else "none"
    pl = Plant(p, setup.drive, setup.mass, Effect(plant_effect, e))
    x, _, _ = pl.simulate(setup.t)
    u = (
        None
        if setup.drive.kind == "harmonic"
        else np.asarray(setup.drive.u(setup.t, x), dtype=float)
    )
    if name == "sensor_quadratic":
        x = x + e["sensor_kappa"] * x**2
    elif name == "sensor_backlash":
        x = play(x, e["backlash_b"])
    return x, u


def _plain(setup: Setup, p: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
    x, v, _ = Plant(p, setup.drive, setup.mass, Effect("none", {})).simulate(setup.t)
    return x, v


# -- output-error refits ---------------------------------------------------------------------
def _scales(p: dict[str, float], names: Sequence[str]) -> np.ndarray:
    """Per-parameter scale for the refit's steps: |value|, 1 rad for phases."""
    return np.array([1.0 if n.startswith("phi_") else max(abs(p[n]), 1e-3) for n in names])


def _physical(p: dict[str, float]) -> dict[str, float]:
    q = dict(p)
    for k in ("vs", "stribeck_vst", "presl_eps", "bump_w", "impact_w", "per_lambda"):
        if k in q:
            q[k] = max(abs(q[k]), 1e-7)
    return q


def jacobian(f: Callable[[np.ndarray], np.ndarray], q0: np.ndarray, y0: np.ndarray) -> np.ndarray:
    """Forward differences ``∂f/∂q`` [n, d] at ``q0`` (``y0 = f(q0)``), step FD_STEP."""
    cols = []
    for i in range(q0.size):
        q = q0.copy()
        q[i] += FD_STEP
        cols.append((f(q) - y0) / FD_STEP)
    return np.stack(cols, axis=1)


def refit(
    f: Callable[[np.ndarray], np.ndarray],
    y: np.ndarray,
    jac: np.ndarray,
    iters: int = LM_ITERS,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``min_q ‖y − f(q)‖²`` from q = 0 (scaled parameters, the truth at 0):
    Levenberg–Marquardt whose Jacobian starts at ``jac`` and follows the model by Broyden's
    rank-one updates, one simulation per iteration; stops when an accepted step lowers the
    cost by less than 1e-4 of it. Returns ``(q̂, y − f(q̂), J)``; an upper bound on the
    minimum where it stops early. A step whose plant cannot be simulated (a parameter made
    unphysical) counts as a failed step."""
    q = np.zeros(jac.shape[1])
    fq = f(q)
    r = y - fq
    cost, lam, J = float(r @ r), 1e-6, jac.copy()
    for _ in range(iters):
        norms = np.sum(J**2, axis=0)
        d = np.sqrt(norms + 1e-12 * np.max(norms) + 1e-300)
        aug = np.concatenate([J, np.diag(math.sqrt(lam) * d)])
        step = np.linalg.lstsq(aug, np.concatenate([r, np.zeros(q.size)]), rcond=None)[0]
        if not np.all(np.isfinite(step)) or float(step @ step) == 0.0:
            break
        try:
            f_new = f(q + step)
        except (RuntimeError, ValueError, FloatingPointError):
            f_new = np.full_like(fq, np.nan)
        if not np.all(np.isfinite(f_new)):
            lam *= 10
            continue
        r_new = y - f_new
        c_new = float(r_new @ r_new)
        J += np.outer((f_new - fq) - J @ step, step) / float(step @ step)
        if c_new < cost:
            converged = cost - c_new < 1e-4 * cost
            q, fq, r, cost, lam = q + step, f_new, r_new, c_new, lam / 5
            if converged:
                break
        else:
            lam *= 10
    return q, r, J


class Fitter:
    """Output-error refits of one case's base (and base + its true term) by :func:`refit`.

    The base Jacobian is taken once at the truth and shared by every refit of the case."""

    def __init__(self, setup: Setup, iters: int = LM_ITERS):
        self.setup = setup
        self.iters = iters
        self.names = setup.free
        self.scale = _scales(setup.p, self.names)
        self.theta0 = np.array([setup.p[n] for n in self.names])
        self.x0, _ = recorded(setup, Effect("none", {}))
        self.jac = jacobian(self.base_x, np.zeros(len(self.names)), self.x0)

    def params(self, q: np.ndarray) -> dict[str, float]:
        theta = self.theta0 + self.scale * q
        return _physical({**self.setup.p, **dict(zip(self.names, theta, strict=True))})

    def base_x(self, q: np.ndarray) -> np.ndarray:
        return recorded(self.setup, Effect("none", {}), self.params(q))[0]

    def residual(self, y: np.ndarray) -> np.ndarray:
        """``y − x_b(θ̂)``: what no base refit (from the truth) absorbs of ``y``."""
        return refit(self.base_x, y, self.jac, self.iters)[1]

    def with_term(self, y: np.ndarray, effect: Effect, free: Sequence[str]) -> np.ndarray:
        """``y − x(θ̂, φ̂)``: base and the effect's ``free`` parameters refitted together."""
        e0 = dict(effect.params)
        pair = {"per_A": "per_B", "per_B": "per_A", "harm_A": "harm_B", "harm_B": "harm_A"}
        # a quadrature amplitude near 0 is scaled by its pair's modulus
        sc = np.array([max(math.hypot(e0[k], e0.get(pair.get(k, k), 0.0)), 1e-9) for k in free])
        nb = len(self.names)

        def x_of(q: np.ndarray) -> np.ndarray:
            e = {**e0, **{k: e0[k] + s * qi for k, s, qi in zip(free, sc, q[nb:], strict=True)}}
            return recorded(self.setup, Effect(effect.name, _physical(e)), self.params(q[:nb]))[0]

        q0 = np.zeros(nb + len(free))
        y0 = x_of(q0)
        cols = [(x_of(np.eye(q0.size)[nb + i] * FD_STEP) - y0) / FD_STEP for i in range(len(free))]
        jac = np.concatenate([self.jac, np.stack(cols, axis=1)], axis=1)
        return refit(x_of, y, jac, self.iters)[1]


def rms(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(r**2)))


def concealment(fitter: Fitter, x_effect: np.ndarray, sigma: float) -> float:
    """``c = rms(x_e − x_b(θ̂))/σ_x`` (module docstring)."""
    return rms(fitter.residual(x_effect)) / sigma


def oracle(
    fitter: Fitter, y: np.ndarray, effect: Effect, sigma: float, bar: float
) -> dict[str, float | bool]:
    """Whether the true term pays on the noisy record ``y`` (module docstring)."""
    free = TERM_FREE[effect.name]
    rss_base = float(np.sum(fitter.residual(y) ** 2))
    rss_full = float(np.sum(fitter.with_term(y, effect, free) ** 2))
    lr = (rss_base - rss_full) / sigma**2
    dbic = lr - len(free) * math.log(y.size)
    return {"oracle_lr": lr, "oracle_dbic": dbic, "oracle_k": len(free), "oracle_pays": dbic > bar}


def counted(c: float, level: float) -> bool:
    """Whether a concealment ``c`` counts at ``level``: within a factor :data:`REACHED` of
    it either way (where c(a) jumps past the level, the nearest side is taken; a case
    3× its level says nothing about the level)."""
    return REACHED * level <= c <= level / REACHED


def scale_to(
    target: float, shape: Shape, c_of: Callable[[float], float], max_evals: int = MAX_EVALS
) -> tuple[float, float, int, bool]:
    """The amplitude at which ``c_of`` hits ``target`` within C_RTOL: log-secant from
    ``shape.a0`` (c is close to a power of a), kept in (0, a_max]; once the target is
    bracketed, inside the bracket (a geometric bisection where the secant leaves it, as c(a)
    can jump where the effect changes the stick/slip sequence). An amplitude where the
    plant chatters (c = ∞) or that stops the body for the whole record (c = 0 above an
    amplitude with c > 0: nothing moves, so nothing is left to conceal) is too strong and
    bounds the bracket from above. Returns (a, c, evaluations, reached); not reached: the
    evaluation nearest the target among those that count (:func:`counted`), else the
    nearest."""
    pts: list[tuple[float, float]] = []
    a = shape.a0
    for k in range(max_evals):
        c = c_of(a)
        pts.append((a, c))
        if abs(c / target - 1.0) < C_RTOL:
            return a, c, k + 1, True
        below = [q for q in pts if 0 < q[1] < target]
        above = [
            q
            for q in pts
            if q[1] > target or (q[1] <= 0 and any(0 < r[1] and r[0] < q[0] for r in pts))
        ]
        lo = max(below, default=None)
        hi = min(above, default=None)
        good = sorted(
            (q for q in pts if 0 < q[1] < math.inf), key=lambda q: abs(math.log(q[1] / target))
        )
        a_next = a * (target / c if 0 < c < math.inf else 10.0 if c <= 0 else 0.3)
        if len(good) >= 2 and good[0][0] != good[1][0]:
            (a1, c1), (a2, c2) = good[:2]
            slope = (math.log(c2) - math.log(c1)) / (math.log(a2) - math.log(a1))
            if 0.2 < slope < 5.0:
                a_next = a1 * (target / c1) ** (1.0 / slope)
        if lo is not None and hi is not None and lo[0] < hi[0]:
            if not lo[0] < a_next < hi[0]:
                a_next = math.sqrt(lo[0] * hi[0])
        a_next = min(a_next, shape.a_max)
        if a_next == a:
            break
        a = a_next
    ok = [q for q in pts if counted(q[1], target) and q[1] < math.inf] or pts
    a, c = min(ok, key=lambda q: abs(math.log(max(q[1], 1e-300) / target)))
    return a, c, len(pts), False


# -- one case --------------------------------------------------------------------------------
def diagnose_bar() -> float:
    """The diagnosis' ΔBIC bar (``min_delta_bic`` of its default settings)."""
    from fricjax.diagnose.run import DiagnoseSettings

    return float(DiagnoseSettings().min_delta_bic)


def setup_of(spec: CaseSpec, seed: int) -> tuple[Setup, np.random.Generator]:
    rng = spec.rng(seed, "plant")
    p, drive, mass = base_plant(spec, rng)
    t = np.arange(round(spec.duration * RATE), dtype=np.float64) / RATE
    free = RAM_FREE if spec.family == "ram" else AXIS_FREE
    return Setup(p, drive, mass, t, free), rng


def make_case(
    spec: CaseSpec, seed: int, bar: float | None = None
) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(signals, truth)`` of one case: the recorded t, x (noise added), u (or None) and
    mass, and everything the scorer needs to know about it."""
    t_start = time.perf_counter()
    setup, rng = setup_of(spec, seed)
    x_base, v_base, stuck = Plant(setup.p, setup.drive, setup.mass, Effect("none", {})).simulate(
        setup.t
    )
    truth: dict[str, Any] = {
        "format": FORMAT,
        "case": spec.case_id(seed),
        "seed": seed,
        **spec._asdict(),
        "kind": "null"
        if spec.effect == NULL
        else "outside"
        if spec.effect in OUTSIDE_EFFECTS
        else "catalogue",
        "right_answer": spec.effect
        if spec.effect in CATALOGUE_EFFECTS
        else UNEXPLAINED
        if spec.effect != NULL
        else NULL,
        "base": setup.p,
        "mass_given_kg": setup.mass,
        "drive": {
            "kind": setup.drive.kind,
            "k": setup.drive.k,
            "vd": setup.drive.vd,
            "d0": setup.drive.d0,
        },
        "stuck_fraction_base": float(np.mean(stuck)),
        "config": str(CONFIGS[spec.family].relative_to(ROOT)),
    }
    sigma = spec.sigma
    if spec.effect == NULL:
        x_clean, u = recorded(setup, Effect("none", {}))
        truth.update(params={}, concealment=0.0, reached=True)
    else:
        long = spec.duration > LONG_RECORD
        fitter = Fitter(setup, LM_ITERS_LONG if long else LM_ITERS)
        # rms(x_e − x_b(θ̂)) [m] of the current shape per amplitude: noise-free, so the
        # concealment at any σ_x is r/σ_x without simulating again
        r_of: dict[float, float] = {}

        def c_of(shape: Shape, sig: float) -> Callable[[float], float]:
            def c(a: float) -> float:
                if a not in r_of:
                    try:
                        x_e = recorded(setup, Effect(spec.effect, shape.params(a)))[0]
                        r_of[a] = concealment(fitter, x_e, 1.0)
                    except RuntimeError:  # the plant chatters: treat as too strong
                        r_of[a] = math.inf
                return r_of[a] / sig

            return c

        evals_max = MAX_EVALS_LONG if long else MAX_EVALS
        # where the base absorbs the effect's first shape, the shape is drawn again
        for tries in range(1, (SHAPE_TRIES if spec.effect in SHAPED and not long else 1) + 1):
            shape = draw_shape(spec.effect, rng, setup.p, x_base, v_base, spec.duration)
            r_of.clear()
            a, c, evals, reached = scale_to(spec.level, shape, c_of(shape, sigma), evals_max)
            truth["shape_tries"] = tries
            if reached:
                break
        if not counted(c, spec.level):
            # Even at its largest physical amplitude the effect leaves less than the level
            # above this noise: no record with this sensor shows it at that level. The case
            # keeps its effect, record and level and takes the largest lower σ_x of SIGMAS
            # at which the same signature reaches the level (a better sensor), if any.
            r_max = max((r for r in r_of.values() if r < math.inf), default=0.0)
            lower = [s for s in sorted(SIGMAS, reverse=True) if s < sigma]
            fit = [s for s in lower if r_max / s >= REACHED * spec.level]
            if fit and r_max / sigma < REACHED * spec.level:
                sigma = fit[0]
                a, c, more, reached = scale_to(spec.level, shape, c_of(shape, sigma), evals_max)
                evals += more
        truth["refit_iters"] = fitter.iters
        effect = Effect(spec.effect, shape.params(a))
        x_clean, u = recorded(setup, effect)
        truth.update(
            params=dict(effect.params),
            amplitude=a,
            amplitude_max=shape.a_max,
            concealment=c,
            reached=reached,
            secant_evals=evals,
            raw_rms_over_sigma=rms(x_clean - fitter.x0) / sigma,
        )
        if sigma != spec.sigma:
            truth.update(sigma=sigma, sigma_planned=spec.sigma)
        if not counted(c, spec.level):
            truth["short_of_level"] = (
                "below the level at the smallest σ_x at the largest physical amplitude"
                if r_max / min(SIGMAS) < REACHED * spec.level
                else "c(a) jumps past the level (the amplitude search did not land on it)"
            )
    noise = spec.rng(seed, "noise").normal(0.0, sigma, setup.t.size)
    if spec.effect in CATALOGUE_EFFECTS:
        truth.update(
            oracle(
                fitter,
                x_clean + noise,
                effect,
                sigma,
                diagnose_bar() if bar is None else bar,
            )
        )
    x = x_clean + noise
    truth["generate_s"] = time.perf_counter() - t_start
    signals = {"t": setup.t, "x": x, "u": u, "mass": setup.mass}
    return signals, truth


def case_path(data: Path, draw: str, spec: CaseSpec) -> Path:
    return Path(data) / f"draw{draw}" / f"{spec.case_id(DRAWS[draw])}.h5"


def write_case(path: Path, spec: CaseSpec, signals: dict[str, Any], truth: dict[str, Any]) -> Path:
    """Layout v1 (``/t``, ``/x``, ``/u`` [N] for the force families, attr ``mass``) with the
    truth as one JSON string in ``/truth``; written atomically."""
    from fricjax.data.recording import Recording, write_recording

    rec = Recording(
        t=signals["t"],
        x=signals["x"],
        u=signals["u"],
        u_unit="N" if signals["u"] is not None else "",
        mass=float(signals["mass"]),
        name=path.stem,
        source="benchmarks/concealed/generate.py (scipy plant, event-located stick/slip)",
        notes=f"concealed benchmark case; noise std {spec.sigma:g} m on x",
    )
    truth = {**truth, "recording_sha256": rec.sha256()}
    return write_recording(rec, path, truth={"json": json.dumps(_json_safe(truth), sort_keys=True)})


def read_truth(path: Path) -> dict[str, Any]:
    """Scoring only: the case's truth from ``/truth``."""
    import h5py

    with h5py.File(path, "r") as f:
        return json.loads(f["truth"].attrs["json"])


def _json_safe(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {str(k): _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_json_safe(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def _one(args: tuple[str, str, int, float]) -> str:
    data, draw, index, deadline = args
    spec = next(s for s in plan(DRAWS[draw]) if s.index == index)
    path = case_path(Path(data), draw, spec)
    if path.is_file():
        return f"{path.name}: exists"
    if deadline and time.time() > deadline:
        return f"{path.name}: not started (--start-until)"
    try:
        signals, truth = make_case(spec, DRAWS[draw])
    except (RuntimeError, ValueError, np.linalg.LinAlgError) as err:  # the others go on
        return f"{path.name} draw {draw} {spec.family} {spec.effect}: FAILED ({err})"
    write_case(path, spec, signals, truth)
    c = truth.get("concealment", 0.0)
    return (
        f"{path.name} draw {draw} {spec.family} {spec.effect} σ={truth['sigma'] * 1e6:g}µm "
        f"T={spec.duration:g}s c={c:.2f}/{spec.level:g} ({truth['generate_s']:.0f} s)"
    )


def generate(
    data: Path, draws: Sequence[str], workers: int = 1, limit: int = 0, start_until: float = 0.0
) -> list[Path]:
    """Write every case of the draws' plans missing from ``data`` (``limit`` > 0: only the
    first ``limit`` of each plan; ``start_until`` > 0: start no case after that many
    seconds); also ``data/draw<X>/plan.json``. Returns the paths."""
    deadline = time.time() + start_until if start_until > 0 else 0.0
    from fricjax.io.atomic import write_text_atomic

    jobs, paths = [], []
    for draw in draws:
        specs = plan(DRAWS[draw])
        if limit:
            specs = specs[:limit] if limit > 0 else specs
        rows = [
            {
                **s._asdict(),
                "case": s.case_id(DRAWS[draw]),
                "recording": case_path(data, draw, s).name,
            }
            for s in specs
        ]
        (Path(data) / f"draw{draw}").mkdir(parents=True, exist_ok=True)
        write_text_atomic(
            Path(data) / f"draw{draw}" / "plan.json",
            json.dumps(
                {"format": FORMAT, "draw": draw, "seed": DRAWS[draw], "cases": rows}, indent=1
            ),
        )
        for s in specs:
            paths.append(case_path(data, draw, s))
            if not paths[-1].is_file():
                jobs.append((str(data), draw, s.index, deadline))
    # the longest records first: with many workers the slowest cases must not start last
    durations = {(d, s.index): s.duration for d in draws for s in plan(DRAWS[d])}
    jobs.sort(key=lambda j: -durations[(j[1], j[2])])
    if workers > 1 and len(jobs) > 1:
        from multiprocessing import get_context

        # spawn, not fork: the parent may have imported jax (fricjax), which forks badly
        with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn")) as pool:
            for line in pool.map(_one, jobs):
                print(line, flush=True)
    else:
        for job in jobs:
            print(_one(job), flush=True)
    return paths


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=str(ROOT / "out" / "concealed"))
    ap.add_argument("--draws", default="A,B")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--limit", type=int, default=0, help="only the first N cases of each draw")
    ap.add_argument("--start-until", type=float, default=0.0, help="start no case after S s")
    args = ap.parse_args(argv)
    draws = [d.strip() for d in args.draws.split(",") if d.strip()]
    for d in draws:
        if d not in DRAWS:
            print(
                f"error: --draws: unknown draw {d!r} (known: {', '.join(DRAWS)})", file=sys.stderr
            )
            return 2
        print(f"draw {d} (seed {DRAWS[d]}): " + plan_table(plan(DRAWS[d])))
    generate(Path(args.data), draws, args.workers, args.limit, args.start_until)
    return 0


if __name__ == "__main__":
    sys.exit(main())
