"""Drive terms ``F_p`` (force applied to the body by the feeding system or actuator)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from fricjax.model.term import Basis, Groups, Signals, Term
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

    def linear_groups(self) -> Groups:
        return (("F0",), *((f"Fp_{i}", f"phi_{i}") for i in range(1, self.harmonics + 1)))

    def basis(self, p: Named, s: Signals) -> Basis:
        """``F_p = F0·1 + Σ_i A_i·sin(iωt) + B_i·cos(iωt)`` (seed eq. 4 rewritten).

        Columns ``[1, sin ωt, cos ωt, …, sin Nωt, cos Nωt]`` [1], shape [..., 1 + 2N],
        depending on ω only (same Chebyshev recurrence as :meth:`force`); coefficients
        ``[F0, A_1, B_1, …]`` with ``A_i = Fp_i cos φ_i``, ``B_i = Fp_i sin φ_i``
        (:meth:`to_linear`; inverse ``Fp_i = √(A_i² + B_i²)``, ``φ_i = atan2(B_i, A_i)``).
        """
        theta = p["omega"] * jnp.asarray(s.t, dtype=jnp.float64)
        c1, s1 = jnp.cos(theta), jnp.sin(theta)
        two_c = 2.0 * c1

        # The recurrence as a scan: unrolled, XLA re-derives every column from the first
        # inside each consumer's fusion (measured 2x slower and slower to compile).
        def harmonic(carry: tuple[Array, ...], _: None) -> tuple[tuple[Array, ...], Array]:
            sin_prev, sin_i, cos_prev, cos_i = carry
            nxt = (sin_i, two_c * sin_i - sin_prev, cos_i, two_c * cos_i - cos_prev)
            return nxt, jnp.stack([sin_i, cos_i], axis=-1)

        start = (jnp.zeros_like(s1), s1, jnp.ones_like(c1), c1)
        _, pairs = jax.lax.scan(harmonic, start, None, length=self.harmonics)  # [N, ..., 2]
        pairs = jnp.moveaxis(pairs, 0, -2).reshape(*theta.shape, 2 * self.harmonics)
        return Basis(
            jnp.concatenate([jnp.ones_like(theta)[..., None], pairs], axis=-1),
            self.linear_groups(),
        )

    def linear_coefficients(self, values: Float[Array, " k"], p: Named) -> Float[Array, " k"]:
        """``[F0, Fp_1, φ_1, …] -> [F0, A_1, B_1, …]`` [N], ``A_i = Fp_i cos φ_i``,
        ``B_i = Fp_i sin φ_i`` (one vector cos/sin over the N phases)."""
        pairs = values[1:].reshape(self.harmonics, 2)
        amp, phase = pairs[:, 0], pairs[:, 1]
        ab = jnp.stack([amp * jnp.cos(phase), amp * jnp.sin(phase)], axis=-1)
        return jnp.concatenate([values[:1], ab.reshape(-1)])

    def linear_values(self, coef: Float[Array, " k"], p: Named) -> Float[Array, " k"]:
        """``[F0, A_1, B_1, …] -> [F0, Fp_1, φ_1, …]``: ``Fp_i = √(A_i² + B_i²)`` [N],
        ``φ_i = atan2(B_i, A_i)`` ∈ (−π, π] [rad]."""
        pairs = coef[1:].reshape(self.harmonics, 2)
        a, b = pairs[:, 0], pairs[:, 1]
        polar = jnp.stack([jnp.hypot(a, b), jnp.arctan2(b, a)], axis=-1)
        return jnp.concatenate([coef[:1], polar.reshape(-1)])


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

    def linear_groups(self) -> Groups:
        return (("gain",), ("offset",))

    def basis(self, p: Named, s: Signals) -> Basis:
        """Columns ``[u, −1]`` [u_unit, 1], shape [..., 2]; coefficients gain, offset."""
        u = jnp.asarray(s.u, dtype=jnp.float64)
        return Basis(jnp.stack([u, -jnp.ones_like(u)], axis=-1), self.linear_groups())
