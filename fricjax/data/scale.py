"""Does the recording's scale make physical sense in the units it claims? (unit warnings)

A recording stored in millimetres, degrees or grams still runs: identification then fits
forces 1000 times too large and every parameter ends on its bound, with no hint. These
checks read the preprocessed record (as identification will) and say which unit is
likely wrong. Each is a physical bound, not a tuned threshold:

* **Speed of a linear axis** above :data:`MAX_LINEAR_SPEED` (20 m/s, 72 km/h: twice the
  fastest linear motors and machine-tool slides) while the same record read as millimetres
  would be an ordinary speed: x is likely in mm.
* **Speed of a rotary axis** above :data:`MAX_ROTARY_SPEED` (2000 rad/s, 19 000 rpm, a
  fast spindle) while read as degrees it would be ordinary: the angle is likely in degrees.
* **Inertial force against the measured force**: ``m·a = F − F_f`` with friction
  ``F_f`` opposing the motion, so ``m·max|a|`` can exceed ``max|F|`` only by what friction
  adds while the body decelerates, and friction that large would stop the body. A ratio
  above :data:`MAX_INERTIA_RATIO` (30) means x (or the mass) is too large by about that
  factor: mm for m, g for kg.
"""

from __future__ import annotations

import numpy as np
from jaxtyping import Float

from fricjax.units import AxisUnits

#: Fastest plausible linear axis [m/s] (module docstring).
MAX_LINEAR_SPEED = 20.0
#: Fastest plausible rotary axis [rad/s] (module docstring).
MAX_ROTARY_SPEED = 2000.0
#: Largest plausible m·max|a| / max|F| (module docstring).
MAX_INERTIA_RATIO = 30.0


def unit_warnings(
    x: Float[np.ndarray, " n"],
    v: Float[np.ndarray, " n"],
    a: Float[np.ndarray, " n"],
    mass: float | None,
    units: AxisUnits,
    *,
    force: Float[np.ndarray, " n"] | None = None,
) -> list[str]:
    """One line per implausible scale of a preprocessed record (module docstring).

    Args:
        x, v, a: position, velocity, acceleration in the axis's units, shape [n].
        mass: moving mass [kg] or inertia [kg·m²], None if unknown.
        units: the axis (:mod:`fricjax.units`).
        force: measured force on the body [N or N·m] (filtered like m·a), or None.
    """
    out = []
    v_max = float(np.max(np.abs(v))) if v.size else 0.0
    travel = float(np.ptp(x)) if x.size else 0.0
    if units.kind == "linear" and v_max > MAX_LINEAR_SPEED and v_max * 1e-3 <= MAX_LINEAR_SPEED:
        out.append(
            f"x looks like millimetres, not metres: peak speed {v_max:.3g} m/s and travel "
            f"{travel:.3g} m are beyond any linear axis (< {MAX_LINEAR_SPEED:g} m/s); multiply "
            "x by 1e-3 before identifying (forces would otherwise come out 1000x too large)"
        )
    factor = np.pi / 180.0
    if units.kind == "rotary" and v_max > MAX_ROTARY_SPEED and v_max * factor <= MAX_ROTARY_SPEED:
        out.append(
            f"the angle looks like degrees, not radians: peak speed {v_max:.3g} rad/s is "
            f"beyond a fast spindle (< {MAX_ROTARY_SPEED:g} rad/s); multiply x by pi/180"
        )
    if mass is not None and force is not None and force.size and a.size:
        peak = float(np.max(np.abs(force)))
        inertial = mass * float(np.max(np.abs(a)))
        if peak > 0 and inertial > MAX_INERTIA_RATIO * peak:
            ratio = inertial / peak
            out.append(
                f"{units.inertia_word} x acceleration reaches {inertial:.3g} {units.force}, "
                f"{ratio:.3g} times the largest measured {units.force_word} ({peak:.3g} "
                f"{units.force}), which friction cannot make up: x in "
                f"{'mm' if units.kind == 'linear' else 'degrees'}, or the {units.inertia_word} "
                f"in {'g' if units.kind == 'linear' else 'g·m²'}? (scale by about 1/{ratio:.2g})"
            )
    return out
