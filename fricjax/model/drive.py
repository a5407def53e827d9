"""Drive terms ``F_p`` (force applied to the body by the feeding system or actuator)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import jax.numpy as jnp
from jaxtyping import Array, Float

from fricjax.model.term import Signals, Term
from fricjax.params import Named, Param


@dataclass(frozen=True)
class HarmonicDrive(Term):
    """``F_p(t) = F0 + Σ_{i=1..N} Fp_i·sin(i·ω·t + φ_i)`` [N] (seed eq. 4).

    Parameters: F0 [N] mean push, omega [rad/s] fundamental, Fp_i [N] amplitudes,
    phi_i [rad] phases, i = 1..N (N = ``harmonics``, 10 in the seed).
    """

    harmonics: int = 10
    name: ClassVar[str] = "harmonic_drive"
    role: ClassVar = "drive"

    def parameters(self) -> tuple[Param, ...]:
        amps = tuple(
            Param(f"Fp_{i}", "N", 0.0, 1e4, 0.0, null=0.0) for i in range(1, self.harmonics + 1)
        )
        phases = tuple(
            Param(f"phi_{i}", "rad", -math.pi, math.pi, 0.0) for i in range(1, self.harmonics + 1)
        )
        return (
            Param("F0", "N", -1e4, 1e4, 0.0, null=0.0),
            Param("omega", "rad/s", 1.0, 1e3, 2 * math.pi * 5),
            *amps,
            *phases,
        )

    def force(self, p: Named, s: Signals) -> Float[Array, "..."]:
        # Fp_i·sin(iθ + φ_i) = A_i·sin(iθ) + B_i·cos(iθ), A_i = Fp_i cos φ_i, B_i = Fp_i sin φ_i,
        # and sin/cos(iθ) by the Chebyshev recurrence from one sin/cos of θ = ω·t: XLA's CPU
        # sine costs ~20-40 ns an element, so ten of them per sample dominated the cost.
        theta = p["omega"] * jnp.asarray(s.t)
        c1, s1 = jnp.cos(theta), jnp.sin(theta)
        two_c = 2.0 * c1
        sin_prev, cos_prev = jnp.zeros_like(s1), jnp.ones_like(c1)
        sin_i, cos_i = s1, c1
        total = p["F0"] + jnp.zeros_like(theta)
        for k in range(1, self.harmonics + 1):
            amp, phase = p[f"Fp_{k}"], p[f"phi_{k}"]
            total = total + (amp * jnp.cos(phase)) * sin_i + (amp * jnp.sin(phase)) * cos_i
            sin_prev, sin_i = sin_i, two_c * sin_i - sin_prev
            cos_prev, cos_i = cos_i, two_c * cos_i - cos_prev
        return total


@dataclass(frozen=True)
class MeasuredInput(Term):
    """``F_p(t) = g·u(t) − offset`` [N], for rigs whose drive signal ``u`` is recorded.

    Parameters: gain [N per unit of u] (e.g. gτ = 35.15 N/V on EMPS), offset [N] — a
    constant force opposing the drive, with the sign convention of the EMPS inverse
    dynamic model ``M·q̈ + Fv·q̇ + Fc·sgn(q̇) + offset = gτ·vir``.
    """

    name: ClassVar[str] = "measured_input"
    role: ClassVar = "drive"

    def parameters(self) -> tuple[Param, ...]:
        return (
            Param("gain", "N/u", 1.0, 1.0, 1.0, free=False),
            Param("offset", "N", -1e4, 1e4, 0.0, null=0.0),
        )

    def force(self, p: Named, s: Signals) -> Float[Array, "..."]:
        return p["gain"] * s.u - p["offset"]
