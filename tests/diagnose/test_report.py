"""The diagnosis report: every figure with its unit, bounds flagged as bounds, Markdown and
the self-contained HTML saying the same (end to end: tests/diagnose/test_judge.py)."""

from __future__ import annotations

import math
import re
from pathlib import Path
from types import SimpleNamespace

from fricjax.diagnose.report import length, params_text, where_text
from fricjax.params import Param, ParamSpec, at_bounds, on_bound
from fricjax.report.document import Heading, Image, Para, Table, to_html, to_markdown
from fricjax.report.plots import plt, save


def test_lengths_are_written_in_a_unit_that_keeps_three_figures() -> None:
    assert length(2.622e-5) == "26.2 µm"
    assert length(0.0529) == "52.9 mm"
    assert length(1.5) == "1.5 m"
    assert length(math.nan) == "not computed"


def test_a_parameter_on_its_bound_is_named_as_such() -> None:
    spec = ParamSpec((Param("mass_eps", "1", -0.3, 0.3, 0.0, null=0.0),))
    assert on_bound(spec, "mass_eps", 0.3) == "upper"
    assert on_bound(spec, "mass_eps", -0.2999999) == "lower"
    assert on_bound(spec, "mass_eps", 0.29) == ""
    fixed = ParamSpec((Param("mass", "kg", 45.0, 45.0, 45.0, free=False),))
    assert on_bound(fixed, "mass", 45.0) == ""  # a fixed value is given, not fitted
    # diagnosis.json flags a finding's parameters on a bound as such
    assert at_bounds(spec, {"mass_eps": 0.3}) == {"mass_eps": "upper"}
    assert at_bounds(spec, {"mass_eps": 0.1}) == {}


def test_a_finding_size_on_its_bound_is_reported_as_a_limit_with_its_range() -> None:
    """A servo record's mass error of +42.9 % sat exactly on its bound: the report says the
    search stopped there, with the range, instead of quoting it as a measured value."""
    spec = ParamSpec((Param("mass_eps", "1", -0.3, 0.3, 0.0, null=0.0),))
    diag = SimpleNamespace(final=SimpleNamespace(problem=SimpleNamespace(spec=spec)))
    shown, bounds = params_text(diag, {"mass_eps": 0.3})
    assert shown == "mass_eps = 0.3"
    (why,) = bounds
    assert "`mass_eps`" in why and "upper bound" in why and "[-0.3, 0.3]" in why
    assert "not a measurement" in why
    assert params_text(diag, {"mass_eps": 0.1})[1] == []


def test_locations_carry_their_units() -> None:
    text = where_text({"velocity_mps": [0.0, 0.04], "frequency_hz": 60.03})
    assert text == "v from 0 to 0.04 m/s; f = 60.03 Hz"
    assert "7 velocity reversals" in where_text({"reversals_s": [1, 2, 3, 4, 5, 6, 7]})


def test_markdown_and_html_say_the_same_and_the_html_needs_nothing_outside(tmp_path: Path) -> None:
    fig, ax = plt.subplots(figsize=(2, 1))
    ax.plot([0, 1], [0, 1])
    png = save(fig, tmp_path / "f.png")
    blocks = [
        Heading("Diagnosis of `a<b>.h5`", 1),
        Para("EMS **falls** by 3 %", "note"),
        Table(("figure", "value"), (("|v| band", "< 0.01 m/s"),)),
        Image(png, "a figure"),
    ]
    md, html = to_markdown(blocks), to_html(blocks, "t")
    assert "| \\|v\\| band | < 0.01 m/s |" in md and "![a figure](f.png)" in md
    assert "<code>a&lt;b&gt;.h5</code>" in html and "<strong>falls</strong>" in html
    srcs = re.findall(r'src="([^"]+)"', html)
    assert len(srcs) == 1 and srcs[0].startswith("data:image/png;base64,")
    assert "http" not in html.replace("<!DOCTYPE html>", "")


def test_a_diagnosis_cut_short_never_says_nothing_is_missing() -> None:
    from fricjax.diagnose.report import NOTHING, verdict
    from fricjax.diagnose.stages import Clock

    clock = Clock(total=10.0, now=lambda: 0.0)
    assert verdict([], clock, NOTHING).startswith("**Nothing is missing**")
    # the base fit's further rounds left out: the base may sit above its minimum
    clock.skip("base_fit", "base fit: further Levenberg–Marquardt rounds")
    cut = verdict([], clock, NOTHING)
    assert "Nothing is missing" not in cut and cut.startswith("**Time limit (10 s in all)")
