"""The force balance ``m·a = F_p − F_f`` (seed eq. 3/5) over a list of terms.

Residual and cost follow seed eq. (11): ``r_i = F(i) − F*(i)`` with the measured force
``F = m·a`` and the model force ``F* = F_p − F_f``; ``cost = Σ r_i²`` [N²];
``EMS = cost / n`` [N²], the error mean square of the seed's Table 4.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import jax.numpy as jnp
from jaxtyping import Array, Float

from fricjax.errors import FricjaxError
from fricjax.model.term import Signals, Term
from fricjax.params import Named, Param

MASS = Param("mass", "kg", 1e-6, 1e6, 1.0, free=False)


@dataclass(frozen=True)
class Model:
    """An ordered tuple of terms; hashable, so jitted functions may close over it."""

    terms: tuple[Term, ...]

    def __post_init__(self) -> None:
        names = [t.name for t in self.terms]
        if len(set(names)) != len(names):
            raise FricjaxError(f"model: a term is listed twice ({', '.join(names)})")
        owner: dict[str, str] = {}
        for term in self.terms:
            for q in term.param_names:
                if q in owner:
                    raise FricjaxError(
                        f"model: parameter {q!r} claimed by both {owner[q]} and {term.name}"
                    )
                owner[q] = term.name

    @property
    def name(self) -> str:
        return "+".join(t.name for t in self.terms)

    def parameters(self) -> tuple[Param, ...]:
        """Every parameter the terms read, plus the moving mass."""
        return (*(q for t in self.terms for q in t.parameters()), MASS)

    def with_terms(self, extra: Sequence[Term]) -> Model:
        return Model((*self.terms, *extra))

    # -- forces ---------------------------------------------------------------------------
    def drive(self, p: Named, s: Signals) -> Float[Array, "..."]:
        """``F_p`` [N]: sum of the drive terms (seed eq. 4, or g·u)."""
        total = jnp.zeros_like(jnp.asarray(s.t, dtype=jnp.float64))
        for term in self.terms:
            if term.role == "drive":
                total = total + term.force(p, s)
        return total

    def friction(self, p: Named, s: Signals) -> Float[Array, "..."]:
        """``F_f`` [N]: sum of the friction terms (seed eq. 1), resisting motion."""
        total = jnp.zeros_like(jnp.asarray(s.t, dtype=jnp.float64) * s.v)
        for term in self.terms:
            if term.role == "friction":
                total = total + term.force(p, s)
        return total

    def static(self, p: Named, s: Signals, direction: Float[Array, "..."]) -> Float[Array, "..."]:
        """Friction limit at rest for impending motion in ``direction`` (±1) [N]."""
        total = jnp.zeros_like(jnp.asarray(s.t, dtype=jnp.float64) * direction)
        for term in self.terms:
            if term.role == "friction":
                total = total + term.static(p, s, direction)
        return total

    def force(self, p: Named, s: Signals) -> Float[Array, "..."]:
        """Model force ``F* = F_p − F_f`` [N] (seed eq. 5)."""
        return self.drive(p, s) - self.friction(p, s)

    def residual(self, p: Named, s: Signals, a: Float[Array, " n"]) -> Float[Array, " n"]:
        """Equation-error residual ``m·a − F*`` [N], shape [n] (seed eq. 11 summand)."""
        return p["mass"] * a - self.force(p, s)


def cost(residual: Float[Array, " n"]) -> Float[Array, ""]:
    """Seed eq. (11): ``Σ r_i²`` [N²]."""
    return jnp.sum(residual**2)


def ems(residual: Float[Array, " n"]) -> Float[Array, ""]:
    """Error mean square ``Σ r_i² / n`` [N²], as in the seed's Table 4."""
    return jnp.mean(residual**2)
