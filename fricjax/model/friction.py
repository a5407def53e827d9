"""Friction terms ``F_f(v)`` (the force resisting motion, subtracted in seed eq. 3).

Signs: ``F_f`` is odd in ``v`` and has the sign of ``v``: a body moving forward (v > 0) feels
``−F_f`` < 0.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import jax.numpy as jnp
from jaxtyping import Array, Float

from fricjax.model.term import Basis, Groups, Signals, Term, sgn
from fricjax.params import POSITIVE, Named, Param


def stribeck_curve(
    v: Float[Array, "..."],
    Fc: Float[Array, ""],
    Fs: Float[Array, ""],
    vs: Float[Array, ""],
    delta: Float[Array, ""],
) -> Float[Array, "..."]:
    """Stribeck level ``g(v) = Fc + (Fs − Fc)·exp(−(|v|/vs)^δ)`` [N] (seed eq. 1).

    ``(|v|/vs)^δ`` is evaluated through ``exp(δ·log(...))`` with the zero-speed branch kept
    out of the log, so the gradient stays finite at ``v = 0`` for every δ > 0. A fixed
    δ = 1 (Tustin, seed eq. 2) arrives as a float, not a traced array
    (:func:`fricjax.problem.named_static`), and skips the log/exp pair.
    """
    r = jnp.abs(v) / vs
    if isinstance(delta, float) and delta == 1.0:
        return Fc + (Fs - Fc) * jnp.exp(-r)
    safe = jnp.where(r > 0, r, 1.0)
    power = jnp.where(r > 0, jnp.exp(delta * jnp.log(safe)), 0.0)
    return Fc + (Fs - Fc) * jnp.exp(-power)


@dataclass(frozen=True)
class StribeckFriction(Term):
    """``F_f(v) = [Fc + (Fs − Fc)·exp(−(|v|/vs)^δ)]·sgn(v) + Fv·v`` [N].

    The standard Stribeck form. It equals the seed's eq. (1) for v > 0 (eq. 2 for δ = 1,
    Tustin) and, unlike eq. (1) as printed, stays odd in v through reversals.
    Parameters: Fc [N] Coulomb level, Fs [N] static level, vs [m/s] Stribeck velocity,
    delta [-] shape exponent, Fv [N·s/m] viscous coefficient.
    """

    name: ClassVar[str] = "stribeck_friction"
    role: ClassVar = "friction"

    def parameters(self) -> tuple[Param, ...]:
        return (
            Param("Fc", "N", 0.0, 1e4, 0.0, null=0.0),
            Param("Fs", "N", 0.0, 1e4, 0.0, null=0.0),
            Param("vs", "m/s", 1e-4, 10.0, 0.1, domain=POSITIVE),
            Param("delta", "1", 0.2, 5.0, 1.0, free=False, domain=POSITIVE),
            Param("Fv", "N*s/m", 0.0, 1e5, 0.0, null=0.0),
        )

    def force(self, p: Named, s: Signals) -> Float[Array, "..."]:
        level = stribeck_curve(s.v, p["Fc"], p["Fs"], p["vs"], p["delta"])
        return level * sgn(s.v) + p["Fv"] * s.v

    def linear_groups(self) -> Groups:
        return (("Fc",), ("Fs",), ("Fv",))

    def basis(self, p: Named, s: Signals) -> Basis:
        """``F_f = Fc·sgn(v)(1 − e) + Fs·sgn(v)·e + Fv·v``, ``e = exp(−(|v|/vs)^δ)``.

        Columns ``[sgn(v)(1 − e), sgn(v)·e, v]`` [1, 1, m/s], shape [..., 3]; they depend
        on (vs, δ) only. The coefficients are Fc, Fs, Fv themselves (rather than Fc and
        Fs − Fc), so the config's box on Fc, Fs, Fv is a box on the coefficients.
        """
        v = jnp.asarray(s.v, dtype=jnp.float64)
        e = stribeck_curve(v, 0.0, 1.0, p["vs"], p["delta"])
        sg = sgn(v)
        return Basis(jnp.stack([sg * (1.0 - e), sg * e, v], axis=-1), self.linear_groups())

    def static(self, p: Named, s: Signals, direction: Float[Array, "..."]) -> Float[Array, "..."]:
        return p["Fs"] * direction + jnp.zeros_like(s.t)


@dataclass(frozen=True)
class CoulombViscous(Term):
    """``F_f(v) = Fc·sgn(v) + Fv·v`` [N] (the EMPS published model, no Stribeck drop).

    Parameters: Fc [N] Coulomb level, Fv [N·s/m] viscous coefficient.
    """

    name: ClassVar[str] = "coulomb_viscous"
    role: ClassVar = "friction"

    def parameters(self) -> tuple[Param, ...]:
        return (
            Param("Fc", "N", 0.0, 1e4, 0.0, null=0.0),
            Param("Fv", "N*s/m", 0.0, 1e5, 0.0, null=0.0),
        )

    def force(self, p: Named, s: Signals) -> Float[Array, "..."]:
        return p["Fc"] * sgn(s.v) + p["Fv"] * s.v

    def linear_groups(self) -> Groups:
        return (("Fc",), ("Fv",))

    def basis(self, p: Named, s: Signals) -> Basis:
        """Columns ``[sgn(v), v]`` [1, m/s], shape [..., 2]; coefficients Fc, Fv."""
        v = jnp.asarray(s.v, dtype=jnp.float64)
        return Basis(jnp.stack([sgn(v), v], axis=-1), self.linear_groups())

    def static(self, p: Named, s: Signals, direction: Float[Array, "..."]) -> Float[Array, "..."]:
        return p["Fc"] * direction + jnp.zeros_like(s.t)
