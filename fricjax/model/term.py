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

import math
from dataclasses import dataclass
from typing import ClassVar, Literal, NamedTuple

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from fricjax.errors import FricjaxError
from fricjax.params import Named, Param

#: Linear parameter names of a term, grouped: each group maps as a unit to as many
#: coefficients (and regressor columns) as it has names.
Groups = tuple[tuple[str, ...], ...]


class TimeGrid(NamedTuple):
    """A uniform time base ``t_k = t_0 + k·Δt`` (k = 0..n−1) split as

        t_k = outer[j] + inner[r],     k = j·R + r,   0 ≤ r < R,   j = 0..J−1     [s]

    with ``outer [J] = t_{jR}`` (the recorded times) and ``inner [R] = r·Δt``; ``J·R ≥ n``
    (the last row may run past the recording: its extra entries are dropped). A term that
    needs a periodic function of ``t`` then evaluates it at the ``J + R`` times (31 for the
    paper twin's 232 samples) and combines them (angle addition,
    :func:`fricjax.model.drive.phasor`) instead of at ``n``. Built by :func:`time_grid`;
    data leaves, so it traces and vmaps with the signals.
    """

    outer: Float[Array, " J"]
    inner: Float[Array, " R"]

    def arrange(self, x: Float[np.ndarray, " n"]) -> Float[np.ndarray, "J R"]:
        """``x [n]`` in the grid layout ``[J, R]``, sample ``k`` at ``[k // R, k % R]``; the
        ``J·R − n`` entries past the end repeat the last sample (finite values for the
        caller to mask out)."""
        j, r = self.outer.shape[-1], self.inner.shape[-1]
        x = np.asarray(x)
        return np.pad(x, (0, j * r - x.shape[0]), mode="edge").reshape(j, r)


class Signals(NamedTuple):
    """Kinematic signals a term may depend on; arrays broadcast together.

    Shapes are ``[n]`` for equation-error evaluation over a recording, ``[J, R]`` for the
    grid layout of :class:`fricjax.problem.GridCost` (models without a stateful term), ``[]``
    inside the simulator. Units: t [s], x [m], v [m/s], u [u_unit of the recording] (zeros
    if absent).
    """

    t: Float[Array, "..."]
    x: Float[Array, "..."]
    v: Float[Array, "..."]
    u: Float[Array, "..."]

    @property
    def grid(self) -> TimeGrid | None:
        """The :class:`TimeGrid` of ``t`` when known (:class:`GridSignals`), else None."""
        return None


class GridSignals(Signals):
    """:class:`Signals` of a recording on a uniform time base, with its :class:`TimeGrid`
    ``grid`` as a hint that terms may use *instead of* ``t`` for periodic functions of time
    (the harmonic drive does, :func:`fricjax.model.drive.phasor`).

    Still the 4-tuple ``(t, x, v, u)`` for unpacking and, for JAX, a pytree of those four
    arrays: anything that rebuilds the signals (``_replace``, ``jax.tree.map``, passing
    them through a ``vmap``/``jit`` boundary) gets them without the hint, which is safe —
    a term then evaluates ``t`` itself. Whoever builds one guarantees that ``grid``
    describes ``t`` (:func:`time_grid` checks a time base; :func:`grid_layout` the shapes).
    """

    def __new__(
        cls,
        t: Float[Array, "..."],
        x: Float[Array, "..."],
        v: Float[Array, "..."],
        u: Float[Array, "..."],
        grid: TimeGrid | None = None,
    ) -> GridSignals:
        self = super().__new__(cls, t, x, v, u)
        self.__dict__["_grid"] = grid
        return self

    @property
    def grid(self) -> TimeGrid | None:
        return self.__dict__.get("_grid")


def grid_layout(grid: TimeGrid | None, t: Float[Array, "..."]) -> Literal["flat", "grid"] | None:
    """How the signals of shape ``t.shape`` relate to ``grid`` (static shapes only):
    ``"flat"``: ``t [n]`` with ``(J − 1)·R < n ≤ J·R`` (the recording's sample order);
    ``"grid"``: ``t [J, R]``, sample ``k = j·R + r`` at ``[j, r]`` (padded past ``n``,
    :meth:`TimeGrid.arrange`); ``None``: no grid, or it does not fit ``t``."""
    if grid is None:
        return None
    j, r = grid.outer.shape[-1], grid.inner.shape[-1]
    shape = tuple(jnp.shape(t))
    if shape == (j, r):
        return "grid"
    if len(shape) == 1 and (j - 1) * r < shape[0] <= j * r:
        return "flat"
    return None


#: Largest ``|outer[j] + inner[r] − t_k|`` that :func:`time_grid` accepts, in units of
#: ``ε·max|t|`` (a few roundings of the largest time; anything beyond is not a uniform grid).
GRID_TOLERANCE_ULPS = 4.0

#: Largest inner length R of :func:`time_grid`'s default split (J + R sines, and R
#: multiply-adds per sample to keep them out of XLA's per-sample loop,
#: :func:`fricjax.model.drive.phasor`).
MAX_INNER = 16


def time_grid(t: Float[np.ndarray, " n"], inner: int | None = None) -> TimeGrid | None:
    """The :class:`TimeGrid` of a uniform time base ``t [n]`` [s], or ``None`` if there is none.

    ``inner`` = R (default ``min(⌈√n⌉, MAX_INNER)``: ``⌈√n⌉`` minimises the J + R
    evaluations, the cap bounds the per-sample cost of using them). ``Δt`` is the
    mean step ``(t_{n−1} − t_0)/(n − 1)``. Returns ``None`` unless ``t`` is 1-D, finite,
    has at least 4 samples, and ``max_k |outer[j] + inner[r] − t_k| ≤ 4·ε·max|t|``
    (ε = 2⁻⁵², :data:`GRID_TOLERANCE_ULPS`; measured ≤ 0.8·ε·max|t| on exact grids): a
    recording whose steps are uniform only to its jitter tolerance (1e-6) keeps the plain
    per-sample evaluation, so using the grid never moves a time by more than a few
    roundings.
    """
    t = np.asarray(t, dtype=np.float64)
    if t.ndim != 1 or t.shape[0] < 4 or not np.isfinite(t).all():
        return None
    n = t.shape[0]
    r = int(inner) if inner is not None else min(math.isqrt(n - 1) + 1, MAX_INNER)
    if not 1 <= r <= n:
        return None
    dt = (t[-1] - t[0]) / (n - 1)
    outer = t[::r]
    offsets = np.arange(r) * dt
    rebuilt = (outer[:, None] + offsets[None, :]).reshape(-1)[:n]
    tol = GRID_TOLERANCE_ULPS * np.finfo(np.float64).eps * float(np.max(np.abs(t)))
    if not np.max(np.abs(rebuilt - t)) <= tol:
        return None
    return TimeGrid(jnp.asarray(outer), jnp.asarray(offsets))


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
    #: True for a term that needs the whole recording in order (a scan over the samples,
    #: e.g. a bristle state): it works in the equation error over ``[n]`` signals, but
    #: neither in the pointwise simulator nor in the ``[J, R]`` layout of
    #: :class:`fricjax.problem.GridCost`. False (the default): the force at a sample
    #: depends on that sample's signals (and ``p``) only.
    stateful: ClassVar[bool] = False

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
