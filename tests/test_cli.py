"""The CLI: thin commands over the API, one-line errors and exit status 2 on user mistakes."""

from __future__ import annotations

import contextlib
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from fricjax.data.recording import read_recording

ROOT = Path(__file__).resolve().parents[1]


def fricjax(*args: str, cwd: Path = ROOT) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "fricjax.cli", *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_help_lists_the_commands() -> None:
    out = fricjax("--help")
    assert out.returncode == 0
    for command in ("twin", "inspect", "import-mat", "cost", "identify", "show", "sweep"):
        assert command in out.stdout


def test_twin_regenerates_the_bundled_file(tmp_path: Path) -> None:
    # Bit for bit only on the machine that wrote it: another CPU rounds the simulator's last
    # digits differently. The time grid and mass are exact; x agrees far below its 24 µm noise.
    out = fricjax("twin", str(tmp_path / "t.h5"))
    assert out.returncode == 0, out.stderr
    made, bundled = read_recording(tmp_path / "t.h5"), read_recording(ROOT / "data/paper_twin.h5")
    np.testing.assert_array_equal(made.t, bundled.t)
    assert made.mass == bundled.mass and made.x.shape == bundled.x.shape
    np.testing.assert_allclose(made.x, bundled.x, rtol=0, atol=1e-3 * 24e-6)


def test_cost_at_truth_is_near_the_noise_level() -> None:
    out = fricjax("cost", "data/paper_twin.h5", "--config", "configs/paper.toml")
    assert out.returncode == 0, out.stderr
    line = next(s for s in out.stdout.splitlines() if s.startswith("EMS"))
    ems = float(line.split()[-1])
    # 24 µm of white noise on x through the seed's preprocessing: ~5e3 N² on the interior
    assert 3e3 < ems < 8e3


def test_inspect_writes_a_figure(tmp_path: Path) -> None:
    png = tmp_path / "twin.png"
    out = fricjax("inspect", "data/paper_twin.h5", "--png", str(png))
    assert out.returncode == 0, out.stderr
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "velocity reversals" in out.stdout and "272" in out.stdout
    # the twin's x noise is 24 µm; the recording's own high band must say so within 15 %
    line = next(s for s in out.stdout.splitlines() if s.startswith("x noise"))
    assert abs(float(line.split()[2]) / 24e-6 - 1) < 0.15


def test_identify_then_show(tmp_path: Path) -> None:
    res = tmp_path / "r.h5"
    out = fricjax(
        "identify",
        "data/paper_twin.h5",
        "--config",
        "configs/paper.toml",
        "--method",
        "rdsa",
        "--chains",
        "4",
        "--max-levels",
        "15",
        "--quiet",
        "--out",
        str(res),
    )
    assert out.returncode == 0, out.stderr
    assert "EMS" in out.stdout
    with h5py.File(res) as f:
        run = f["runs/rdsa"]
        assert run["params/value"].shape == (26,)
        assert run["traces/best_cost"].shape[1] == 4
        assert f.attrs["recording_sha256"] == read_recording(ROOT / "data/paper_twin.h5").sha256()
        cost = run.attrs["cost"]
    assert np.isfinite(cost)
    shown = fricjax("show", str(res))
    assert shown.returncode == 0, shown.stderr
    for table in ("Table 1", "Table 2", "Table 3", "Table 4"):
        assert table in shown.stdout
    assert "truth" in shown.stdout and "err" in shown.stdout


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["cost", "data/missing.h5", "--config", "configs/paper.toml"], "missing.h5"),
        (["cost", "data/paper_twin.h5", "--config", "configs/nope.toml"], "nope.toml"),
        (["identify", "data/paper_twin.h5", "--method", "tabu"], "unknown method 'tabu'"),
        (["show", "data/paper_twin.h5"], "not a fricjax results file"),
    ],
)
def test_user_mistakes_give_one_line_and_exit_2(args: list[str], needle: str) -> None:
    out = fricjax(*args)
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and needle in lines[0]


def test_a_misspelt_parameter_is_refused_not_dropped(tmp_path: Path) -> None:
    # Dropped in silence, "Fcc" would leave Fc at its config init and the cost would be
    # reported at parameters the user never gave.
    params = tmp_path / "p.toml"
    params.write_text("Fc = 400.0\nFcc = 3.0\n")
    out = fricjax(
        "cost", "data/paper_twin.h5", "--config", "configs/paper.toml", "--params", str(params)
    )
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and f"{params}: Fcc: unknown parameter of the model" in lines[0]


def test_ctrl_c_exits_130_not_0(monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    # A script that runs diagnoses in a loop must see an interrupted one as failed.
    import fricjax.api
    import fricjax.cli
    from fricjax.cli import main

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    def exit_now(code: int) -> None:  # os._exit would end pytest itself
        raise SystemExit(code)

    monkeypatch.setattr(fricjax.api, "diagnose_recording", interrupted)
    monkeypatch.setattr(fricjax.cli, "_exit_now", exit_now)
    monkeypatch.setattr(sys, "argv", ["fricjax", "diagnose", "data/paper_twin.h5"])
    with pytest.raises(SystemExit) as exc:
        main()
    assert exc.value.code == 130
    assert capsys.readouterr().err.strip() == "interrupted"


def test_nan_in_a_csv_is_named(tmp_path: Path) -> None:
    csv = tmp_path / "bad.csv"
    csv.write_text("t,x\n" + "\n".join(f"{k / 1000},{'nan' if k == 7 else k}" for k in range(40)))
    out = fricjax(
        "cost",
        str(csv),
        "--config",
        "configs/paper.toml",
        "--mass",
        "45",
        "--params",
        str(ROOT / "configs" / "paper.toml"),
    )
    assert out.returncode == 2
    assert "bad.csv" in out.stderr and "NaN" in out.stderr


def test_diagnosis_progress_shows_each_stage_live_on_a_terminal_and_as_log_lines_elsewhere() -> (
    None
):
    import io

    from rich.console import Console

    from fricjax.cli import _stage_progress
    from fricjax.diagnose.stages import StageEvent

    tty = Console(file=io.StringIO(), force_terminal=True, width=100)
    with _stage_progress(False, tty) as on_stage:
        assert on_stage is not None
        on_stage(StageEvent("base_fit", "base fit: search and refine", 0.0))
        on_stage(StageEvent("candidates", "output-error fit of impact", 12.5))
    # the finished stage is printed with the time the next one began
    from rich.text import Text

    assert "12.5 s done: base_fit" in Text.from_ansi(tty.file.getvalue()).plain
    with _stage_progress(True, tty) as on_stage:
        assert on_stage is None
    # not a terminal (a log file): plain lines, no control characters
    with _stage_progress(False, Console(file=io.StringIO())) as on_stage:
        assert on_stage is not None
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        on_stage(StageEvent("candidates", "output-error fit of impact", 12.5))
    assert err.getvalue() == "    12.5 s  candidates: output-error fit of impact\n"


def test_a_time_limit_that_is_not_positive_is_refused() -> None:
    out = fricjax("diagnose", "data/paper_twin.h5", "--time-limit", "0", "--out", "/nonexistent")
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "--time-limit: must be > 0" in lines[0]
