"""Units of a linear or rotary axis: one table every label, table, report and plot reads.

A friction model of a sliding body and of a rotating one are the same equation,
``J·θ̈ = τ_p − τ_f`` instead of ``m·ẍ = F_p − F_f``: only the units change. The model terms
declare their parameters in the linear SI units (``"N"``, ``"m/s"``, ``"N*s/m"``, ``"kg"``);
:func:`axis_unit` maps such a unit to the axis's own, and :class:`AxisUnits` holds the
labels of the signals.

==============  ================  =====================
quantity        linear            rotary
==============  ================  =====================
position        m                 rad
velocity        m/s               rad/s
acceleration    m/s²              rad/s²
force           N                 N·m
inertia         kg                kg·m²
viscous coeff.  N·s/m             N·m·s/rad
==============  ================  =====================

The axis kind comes from the config (``[model].axis``) or the recording (root attr
``axis``); both default to ``"linear"``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from fricjax.errors import FricjaxError, where

Axis = Literal["linear", "rotary"]
AXES: tuple[str, ...] = ("linear", "rotary")


@dataclass(frozen=True)
class AxisUnits:
    """Unit strings of one axis kind (see the module table)."""

    kind: Axis
    position: str
    velocity: str
    acceleration: str
    force: str
    inertia: str
    viscous: str
    #: the word for the equation's force and for the moving mass
    force_word: str
    inertia_word: str
    #: the inertial force of the equation of motion: m·a, or J·α on a rotary axis
    inertial: str = "m·a"

    @property
    def force_sq(self) -> str:
        """Unit of a squared force (cost, EMS): ``N²`` or ``(N·m)²``."""
        return f"{self.force}²" if "·" not in self.force else f"({self.force})²"

    def label(self, quantity: str, symbol: str) -> str:
        """``"symbol [unit]"`` for ``quantity`` in position, velocity, acceleration, force,
        inertia, viscous, force_sq."""
        return f"{symbol} [{getattr(self, quantity)}]"

    def signal_units(self) -> dict[str, str]:
        """Unit of each signal ``fricjax simulate`` compares (x, v, a, force, actuation)."""
        return {
            "x": self.position,
            "v": self.velocity,
            "a": self.acceleration,
            "force": self.force,
            "actuation": self.force,
        }

    def period(self, length: float) -> str:
        """A spatial period in words: ``"0.0063 m of travel"`` or
        ``"6.28 rad (once per revolution)"``."""
        if self.kind == "rotary":
            per_rev = 2.0 * math.pi / length if length > 0 else math.inf
            if abs(per_rev - round(per_rev)) < 0.02 and round(per_rev) >= 1:
                k = round(per_rev)
                times = "once" if k == 1 else "twice" if k == 2 else f"{k} times"
                return f"{length:.3g} rad ({times} per revolution)"
            return f"{length:.3g} rad ({per_rev:.3g} times per revolution)"
        return f"{length:.3g} m of travel"


LINEAR = AxisUnits(
    kind="linear",
    position="m",
    velocity="m/s",
    acceleration="m/s²",
    force="N",
    inertia="kg",
    viscous="N·s/m",
    force_word="force",
    inertia_word="mass",
)
ROTARY = AxisUnits(
    kind="rotary",
    position="rad",
    velocity="rad/s",
    acceleration="rad/s²",
    force="N·m",
    inertia="kg·m²",
    viscous="N·m·s/rad",
    force_word="torque",
    inertia_word="moment of inertia",
    inertial="J·α",
)

# Linear SI unit of a term's parameter (as the terms write it) -> its rotary counterpart.
_ROTARY_OF = {
    "N": "N·m",
    "m": "rad",
    "m/s": "rad/s",
    "m/s²": "rad/s²",
    "kg": "kg·m²",
    "N*s/m": "N·m·s/rad",
    "N·s/m": "N·m·s/rad",
    "N*s²/m²": "N·m·s²/rad²",
}
# Spellings a user may type for the same unit.
_SPELLINGS = {
    "N*s/m": ("N*s/m", "Ns/m", "N.s/m", "N·s/m"),
    "N·m": ("N·m", "N*m", "Nm", "N.m"),
    "kg·m²": ("kg·m²", "kg*m^2", "kg*m2", "kgm2", "kg·m^2", "kg m^2"),
    "N·m·s/rad": ("N·m·s/rad", "N*m*s/rad", "Nms/rad", "N.m.s/rad"),
    "N·m·s²/rad²": ("N·m·s²/rad²", "N*m*s^2/rad^2"),
    "rad/s²": ("rad/s²", "rad/s^2"),
    "m/s²": ("m/s²", "m/s^2"),
    "1": ("1", "", "-"),
}


def axis_units(kind: str, *, source: str = "config") -> AxisUnits:
    """The :class:`AxisUnits` of ``"linear"`` or ``"rotary"``; anything else is refused."""
    if kind == "linear":
        return LINEAR
    if kind == "rotary":
        return ROTARY
    raise FricjaxError(
        f"{where(source, 'axis')}: must be one of {', '.join(map(repr, AXES))}, got {kind!r}"
    )


def axis_unit(unit: str, axis: AxisUnits) -> str:
    """A term's linear SI ``unit`` as the axis writes it (``"N"`` -> ``"N·m"`` on a rotary
    axis; ``"N/u"`` -> ``"N·m/u"``); units without a length (rad, rad/s, s, 1) unchanged."""
    if axis.kind == "linear":
        return "N·s/m" if unit == "N*s/m" else unit
    if unit.startswith("N/"):
        return "N·m/" + unit[2:]
    return _ROTARY_OF.get(unit, unit)


def same_unit(expected: str, given: str) -> bool:
    """Whether ``given`` is a spelling of ``expected`` (``expected`` ending in ``/u``: any
    ``N/<unit of the input>``, or ``N·m/<unit>``)."""
    if expected.endswith("/u"):
        head = expected[:-1]
        return given.startswith(head) or any(
            given.startswith(s + "/") for s in _SPELLINGS.get(head[:-1], ())
        )
    canon = next((k for k, v in _SPELLINGS.items() if expected in v), expected)
    return given.strip() in _SPELLINGS.get(canon, (canon,))
