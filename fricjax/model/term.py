"""The interface every model term implements.

A model is a list of terms (seed eq. 3/5: ``m·a = F_p − F_f``). A term is a small frozen,
hashable object holding only *structure* (e.g. the number of harmonics); its numbers come in
as the named-parameter mapping ``p``. Two roles:

* ``"drive"`` terms return a force *on* the body (added to ``F_p``);
* ``"friction"`` terms return the friction ``F_f`` that *resists* motion (subtracted), and
  also say what they do at rest (``static``) so the simulator can decide stick or slip.

New physics (LuGre, drag, position-dependent friction, ...) is a new term; no other term
changes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Literal, NamedTuple

import jax.numpy as jnp
from jaxtyping import Array, Float

from fricjax.params import Named, Param


class Signals(NamedTuple):
    """Kinematic signals a term may depend on; arrays broadcast together.

    Shapes are ``[n]`` for equation-error evaluation over a recording and ``[]`` inside the
    simulator. Units: t [s], x [m], v [m/s], u [u_unit of the recording] (zeros if absent).
    """

    t: Float[Array, "..."]
    x: Float[Array, "..."]
    v: Float[Array, "..."]
    u: Float[Array, "..."]


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


def sgn(v: Float[Array, "..."]) -> Float[Array, "..."]:
    """sgn(v) with sgn(0) = 0 (seed eq. 1), so friction stays odd in v."""
    return jnp.sign(v)
