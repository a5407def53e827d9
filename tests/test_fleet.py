"""Fleet of independent fits (fricjax.fleet): same answers as single fits, every recording
accounted for, drift flagged by its stated statistic, the file round-trips."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fricjax.api import fleet_recordings
from fricjax.config import load_config
from fricjax.data.recording import Recording, write_recording
from fricjax.data.twin import AXIS_TRUTH, axis_twin
from fricjax.fleet import run_fleet
from fricjax.identify import IdentifySettings, identify
from fricjax.io.fleet import read_fleet
from fricjax.report.fleet import drift

ROOT = Path(__file__).resolve().parents[1]
AXIS = ROOT / "configs" / "axis.toml"
#: Coulomb level of the recording that drifted (the others: AXIS_TRUTH's 20 N).
DRIFTED_FC = 26.0


def write_axis_fleet(folder: Path, n: int = 3) -> list[Path]:
    """``n`` recordings of one axis (noise seeds 0..n-1, a ``date`` attribute each), the
    last with its Coulomb level moved to DRIFTED_FC, plus a CSV without the drive input."""
    import h5py

    paths = []
    for s in range(n):
        truth = {**AXIS_TRUTH, "Fc": DRIFTED_FC} if s == n - 1 else None
        rec, _ = axis_twin(seed=s, truth=truth, name=f"run{s}")
        path = write_recording(rec, folder / f"run{s}.h5")
        with h5py.File(path, "a") as f:
            f.attrs["date"] = f"2026-0{n - s}-01"  # dates run backwards to the file names
        paths.append(path)
    bad = Recording(t=np.arange(50) / 1000.0, x=np.zeros(50), mass=95.0, name="no_u")
    paths.append(write_recording(bad, folder / "no_u.h5"))
    return paths


@pytest.fixture(scope="module")
def fleet_run(tmp_path_factory: pytest.TempPathFactory):
    folder = tmp_path_factory.mktemp("fleet")
    write_axis_fleet(folder)
    out = folder / "fleet.h5"
    fleet, result, report, png = fleet_recordings([folder], AXIS, out, order_by="date")
    return folder, out, fleet, result, report, png


def test_fleet_fit_equals_single_fit_within_a_tenth_of_sigma(fleet_run) -> None:
    _, _, fleet, *_ = fleet_run
    from fricjax.api import load

    cfg = load_config(AXIS)
    settings = IdentifySettings.from_tables(cfg.tables, source=cfg.source)
    checked = 0
    for fit in fleet.fits:
        if not fit.ok:
            continue
        _, _, problem = load(fit.path, cfg)
        single = identify(problem, settings)
        assert single.names == fleet.names
        np.testing.assert_array_less(np.abs(fit.value - single.value), 0.1 * single.std)
        np.testing.assert_allclose(fit.std, single.std, rtol=1e-6)
        checked += 1
    assert checked == 3


def test_every_recording_is_in_the_file_with_its_status(fleet_run) -> None:
    _, out, fleet, *_ = fleet_run
    back = read_fleet(out)
    assert [f.name for f in back.fits] == ["no_u", "run0", "run1", "run2"]
    status = {f.name: (f.status, f.reason) for f in back.fits}
    assert status["no_u"][0] == "failed" and "/u" in status["no_u"][1]
    assert all(status[f"run{s}"] == ("ok", "") for s in range(3))
    np.testing.assert_array_equal(back.values, fleet.values)  # NaN row for the failure
    np.testing.assert_array_equal(back.stds, fleet.stds)
    assert back.attrs["n_ok"] == 3 and back.attrs["n_failed"] == 1
    # the fitted mass is the generating one within 1.2 %: the equation error's own bias
    # (the noisy, filtered acceleration is a regressor) is 0.7-1.1 % here, 5-8 honest σ of
    # the noise's spread (the white-residual σ, 5x larger, used to hide it)
    j = back.names.index("mass")
    ok = np.isfinite(back.values[:, j])
    assert np.all(np.abs(back.values[ok, j] - AXIS_TRUTH["mass"]) < 0.012 * AXIS_TRUTH["mass"])


def test_report_flags_the_drifted_coulomb_level_only(fleet_run) -> None:
    _, _, fleet, result, report, png = fleet_run
    moved = {f.name for f, m in zip(fleet.fits, result.moved, strict=True) if m}
    assert moved == {"run2"}
    j = fleet.names.index("Fc")
    i = [f.name for f in fleet.fits].index("run2")
    assert result.z[i, j] > result.threshold
    text = report.read_text()
    # ordered by the date attribute: run2 (2026-01-01) first, run0 (2026-03-01) last
    assert text.index("| run2 |") < text.index("| run1 |") < text.index("| run0 |")
    assert "no_u" in text.split("## Failures")[1]
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_drift_false_alarm_rate_is_at_most_alpha_on_an_unchanged_plant() -> None:
    # 400 fleets of 30 recordings x 3 parameters, Gaussian estimates with known but
    # unequal σ around one truth: the Bonferroni flag fires in at most α of the fleets.
    rng = np.random.default_rng(1)
    alarms = 0
    for _ in range(400):
        std = rng.uniform(0.5, 2.0, size=(30, 3))
        values = 10.0 + std * rng.standard_normal((30, 3))
        alarms += bool(drift(values, std).moved.any())
    assert alarms / 400 <= 0.05 + 2 * np.sqrt(0.05 * 0.95 / 400)


def test_drift_z_is_the_leave_one_out_score() -> None:
    values = np.array([[1.0], [2.0], [4.0]])
    std = np.array([[1.0], [1.0], [2.0]])
    z = drift(values, std).z
    # recording 2 against the mean of 1 and 2 (1.5, variance 1/2): (4 - 1.5)/sqrt(4 + 0.5)
    assert z[2, 0] == pytest.approx(2.5 / np.sqrt(4.5))


@pytest.mark.slow  # compiles a second program (width 1)
def test_shard_size_does_not_change_the_answers(fleet_run) -> None:
    from fricjax.api import load
    from fricjax.fleet import Member

    _, _, fleet, *_ = fleet_run
    cfg = load_config(AXIS)
    settings = IdentifySettings.from_tables(cfg.tables, source=cfg.source)
    members = []
    for f in fleet.fits:
        if f.ok:
            members.append(Member(f.name, f.path, f.order, load(f.path, cfg)[2]))
    ones = run_fleet(members, settings, shard_size=1)
    by_name = {f.name: f for f in fleet.fits}
    for fit in ones:
        ref = by_name[fit.name]
        np.testing.assert_array_less(np.abs(fit.value - ref.value), 0.1 * ref.std)


def test_cli_fleet_refuses_a_missing_path_in_one_line(tmp_path: Path) -> None:
    import subprocess
    import sys

    out = subprocess.run(
        [sys.executable, "-m", "fricjax.cli", "fleet", str(tmp_path / "nope"), "--config",
         str(AXIS), "--out", str(tmp_path / "f.h5")],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert out.returncode == 2
    assert out.stderr.strip().count("\n") == 0
    assert "no such recording or directory" in out.stderr


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"workers": 2, "scheduler": "tcp://127.0.0.1:1"}, "not both"),
        ({"workers": 0}, "--workers: must be >= 1"),
        ({"shard_size": 0}, "--shard-size: must be >= 1"),
    ],
)
def test_fleet_usage_mistakes_are_one_line_errors(
    tmp_path: Path, kwargs: dict, message: str
) -> None:
    from fricjax.errors import FricjaxError

    rec, _ = axis_twin(seed=0, duration=0.2)
    path = write_recording(rec, tmp_path / "r.h5")
    with pytest.raises(FricjaxError, match=message):
        fleet_recordings([path], AXIS, tmp_path / "f.h5", **kwargs)
    assert not (tmp_path / "f.h5").exists()
