"""Plain-text figures of the reports (fricjax.report.tables)."""

from __future__ import annotations

import math

from fricjax.report.tables import p_text


def test_a_p_value_that_underflows_is_bounded_not_zero() -> None:
    assert p_text(0.00123) == "p = 0.0012"
    assert p_text(0.0) == "p < 1e-300"  # F's tail below the smallest double: not zero
    assert p_text(5e-324) == "p < 1e-300"
    assert p_text(1e-300) == "p = 1e-300"
    assert p_text(math.nan) == "p = nan"
