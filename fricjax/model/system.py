"""The force balance ``m·a = F_p − F_f`` (seed eq. 3/5) over a list of terms.

Residual and cost follow seed eq. (11): ``r_i = F(i) − F*(i)`` with the measured force
``F = m·a`` and the model force ``F* = F_p − F_f``; ``cost = Σ r_i²`` [N²];
``EMS = cost / n`` [N²], the error mean square of the seed's Table 4.

Separable form (variable projection). When every term declares a linear basis
(:meth:`fricjax.model.term.Term.basis`), the model force and the residual are linear in
the coefficients ``c`` for fixed nonlinear parameters ``p_nl`` (ω, vs, δ):

    F*(p) = Φ_F(p_nl) · c_F,     Φ_F = [Φ_drive,1 … | −Φ_friction,1 …]   (friction subtracts)
    r(p)  = m·a − F*(p) = Ψ(p_nl) · c,    Ψ = [a | −Φ_F],   c = [m, c_F]

so the moving mass is one more linear coefficient (its column is ``a``); when it is fixed,
``m·a`` is simply a known part of the residual.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from fricjax.errors import FricjaxError
from fricjax.model.term import Basis, Groups, Signals, Term, no_basis
from fricjax.params import MASS_DOMAIN, Named, Param

MASS = Param("mass", "kg", 1e-6, 1e6, 1.0, free=False, domain=MASS_DOMAIN)


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

    def overflowing(self, p: Mapping[str, float], s: Signals, limit: float) -> str:
        """Which term's force is too large to square and sum at ``p`` over signals ``s``
        [n]: not finite, or ``max|F|·√n > limit`` (the size whose squares still sum to a
        finite float64). In words, with the term's parameter values ("stribeck (Fc = 30,
        Fv = 1e+300, ...)"); the mass times ``a`` when no term is; "" when none is."""
        named = {k: jnp.asarray(v, dtype=jnp.float64) for k, v in p.items()}
        root_n = float(np.sqrt(np.size(s.t)))
        bad = []
        for term in self.terms:
            size = float(jnp.max(jnp.abs(term.force(named, s))))
            if not size * root_n <= limit:
                values = ", ".join(f"{q} = {float(p[q]):g}" for q in term.param_names if q in p)
                bad.append(f"{term.name} ({values})")
        if not bad and MASS.name in p:
            bad.append(f"the mass times the acceleration (mass = {float(p[MASS.name]):g})")
        return "; ".join(bad)

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

    def rest_force(
        self, p: Named, s: Signals, drive: Float[Array, "..."] | None = None
    ) -> Float[Array, "..."]:
        """Net force on the body at rest [N] (the stick/slip rule of Karnopp):

            F*_rest = 0                     while |F_p| ≤ |F_s(sgn F_p)|   (stuck)
                    = F_p − F_s(sgn F_p)    once the drive exceeds it      (breaking away)

        with ``F_s(d)`` = :meth:`static`. Stateful terms (LuGre bristles) have no pointwise
        static limit and add none here: their force lives in the sliding samples after a
        breakaway, where the bristle state lags. ``drive``: :meth:`drive` at (p, s) when the
        caller has it already.
        """
        drive = self.drive(p, s) if drive is None else drive
        d = jnp.sign(drive)
        limit = jnp.zeros_like(drive * d)
        for term in self.terms:
            if term.role == "friction" and not term.stateful:
                limit = limit + term.static(p, s, d)
        return jnp.where(jnp.abs(drive) <= jnp.abs(limit), 0.0, drive - limit)

    def residual(
        self,
        p: Named,
        s: Signals,
        a: Float[Array, " n"],
        rest: Bool[Array, " n"] | None = None,
    ) -> Float[Array, " n"]:
        """Equation-error residual ``m·a − F*`` [N], shape [n] (seed eq. 11 summand).

        ``rest``: samples taken to be at rest, where ``F*`` is :meth:`rest_force` instead of
        the sliding law. There the measured v is noise around zero (and the filtered v of a
        stuck body smears the breakaway): the sliding law would evaluate ``sgn`` of noise and
        the friction of a body that is not sliding.
        """
        # the drive once for both laws: traced twice, it doubled the diagnosis' compile time
        drive = self.drive(p, s)
        force = drive - self.friction(p, s)
        if rest is not None:
            force = jnp.where(rest, self.rest_force(p, s, drive), force)
        return p["mass"] * a - force

    # -- separable form (see module docstring) --------------------------------------------
    def require_basis(self) -> None:
        """Raise the one-line :class:`FricjaxError` naming the first term without a basis."""
        for term in self.terms:
            if not term.has_basis:
                raise no_basis(term)

    def force_groups(self) -> Groups:
        """Linear names of ``F*`` in column order: the terms' groups, term by term."""
        self.require_basis()
        return tuple(g for term in self.terms for g in (term.linear_groups() or ()))

    def linear_groups(self) -> Groups:
        """Linear names of the residual in column order: ``("mass",)``, then the force's."""
        return ((MASS.name,), *self.force_groups())

    def basis(self, p: Named, s: Signals) -> Basis:
        """``Φ_F [..., k_F]`` with ``F*(p) = Φ_F · to_linear(p)[1:]`` [N per coefficient unit]:
        the drive terms' columns and the friction terms' columns negated."""
        self.require_basis()
        cols = []
        for term in self.terms:
            b = term.basis(p, s).columns
            cols.append(b if term.role == "drive" else -b)
        return Basis(jnp.concatenate(cols, axis=-1), self.force_groups())

    def residual_basis(self, p: Named, s: Signals, a: Float[Array, " n"]) -> Basis:
        """``Ψ [n, 1 + k_F] = [a | −Φ_F]`` with ``residual(p) = Ψ · to_linear(p)`` [N]."""
        phi = self.basis(p, s).columns
        a = jnp.broadcast_to(jnp.asarray(a, dtype=jnp.float64), phi.shape[:-1])
        return Basis(jnp.concatenate([a[..., None], -phi], axis=-1), self.linear_groups())

    def to_linear(self, p: Named) -> Float[Array, " k"]:
        """Coefficients ``c = [m, c_F]`` [k] of the residual basis, from named parameters."""
        self.require_basis()
        parts = [jnp.reshape(jnp.asarray(p[MASS.name], dtype=jnp.float64), (1,))]
        parts += [term.to_linear(p) for term in self.terms]
        return jnp.concatenate(parts)

    def from_linear(self, coef: Float[Array, " k"], p: Named) -> dict[str, Float[Array, ""]]:
        """Named linear parameters (mass included) from coefficients ``c [k]``."""
        values = self.linear_values(coef, p)
        names = [n for g in self.linear_groups() for n in g]
        return {n: values[i] for i, n in enumerate(names)}

    def linear_values(self, coef: Float[Array, " k"], p: Named) -> Float[Array, " k"]:
        """Values of the linear parameters (order of :meth:`linear_groups`) from ``c [k]``."""
        return self._per_term(coef, p, "linear_values")

    def linear_coefficients(self, values: Float[Array, " k"], p: Named) -> Float[Array, " k"]:
        """Coefficients ``c [k]`` from the linear parameters' values (inverse map)."""
        return self._per_term(values, p, "linear_coefficients")

    def _per_term(self, vec: Float[Array, " k"], p: Named, method: str) -> Float[Array, " k"]:
        self.require_basis()
        parts, i = [vec[:1]], 1  # the mass is its own coefficient
        for term in self.terms:
            k = len(term.linear_names)
            parts.append(getattr(term, method)(vec[i : i + k], p))
            i += k
        return jnp.concatenate(parts)


def cost(residual: Float[Array, " n"]) -> Float[Array, ""]:
    """Seed eq. (11): ``Σ r_i²`` [N²]."""
    return jnp.sum(residual**2)


def ems(residual: Float[Array, " n"]) -> Float[Array, ""]:
    """Error mean square ``Σ r_i² / n`` [N²], as in the seed's Table 4."""
    return jnp.mean(residual**2)
