"""One table of units for linear and rotary axes."""

from __future__ import annotations

import math

import pytest

from fricjax.errors import FricjaxError
from fricjax.units import LINEAR, ROTARY, axis_unit, axis_units, same_unit


def test_rotary_units_are_the_angular_counterparts() -> None:
    assert [axis_unit(u, ROTARY) for u in ("N", "m/s", "N*s/m", "kg", "rad/s", "1")] == [
        "N·m",
        "rad/s",
        "N·m·s/rad",
        "kg·m²",
        "rad/s",
        "1",
    ]
    assert axis_unit("N/u", ROTARY) == "N·m/u"
    assert axis_unit("N", LINEAR) == "N"
    assert (ROTARY.force_sq, LINEAR.force_sq) == ("(N·m)²", "N²")
    assert ROTARY.label("position", "x") == "x [rad]"


def test_a_spatial_period_reads_per_revolution_on_a_rotary_axis() -> None:
    assert ROTARY.period(2 * math.pi) == "6.28 rad (once per revolution)"
    assert ROTARY.period(2 * math.pi / 6) == "1.05 rad (6 times per revolution)"
    assert LINEAR.period(0.0063) == "0.0063 m of travel"


def test_spellings_and_refusals() -> None:
    assert same_unit("N*s/m", "N·s/m") and same_unit("N·m·s/rad", "Nms/rad")
    assert same_unit("N·m/u", "N·m/V") and same_unit("N/u", "N/V")
    assert not same_unit("N", "N·m")
    with pytest.raises(FricjaxError, match="must be one of 'linear', 'rotary'"):
        axis_units("angular")
