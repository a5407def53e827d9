"""Named parameter specifications and the flat-vector <-> named-pytree maps.

Search algorithms see a flat vector ``theta`` of the *free* parameters inside a box
``[lower, upper]``; model terms see a mapping ``name -> value`` that also holds the fixed
parameters. :class:`ParamSpec` converts between the two and is static (hashable), so it can
be closed over by jitted functions while ``theta`` stays a traced array.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from fricjax.errors import FricjaxError, where

Named = Mapping[str, Float[Array, "..."]]


def check_known(named: Mapping[str, float], names: tuple[str, ...], source: str) -> None:
    """Refuse, in one line naming ``source`` and the key, a parameter the model does not
    take: a misspelt name would otherwise be dropped and its default used in silence."""
    for key in named:
        if key not in names:
            raise FricjaxError(
                f"{where(source, key)}: unknown parameter of the model (it takes: "
                f"{', '.join(names)})"
            )


def check_values(named: Mapping[str, float], spec: ParamSpec, source: str) -> None:
    """Refuse, in one line naming ``source`` and the key, a value given for a parameter of
    ``spec`` that is unknown to the model, not a finite number, or outside the parameter's
    physical :class:`Domain` (a mass of 0 kg, a Stribeck velocity of −1 m/s): the cost
    would otherwise be NaN or a force no rig can produce, printed as if it were a result."""
    check_known(named, spec.names, source)
    for key, value in named.items():
        check_value(spec[key], value, where(source, key))


def check_value(p: Param, value: object, loc: str) -> float:
    """``value`` as a float if it is a finite number inside ``p.domain``, else FricjaxError
    naming ``loc``."""
    try:
        if isinstance(value, bool | np.bool_ | str | bytes):
            raise TypeError
        value = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise FricjaxError(f"{loc}: must be a number, got {value!r}") from None
    if not math.isfinite(value):
        raise FricjaxError(f"{loc}: not a finite number ({value})")
    if not p.domain.contains(value):
        raise FricjaxError(
            f"{loc}: {value:g} is outside the physical domain of {p.name} ({p.domain}, {p.unit})"
        )
    return value


@dataclass(frozen=True)
class Domain:
    """The physically meaningful values of a parameter: ``low < value`` (``low_open``) or
    ``low <= value``, and ``value <= high``. Outside it the model is undefined or
    unphysical (division by a zero Stribeck velocity, a non-positive mass)."""

    low: float = -math.inf
    high: float = math.inf
    low_open: bool = False

    def contains(self, value: float) -> bool:
        above = value > self.low if self.low_open else value >= self.low
        return above and value <= self.high

    def __str__(self) -> str:
        parts = []
        if self.low > -math.inf:
            parts.append(f"{'>' if self.low_open else '>='} {self.low:g}")
        if self.high < math.inf:
            parts.append(f"<= {self.high:g}")
        return " and ".join(parts) or "any real number"


#: Any real number (the default: offsets, phases, amplitudes whose sign is a phase shift).
REAL = Domain()
#: Strictly positive: Stribeck velocities, shape exponents, frequencies.
POSITIVE = Domain(0.0, low_open=True)
#: A moving mass [kg] (or a moment of inertia [kg·m²] on a rotary axis): positive and at
#: most 1e8. The heaviest bodies moved on guides or bearings (a ship lift's caisson with its
#: water, ~1e7 kg) are an order of magnitude below, so a larger value is a typo or a wrong
#: unit, not a rig.
MASS_DOMAIN = Domain(0.0, 1e8, low_open=True)


@dataclass(frozen=True)
class Param:
    """One model parameter.

    Attributes:
        name: identifier used by model terms (``"Fc"``, ``"Fp_3"``, ...).
        unit: SI unit string (``"N"``, ``"N*s/m"``, ``"rad/s"``, ``"kg"``, ...).
        lower, upper: prior bounds of the search box (equal for a fixed parameter).
        init: initial / fixed value.
        free: whether identification may change it.
        null: value at which the term has no effect (nested-model tests); NaN if none.
        domain: the physically meaningful values (:class:`Domain`); bounds, initial and
            fixed values, and values read from files must lie in it.
    """

    name: str
    unit: str
    lower: float
    upper: float
    init: float
    free: bool = True
    null: float = math.nan
    domain: Domain = field(default=REAL, compare=False)

    def fixed_at(self, value: float) -> Param:
        """This parameter, fixed at ``value``."""
        return replace(self, init=float(value), free=False)


@dataclass(frozen=True)
class ParamSpec:
    """Ordered collection of :class:`Param`; the free ones form the search vector."""

    params: tuple[Param, ...]
    source: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        seen: set[str] = set()
        for p in self.params:
            if p.name in seen:
                raise FricjaxError(f"{where(self.source, 'params')}: {p.name} defined twice")
            seen.add(p.name)
            _check_param(p, self.source)

    # -- views ----------------------------------------------------------------------------
    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.params)

    @property
    def free(self) -> tuple[Param, ...]:
        return tuple(p for p in self.params if p.free)

    @property
    def free_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.free)

    @property
    def n_free(self) -> int:
        return len(self.free)

    @property
    def lower(self) -> np.ndarray:
        """Lower bounds of the free parameters, shape [d]."""
        return np.array([p.lower for p in self.free], dtype=np.float64)

    @property
    def upper(self) -> np.ndarray:
        """Upper bounds of the free parameters, shape [d]."""
        return np.array([p.upper for p in self.free], dtype=np.float64)

    @property
    def init(self) -> np.ndarray:
        """Initial values of the free parameters, shape [d]."""
        return np.array([p.init for p in self.free], dtype=np.float64)

    def __getitem__(self, name: str) -> Param:
        for p in self.params:
            if p.name == name:
                return p
        raise FricjaxError(f"{where(self.source, 'params')}: unknown parameter {name!r}")

    def __contains__(self, name: object) -> bool:
        return any(p.name == name for p in self.params)

    # -- conversions ----------------------------------------------------------------------
    def unflatten(self, theta: Float[Array, " d"]) -> dict[str, Float[Array, ""]]:
        """Free vector ``theta`` [d] -> ``{name: value}`` for every parameter (fixed included).

        Pure indexing, so it traces under ``jit``/``vmap``/``grad``.
        """
        out: dict[str, Float[Array, ""]] = {}
        i = 0
        for p in self.params:
            if p.free:
                out[p.name] = theta[i]
                i += 1
            else:
                out[p.name] = jnp.asarray(p.init, dtype=jnp.float64)
        return out

    def flatten(self, named: Mapping[str, float]) -> np.ndarray:
        """``{name: value}`` -> free vector [d]; missing free names take their ``init``."""
        unknown = sorted(set(named) - set(self.names))
        if unknown:
            raise FricjaxError(
                f"{where(self.source, 'params')}: unknown parameter {unknown[0]!r} "
                f"(known: {', '.join(self.names)})"
            )
        return np.array([float(named.get(p.name, p.init)) for p in self.free], dtype=np.float64)

    def as_dict(self, theta: Iterable[float] | None = None) -> dict[str, float]:
        """All parameters as plain floats, the free ones taken from ``theta`` (default init)."""
        vals = self.init if theta is None else np.asarray(theta, dtype=np.float64)
        named = self.unflatten(jnp.asarray(vals))
        return {k: float(v) for k, v in named.items()}

    def structural(self) -> ParamSpec:
        """Names, free/fixed and fixed values only (bounds and inits of free parameters
        dropped): what a residual needs. Jitted code keyed on it is shared by problems whose
        specs differ only in bounds (e.g. bounds scaled to each recording)."""
        params = tuple(
            Param(p.name, "", 0.0, 0.0, 0.0)
            if p.free
            else Param(p.name, "", p.init, p.init, p.init, free=False)
            for p in self.params
        )
        return ParamSpec(params)

    # -- editing --------------------------------------------------------------------------
    def with_fixed(self, values: Mapping[str, float]) -> ParamSpec:
        """A copy where the named parameters are fixed at the given values."""
        self.flatten(values)
        params = tuple(p.fixed_at(values[p.name]) if p.name in values else p for p in self.params)
        return replace(self, params=params)

    def extended(self, extra: Iterable[Param]) -> ParamSpec:
        """A copy with ``extra`` parameters appended (names must be new)."""
        return replace(self, params=self.params + tuple(extra))


# A parameter within this fraction of its search range from a bound is "on the bound":
# LM's sine transform reaches a bound only asymptotically, 1e-3 of the range is where its
# gradient has fallen to ~6 % of its interior value.
BOUND_TOL = 1e-3


def on_bound(spec: ParamSpec | None, name: str, value: float) -> str:
    """``"lower"``/``"upper"`` where ``value`` sits on that bound of ``name``'s search
    range (within :data:`BOUND_TOL` of it), else ``""``."""
    if spec is None or name not in spec.names or not spec[name].free:
        return ""
    p = spec[name]
    tol = BOUND_TOL * (p.upper - p.lower)
    if value <= p.lower + tol:
        return "lower"
    if value >= p.upper - tol:
        return "upper"
    return ""


def at_bounds(spec: ParamSpec, params: dict[str, float]) -> dict[str, str]:
    """``{name: "lower"|"upper"}`` for each of ``params`` on a bound of its search range: a
    limit the fit ran into, not a measurement."""
    return {n: side for n, v in params.items() if (side := on_bound(spec, n, float(v)))}


def _check_param(p: Param, source: str) -> None:
    loc = where(source, f"[params].{p.name}")
    for label, value in (("value", p.init), ("lower", p.lower), ("upper", p.upper)):
        check_value(p, value, f"{loc}: {label}")
    if p.lower > p.upper:
        raise FricjaxError(f"{loc}: lower bound {p.lower:g} > upper bound {p.upper:g}")
    if not (p.lower <= p.init <= p.upper):
        what = "fixed value" if not p.free else "initial value"
        raise FricjaxError(
            f"{loc}: {what} {p.init:g} outside its bounds [{p.lower:g}, {p.upper:g}]"
        )
