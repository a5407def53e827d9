"""The diagnosis report: every figure with its unit, sentences from the numbers of the table
beside them, bounds flagged, the HTML self-contained; end to end (slow) on a record with a
visible finding, rendered by a real headless browser when one is installed."""

from __future__ import annotations

import math
import re
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from fricjax.diagnose.report import (
    fit_rows,
    fit_sentence,
    length,
    params_text,
    where_text,
)
from fricjax.diagnose.run import at_bounds, on_bound
from fricjax.params import Param, ParamSpec
from fricjax.report.document import Heading, Image, Para, Table, to_html, to_markdown
from fricjax.report.plots import plt, save

ROOT = Path(__file__).resolve().parents[2]


def _fit(**after: float) -> SimpleNamespace:
    before = {"ems": 32355.0, "bic": 117.4, "whiteness_p": 0.43, "simulation_rms_m": 0.0529}
    before["output_error_cost"] = 1000.0
    return SimpleNamespace(fit={"before": before, "after": {**before, **after}})


def test_lengths_are_written_in_a_unit_that_keeps_three_figures() -> None:
    assert length(2.622e-5) == "26.2 µm"
    assert length(0.0529) == "52.9 mm"
    assert length(1.5) == "1.5 m"
    assert length(math.nan) == "not computed"


def test_the_fit_sentence_quotes_the_table_it_stands_beside() -> None:
    """Position RMS 52.9 → 47.2 mm is −10.8 %, and an output error that falls by 99.7 % is
    not rounded to "100 % less": the sentence and the table carry the same figures."""
    diag = _fit(ems=20000.0, simulation_rms_m=0.0472, output_error_cost=3.0)
    rows = {r[0].split(" [")[0]: r for r in fit_rows(diag)}
    text = fit_sentence(diag)
    sim = rows["position RMS of one simulation over the whole record"]
    assert (sim[1], sim[2], sim[3]) == ("52.9", "47.2", "-10.8 %")
    assert "52.9 → 47.2 mm (-10.8 %)" in text
    oe = rows["output error of 0.05 s simulated segments"]
    assert oe[3] == "-99.7 %" and "(-99.7 %" in text
    assert (
        "EMS 32355 → 20000 N² (-38.2 %)" in text
        and rows["EMS, mean squared force residual"][3] == "-38.2 %"
    )


def test_a_simulation_that_could_not_run_is_said_so_not_printed_as_nan() -> None:
    diag = _fit(simulation_rms_m=math.nan)
    sim = next(r for r in fit_rows(diag) if r[0].startswith("position RMS"))
    assert sim[2] == "not computed" and "nan" not in fit_sentence(diag)


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
    diag = SimpleNamespace(selection=SimpleNamespace(spec=spec, steps=[]))
    shown, bounds = params_text(diag, {"mass_eps": 0.3})
    assert shown == "mass_eps = 0.3"
    ((name, why),) = bounds
    assert name == "mass_eps" and "upper bound" in why and "[-0.3, 0.3]" in why
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


# -- end to end ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def harmonic_report(tmp_path_factory: pytest.TempPathFactory):
    """0.272 s paper twin with a 300 N harmonic at 60 Hz (named as extra_harmonic)."""
    import fricjax.diagnose.catalogue as cat
    from fricjax.api import diagnose_recording
    from fricjax.data.recording import write_recording
    from fricjax.data.twin import PAPER_MODEL, PAPER_TRUTH, paper_twin

    term, params = cat.ExtraHarmonic(), {"harm_A": 300.0, "harm_B": 0.0, "harm_f": 60.0}
    rec, truth = paper_twin(
        duration=0.272,
        seed=5,
        model=PAPER_MODEL.with_terms([term]),
        truth={**PAPER_TRUTH, **params},
    )
    tmp = tmp_path_factory.mktemp("harmonic")
    path = write_recording(rec, tmp / "short.h5", truth=truth)
    return diagnose_recording(
        path,
        ROOT / "configs" / "paper.toml",
        out=tmp / "out",
        overrides={"n_mc": 400, "max_terms": 2},
    )


@pytest.mark.slow
def test_the_finding_figure_shows_the_fitted_term_and_before_differs_from_after(
    harmonic_report,
) -> None:
    from fricjax.diagnose.report import residuals, term_force

    diag, paths = harmonic_report
    first = diag.findings[0]
    assert first["effect"] == "extra_harmonic"
    before, after = residuals(diag)
    term = term_force(diag, first)
    assert term is not None
    # the term carries the 60 Hz force the base left: its amplitude at 60 Hz is of the
    # hidden 300 N, and the residual after it is smaller than before
    dt = float(diag.problem.t[1] - diag.problem.t[0])
    f = np.fft.rfftfreq(term.size, dt)
    k = np.argmin(np.abs(f - 60.0))
    assert 150.0 < 2 * np.abs(np.fft.rfft(term))[k] / term.size < 450.0
    assert np.mean(after**2) < 0.8 * np.mean(before**2)
    assert paths["finding_1"].name == "finding_1_extra_harmonic.png"
    report = paths["report"].read_text()
    assert "f = 60" in report and "Hz" in report and "## Next steps" in report


@pytest.mark.slow
def test_the_html_report_renders_in_a_headless_browser(harmonic_report, tmp_path: Path) -> None:
    import shutil

    if not any(shutil.which(b) for b in ("chromium", "chromium-browser", "google-chrome")):
        pytest.skip("no chromium on PATH (Debian: apt-get install chromium)")
    _, paths = harmonic_report
    png = tmp_path / "report.png"
    done = subprocess.run(
        [
            sys.executable,
            str(ROOT / "benchmarks" / "report_screenshot.py"),
            str(paths["html"].parent),
            "--png",
            str(png),
            "--width",
            "1000",
            "--height",
            "1800",
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert png.stat().st_size > 20_000  # text, tables and figures, not a blank page
