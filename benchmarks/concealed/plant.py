"""The concealed benchmark's own plant: a rigid body with Stribeck friction, integrated by
scipy's ``solve_ivp`` with event-located stick and slip. Shares no code with fricjax's model.

Equation of motion (SI units; ``m`` [kg], ``x`` [m], ``v`` [m/s], forces [N])::

    m·dv/dt = F_a(t, x) − F_f(v, s, x, t, z)      while sliding in direction s = ±1
    v = 0, x constant                              while stuck

with the applied force ``F_a`` (drive plus any drive-side effect) and the friction of the
sliding direction ``s`` (the direction is held for a whole slip phase, so sgn(v) never
chatters at v = 0)::

    F_f = s·[Fc + (Fs − Fc)·exp(−|v|/vs)] + Fv·v   (+ the friction-side effects)

A slip phase ends where ``v`` reaches 0 (a ``solve_ivp`` terminal event, located to the
integrator's tolerance, then v is set to exactly 0). There the body reverses if the applied
force beats the static friction of the other direction, ``L_s = s·F_f(0, s)``, and sticks
otherwise; it breaks away from a stick in direction s at the first time where
``s·F_a(t, x) > L_s(t)`` (a scan of the force on a grid of ``STICK_SCAN`` s, then Brent's
root). Time-varying friction (a drift) and a Dahl bristle state ``z`` (frozen at rest) are
part of the state the limits read.

Parameter dictionaries use the names of ``shared/conventions.md`` where they exist (the base:
``Fc, Fs, vs, Fv``; a ram's ``F0, omega, Fp_i, phi_i``; a force axis' ``offset``) so the
truth files read like fricjax's configs; the formulas below are written independently.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
from scipy.integrate import solve_ivp
from scipy.optimize import brentq

RTOL = 1e-7
ATOL = (1e-12, 1e-10, 1e-9)  # x [m], v [m/s], z [1]
STICK_SCAN = 2e-4  # s: grid on which a stuck body's breakaway is looked for
MAX_PHASES = 20000
MAX_WALL = 60.0  # s: a simulation that takes longer chatters (RuntimeError)


@dataclass(frozen=True)
class Effect:
    """A hidden effect: its name and its parameters (SI units)."""

    name: str
    params: Mapping[str, float]


NO_EFFECT = Effect("none", {})


def harmonic_drive(p: Mapping[str, float], t: float | np.ndarray) -> float | np.ndarray:
    """Seed eq. 4: ``F_p(t) = F0 + Σ_i Fp_i·sin(i·ω·t + φ_i)`` [N] (the ram's drive)."""
    n = sum(1 for k in p if k.startswith("Fp_"))
    i = np.arange(1, n + 1)
    amp = np.array([p[f"Fp_{k}"] for k in i])
    phase = np.array([p[f"phi_{k}"] for k in i])
    arg = np.multiply.outer(np.asarray(t, dtype=float), i * p["omega"]) + phase
    return p["F0"] + np.sin(arg) @ amp


@dataclass(frozen=True)
class Drive:
    """Where the applied force comes from.

    ``kind``: ``"harmonic"`` (the ram: :func:`harmonic_drive` of the parameters), ``"input"``
    (a force profile ``u(t)`` [N] on the body, recorded in ``/u``, minus ``offset``) or
    ``"spring"`` (a spring of stiffness ``k`` [N/m] whose far end moves at ``vd`` [m/s] from
    a pre-tension ``d0`` [m]: ``u = k·(d0 + vd·t − x)``, recorded in ``/u``, minus
    ``offset``: the classic stick-slip rig)."""

    kind: str
    profile: Callable[[float | np.ndarray], float | np.ndarray] | None = None
    k: float = 0.0
    vd: float = 0.0
    d0: float = 0.0

    def u(self, t: float | np.ndarray, x: float | np.ndarray) -> float | np.ndarray:
        """The recorded force signal [N] (``"input"`` and ``"spring"`` only)."""
        if self.kind == "spring":
            return self.k * (self.d0 + self.vd * t - x)
        assert self.profile is not None
        return self.profile(t)


class Plant:
    """Base parameters ``p``, the drive, the true mass [kg] and one hidden effect.

    :meth:`applied` and :meth:`friction` accept scalars or arrays (the stick scan evaluates
    them on a grid)."""

    def __init__(self, p: Mapping[str, float], drive: Drive, mass: float, effect: Effect):
        self.p = dict(p)
        self.drive = drive
        self.effect = effect
        e = effect.params
        self.mass = mass / (1.0 - e["mass_eps"]) if effect.name == "mass_error" else mass
        self.e = dict(e)
        self.presliding = effect.name == "presliding_hysteresis"
        if drive.kind == "harmonic":  # the drive's arrays, once (the integrator calls often)
            n = sum(1 for k in self.p if k.startswith("Fp_"))
            i = np.arange(1, n + 1)
            self._harmonics = (
                self.p["F0"],
                i * self.p["omega"],
                np.array([self.p[f"Fp_{k}"] for k in i]),
                np.array([self.p[f"phi_{k}"] for k in i]),
            )

    # -- forces ------------------------------------------------------------------------------
    def drive_force(self, t: float | np.ndarray, x: float | np.ndarray) -> float | np.ndarray:
        """The force the drive puts on the body [N] (saturated if that is the effect)."""
        if self.drive.kind == "harmonic":
            f0, w, amp, phase = self._harmonics
            f = f0 + np.sin(np.multiply.outer(t, w) + phase) @ amp
        else:
            f = self.drive.u(t, x) - self.p["offset"]
        if self.effect.name == "drive_saturation":
            lim = self.e["sat_F"]
            f = np.clip(f, -lim, lim)
        return f

    def applied(self, t: float | np.ndarray, x: float | np.ndarray) -> float | np.ndarray:
        """``F_a`` [N]: drive plus the drive-side effects (not friction)."""
        f = self.drive_force(t, x)
        name, e = self.effect.name, self.e
        if name == "position_periodic":
            ph = 2.0 * math.pi * x / e["per_lambda"]
            f = f + e["per_A"] * np.sin(ph) + e["per_B"] * np.cos(ph)
        elif name == "impact":
            f = f + e["impact_A"] * np.exp(-0.5 * ((t - e["impact_t0"]) / e["impact_w"]) ** 2)
        elif name == "extra_harmonic":
            ph = 2.0 * math.pi * e["harm_f"] * t
            f = f + e["harm_A"] * np.sin(ph) + e["harm_B"] * np.cos(ph)
        return f

    def friction(
        self,
        v: float | np.ndarray,
        s: float,
        x: float | np.ndarray,
        t: float | np.ndarray,
        z: float,
    ) -> float | np.ndarray:
        """``F_f`` [N] sliding in direction ``s`` (= ±1) at speed ``v`` (``s·v ≥ 0``)."""
        p, e, name = self.p, self.e, self.effect.name
        speed = np.abs(v)
        f = s * (p["Fc"] + (p["Fs"] - p["Fc"]) * np.exp(-speed / p["vs"])) + p["Fv"] * v
        if name == "stribeck":
            f = f + s * e["stribeck_A"] * np.exp(-((speed / e["stribeck_vst"]) ** 2))
        elif name == "stribeck_shape":
            r = speed / p["vs"]
            f = f + s * (p["Fs"] - p["Fc"]) * (
                np.exp(-(r ** (1.0 + e["shape_ddelta"]))) - np.exp(-r)
            )
        elif name == "asymmetric_friction":
            f = f + e["asym_dFc"] + e["asym_dFv"] * speed
        elif name == "quadratic_drag":
            f = f + e["drag_Cd"] * v * speed
        elif name == "presliding_hysteresis":
            f = f + e["presl_A"] * (z - s)
        elif name == "position_bump":
            f = f + s * e["bump_A"] * np.exp(-0.5 * ((x - e["bump_x0"]) / e["bump_w"]) ** 2)
        elif name == "friction_drift":
            f = f + s * e["drift_beta"] * (t - e["drift_tmid"]) / e["drift_T"]
        return f

    def limit(self, s: float, x: float, t: float | np.ndarray, z: float) -> float | np.ndarray:
        """Static friction against a breakaway in direction ``s`` [N] (≥ 0 in a plant that
        makes sense): ``s·F_f(0, s)``."""
        return s * self.friction(0.0, s, x, t, z)

    # -- integration -------------------------------------------------------------------------
    def _rhs(self, s: float) -> Callable[[float, np.ndarray], list[float]]:
        m, eps = self.mass, self.e.get("presl_eps", 1.0)

        def rhs(t: float, y: np.ndarray) -> list[float]:
            x, v, z = y
            a = (self.applied(t, x) - self.friction(v, s, x, t, z)) / m
            dz = (s - z) * abs(v) / eps if self.presliding else 0.0
            return [v, a, dz]

        return rhs

    def _breakaway(self, t0: float, t_end: float, x: float, z: float) -> tuple[float, int]:
        """First time after ``t0`` where a stuck body at ``x`` breaks away, and its
        direction; ``(t_end, 0)`` if it stays stuck."""

        def excess(t: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            fa = self.applied(t, x)
            return fa - self.limit(1.0, x, t, z), -fa - self.limit(-1.0, x, t, z)

        grid = np.arange(t0, t_end + STICK_SCAN, STICK_SCAN)
        grid[-1] = min(grid[-1], t_end)
        up, down = excess(grid)
        over = (up > 0) | (down > 0)
        over[0] = False  # the body has just stopped: the start is a stick by definition
        if not over.any():
            return t_end, 0
        j = int(np.argmax(over))
        s = 1 if up[j] > 0 else -1

        def g(t: float) -> float:
            u, d = excess(t)
            return float(u if s > 0 else d)

        lo = grid[j - 1]
        t_b = brentq(g, lo, grid[j], xtol=1e-13) if g(lo) < 0 else lo
        # just past the root, so the body starts with a (tiny) acceleration away from rest
        return float(t_b) + 1e-12, s

    def simulate(self, t: np.ndarray, x0: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """From rest at ``x0`` [m] (default 0): ``(x, v, stuck)`` at the sample times ``t``
        [n]; ``stuck`` marks the samples inside a stick (where v is exactly 0). Every slip
        phase starts and ends at v = 0 (a breakaway, a reversal or a stop)."""
        n = t.size
        xs, vs, stuck = np.zeros(n), np.zeros(n), np.zeros(n, dtype=bool)
        t_now, x, z, t_end = float(t[0]), float(x0), 0.0, float(t[-1])
        s = self._direction(t_now, x, z)
        started = time.perf_counter()
        for _ in range(MAX_PHASES):
            if time.perf_counter() - started > MAX_WALL:
                break
            if s == 0:
                t_next, s = self._breakaway(t_now, t_end, x, z)
                sel = (t >= t_now) & ((t < t_next) if s else (t <= t_end))
                xs[sel], vs[sel], stuck[sel] = x, 0.0, True
                if s == 0:
                    return xs, vs, stuck
                t_now = t_next
                continue
            sol = solve_ivp(
                self._rhs(s),
                (t_now, t_end),
                [x, 0.0, z],
                method="DOP853",
                rtol=RTOL,
                atol=ATOL,
                events=_zero_velocity(s),
                dense_output=True,
            )
            t_stop = float(sol.t[-1])
            done = sol.status == 0  # reached t_end without a stop
            sel = (t >= t_now) & ((t <= t_end) if done else (t < t_stop))
            if sel.any():
                y = sol.sol(t[sel])
                xs[sel], vs[sel] = y[0], y[1]
            if done:
                return xs, vs, stuck
            x, z = float(sol.y_events[0][0][0]), float(sol.y_events[0][0][2])
            t_now = t_stop
            s = self._direction(t_now, x, z, came=s)
        raise RuntimeError("too many stick/slip phases")

    def _direction(self, t: float, x: float, z: float, came: int = 0) -> int:
        """At rest (v = 0) at time t: the direction the body slides off in, 0 to stick.
        A body that has just stopped sliding in direction ``came`` can only reverse."""
        fa = float(self.applied(t, x))
        for s in (1, -1):
            if s != came and s * fa > float(self.limit(s, x, t, z)):
                return s
        return 0


def _zero_velocity(s: int) -> Callable[[float, np.ndarray], float]:
    def event(t: float, y: np.ndarray) -> float:
        return y[1]

    event.terminal = True  # type: ignore[attr-defined]
    event.direction = -s  # type: ignore[attr-defined]
    return event
