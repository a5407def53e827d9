"""The interface every model term implements.

A model is a list of terms (seed eq. 3/5: ``m·a = F_p − F_f``). A term is a small frozen,
hashable object holding only *structure* (e.g. the number of harmonics); its numbers come in
as the named-parameter mapping ``p``. Two roles:

* ``"drive"`` terms return a force *on* the body (added to ``F_p``);
* ``"friction"`` terms return the friction ``F_f`` that *resists* motion (subtracted), and
  also say what they do at rest (``static``) so the simulator can decide stick or slip.

New physics (LuGre, drag, position-dependent friction, ...) is a new term; no other term
changes.

Linear declarations (variable projection, Golub–Pereyra). A term may also say which of its
parameters enter its force *linearly* once the others (the nonlinear ones: ω, vs, δ, ...) are
fixed. It then provides

* :meth:`Term.linear_groups` — the linear parameter names, in groups (static);
* :meth:`Term.basis` — regressor columns ``Φ [..., k]`` that depend only on the nonlinear
  parameters and the signals;
* :meth:`Term.to_linear` / :meth:`Term.from_linear` — the map between the group's named
  parameters and the ``k`` linear coefficients ``c`` (built on the vector maps
  :meth:`Term.linear_coefficients` / :meth:`Term.linear_values`, which a term with a
  non-identity map overrides),

such that, for every ``p``, ``force(p, s) = Φ(p_nl, s) · to_linear(p)`` (exactly, up to
rounding). A group of ``g`` names has ``g`` coefficients and ``g`` columns; most groups are
one parameter with coefficient = the parameter itself, but a group may be a nonlinear
reparametrisation of its names (the harmonic drive's ``(Fp_i, φ_i) ↔ (A_i, B_i)``), which is
why the maps belong to the term. A term without ``linear_groups`` is fully nonlinear: the
model it is part of is then not separable.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Literal, NamedTuple

import jax.numpy as jnp
from jaxtyping import Array, Float

from fricjax.errors import FricjaxError
from fricjax.params import Named, Param

#: Linear parameter names of a term, grouped: each group maps as a unit to as many
#: coefficients (and regressor columns) as it has names.
Groups = tuple[tuple[str, ...], ...]


class Signals(NamedTuple):
    """Kinematic signals a term may depend on; arrays broadcast together.

    Shapes are ``[n]`` for equation-error evaluation over a recording and ``[]`` inside the
    simulator. Units: t [s], x [m], v [m/s], u [u_unit of the recording] (zeros if absent).
    """

    t: Float[Array, "..."]
    x: Float[Array, "..."]
    v: Float[Array, "..."]
    u: Float[Array, "..."]


class Basis(NamedTuple):
    """Regressor columns of the linear parameters: ``force = columns · c`` (see module doc).

    ``columns [..., k]``: one column per linear coefficient, in the order of ``groups``
    (units: force per unit of the coefficient, e.g. ``[1]`` for a force in N, ``[m/s]``
    for a viscous coefficient in N·s/m). ``groups``: the linear names, grouped (static);
    ``k = Σ len(group)``.
    """

    columns: Float[Array, "... k"]
    groups: Groups

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(n for g in self.groups for n in g)


@dataclass(frozen=True)
class Term:
    """Base class of model terms. Subclasses set ``name``/``role`` and implement ``force``."""

    name: ClassVar[str] = ""
    role: ClassVar[Literal["drive", "friction"]] = "drive"

    def parameters(self) -> tuple[Param, ...]:
        """The parameters this term reads, with units, default bounds and null values."""
        raise NotImplementedError

    def force(self, p: Named, s: Signals) -> Float[Array, "..."]:
        """Drive force on the body [N] (role "drive") or resisting friction F_f [N]."""
        raise NotImplementedError

    def static(self, p: Named, s: Signals, direction: Float[Array, "..."]) -> Float[Array, "..."]:
        """Friction limit at rest for impending motion in ``direction`` (±1) [N].

        Equals ``lim_{v→0, sgn v = direction} force``; a drive term has none (zero).
        """
        return jnp.zeros_like(s.t * direction)

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(q.name for q in self.parameters())

    # -- linear declarations (optional; see module docstring) ---------------------------
    def linear_groups(self) -> Groups | None:
        """The linear parameters, grouped; ``None`` (default): the term is fully nonlinear."""
        return None

    @property
    def has_basis(self) -> bool:
        return self.linear_groups() is not None

    @property
    def linear_names(self) -> tuple[str, ...]:
        return tuple(n for g in (self.linear_groups() or ()) for n in g)

    def basis(self, p: Named, s: Signals) -> Basis:
        """Columns ``Φ [..., k]`` with ``force(p, s) = Φ · to_linear(p)``; they read only the
        nonlinear parameters of ``p`` (the linear ones may hold any value)."""
        raise no_basis(self)

    def linear_coefficients(self, values: Float[Array, " k"], p: Named) -> Float[Array, " k"]:
        """Coefficients ``c [k]`` from the linear parameters' values ``[k]`` (order of
        :attr:`linear_names`); default: ``c = values``. ``p`` supplies anything else the
        map needs. Vector in, vector out, so a solver can map many at once."""
        return values

    def linear_values(self, coef: Float[Array, " k"], p: Named) -> Float[Array, " k"]:
        """Inverse of :meth:`linear_coefficients`: values ``[k]`` (order of
        :attr:`linear_names`) from coefficients ``c [k]``; default: ``values = c``."""
        return coef

    def to_linear(self, p: Named) -> Float[Array, " k"]:
        """Linear coefficients ``c [k]`` of the named parameters in ``p``."""
        values = jnp.stack([jnp.asarray(p[n], dtype=jnp.float64) for n in self._linear()])
        return self.linear_coefficients(values, p)

    def from_linear(self, coef: Float[Array, " k"], p: Named) -> dict[str, Float[Array, ""]]:
        """Named linear parameters from coefficients ``c [k]`` (inverse of :meth:`to_linear`)."""
        values = self.linear_values(coef, p)
        return {n: values[i] for i, n in enumerate(self._linear())}

    def _linear(self) -> tuple[str, ...]:
        if self.linear_groups() is None:
            raise no_basis(self)
        return self.linear_names


def no_basis(term: Term) -> FricjaxError:
    """The one-line error for a term without linear declarations (model not separable)."""
    return FricjaxError(
        f"model: term {term.name} declares no linear basis, so the model is not separable "
        "(use the full search: --no-separable or [search].separable = false)"
    )


def sgn(v: Float[Array, "..."]) -> Float[Array, "..."]:
    """sgn(v) with sgn(0) = 0 (seed eq. 1), so friction stays odd in v."""
    return jnp.sign(v)
