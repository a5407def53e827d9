"""Unit warnings: a recording whose scale is physically implausible in its stated units."""

from __future__ import annotations

import numpy as np

from fricjax.data.scale import unit_warnings
from fricjax.units import LINEAR, ROTARY

T = np.arange(4000) / 1000.0
OMEGA = 2 * np.pi * 0.5


def slide(scale: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """x, v, a of a 0.2 m stroke at 0.5 Hz (peak 0.31 m/s), x multiplied by ``scale``."""
    x = 0.1 * np.sin(OMEGA * T)
    return (
        scale * x,
        scale * 0.1 * OMEGA * np.cos(OMEGA * T),
        -scale * 0.1 * OMEGA**2 * np.sin(OMEGA * T),
    )


def test_a_plausible_slide_gives_no_warning() -> None:
    x, v, a = slide(1.0)
    force = 20.0 * 0.1 * OMEGA**2 * np.sin(OMEGA * T) + 15.0  # m·a plus friction
    assert unit_warnings(x, v, a, 20.0, LINEAR, force=force) == []


def test_the_same_slide_in_millimetres_is_named() -> None:
    x, v, a = slide(1000.0)
    force = 20.0 * 0.1 * OMEGA**2 * np.sin(OMEGA * T) + 15.0  # forces are still in N
    lines = unit_warnings(x, v, a, 20.0, LINEAR, force=force)
    assert len(lines) == 2
    assert "millimetres" in lines[0] and "multiply x by 1e-3" in lines[0]
    assert "x in mm" in lines[1]
    # without a force sensor the speed alone still tells (314 m/s for a 0.2 m rig)
    assert len(unit_warnings(x, v, a, 20.0, LINEAR)) == 1


def test_a_rotary_angle_in_degrees_is_named() -> None:
    t = np.arange(2000) / 1000.0
    w = 2 * np.pi * 100.0 * 0.9  # 90 % of 6000 rpm, in degrees/s it is 3.2e4
    deg = 180 / np.pi
    x, v, a = deg * w * t, deg * w * np.ones_like(t), np.zeros_like(t)
    lines = unit_warnings(x, v, a, 1e-3, ROTARY)
    assert len(lines) == 1 and "degrees" in lines[0] and "pi/180" in lines[0]
    assert unit_warnings(x / deg, v / deg, a, 1e-3, ROTARY) == []
