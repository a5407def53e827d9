"""The installed ``fricjax`` command: every usage mistake is one line and exit 2, outputs
never replace inputs, refusals of the machine exit 1, an interrupted run has its status."""

from __future__ import annotations

import errno
import os
import signal
import subprocess
import sys
from pathlib import Path

import h5py
import pytest

import fricjax.cli
from fricjax.cli import main
from fricjax.errors import EXIT

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = Path(sys.executable).parent / "fricjax"
TWIN = str(ROOT / "data" / "paper_twin.h5")
PAPER = str(ROOT / "configs" / "paper.toml")


def installed(*args: str, cwd: Path = ROOT, **kwargs) -> subprocess.CompletedProcess[str]:
    """The console script, importing fricjax from this checkout (worktrees included)."""
    env = {**os.environ, "PYTHONPATH": str(ROOT), "FRICJAX_COMPILATION_CACHE": "0"}
    return subprocess.run(
        [str(SCRIPT), *args],
        cwd=cwd,
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
        **kwargs,
    )


pytestmark = pytest.mark.skipif(not SCRIPT.exists(), reason=f"no installed script {SCRIPT}")


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--bogus"], "No such option: --bogus"),
        (["identify"], "fricjax identify: Missing argument 'recording'"),
        (["identfy", TWIN], "No such command 'identfy'"),
        (["identify", TWIN, "--chains", "abc"], "'--chains'"),
        (["identify", TWIN, "--chains", "0"], "'--chains'"),
        (["identify", TWIN, "--chains"], "'--chains' requires an argument"),
        (["identify", TWIN, "--seed", str(2**64)], "'--seed'"),
        (["identify", TWIN, "--seed", "-1"], "'--seed'"),
        (["sweep", TWIN, "--restarts", "0"], "'--restarts'"),
        (["simulate", TWIN, "--substeps", "0"], "'--substeps'"),
        (["validate", TWIN], "Missing option '--results'"),
        (["diagnose"], "Missing argument 'RECORDING...'"),
        (["bench", "nope"], "No such command 'nope'"),
        (["twin", "--duration", "x"], "'--duration'"),
    ],
)
def test_a_usage_mistake_is_one_line_and_exit_2(args: list[str], needle: str) -> None:
    out = installed(*args)
    lines = out.stderr.strip().splitlines()
    assert out.returncode == EXIT["mistake"] == 2, out.stderr
    assert len(lines) == 1 and "Traceback" not in out.stderr, out.stderr
    assert lines[0].startswith("error: command line: ") and needle in lines[0]


def test_version_and_bare_command() -> None:
    from importlib import metadata

    version = installed("--version")
    assert (version.returncode, version.stdout.strip()) == (
        0,
        f"fricjax {metadata.version('fricjax')}",
    )
    bare = installed()  # asking what the tool does is not a mistake: help, exit 0
    assert bare.returncode == 0 and "identify" in bare.stdout and bare.stderr == ""


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["identify", "rec.h5", "-c", "c.toml", "--out", "rec.h5"], "the input recording"),
        (["identify", "rec.h5", "-c", "c.toml", "--out", "link.h5"], "the input recording"),
        (["identify", "rec.h5", "-c", "c.toml", "--out", "c.toml"], "the input --config"),
        (["sweep", "rec.h5", "-c", "c.toml", "--out", "rec.h5"], "the input recording"),
        (["validate", "rec.h5", "--results", "c.toml", "--out", "c.toml"], "the input --results"),
        (
            ["simulate", "simulation.h5", "--params", "c.toml", "-c", "c.toml", "--out", "."],
            "the input recording",
        ),
        (["diagnose", "models.h5", "-c", "c.toml", "--out", "."], "the input recording"),
        (["import-mat", "rec.h5", "rec.h5"], "the input MAT"),
        (["inspect", "rec.h5", "--png", "rec.h5"], "the input recording"),
        (["identify", "rec.h5", "-c", "c.toml", "--out", "folder"], "is a folder"),
        (["identify", "rec.h5", "-c", "c.toml", "--out", "rec.h5/r.h5"], "is a file, not"),
    ],
)
def test_an_output_never_replaces_an_input(tmp_path: Path, args: list[str], needle: str) -> None:
    data = Path(TWIN).read_bytes()
    for name in ("rec.h5", "simulation.h5", "models.h5"):
        (tmp_path / name).write_bytes(data)
    (tmp_path / "c.toml").write_text(Path(PAPER).read_text())
    (tmp_path / "link.h5").symlink_to(tmp_path / "rec.h5")
    (tmp_path / "folder").mkdir()
    out = installed(*args, cwd=tmp_path)
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2 and len(lines) == 1 and needle in lines[0], out.stderr
    assert all((tmp_path / n).read_bytes() == data for n in ("rec.h5", "simulation.h5"))
    assert (tmp_path / "c.toml").read_text() == Path(PAPER).read_text()


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["identify", TWIN, "--chains", "1000000000"], "chains need about"),
        (
            ["simulate", TWIN, "--params", PAPER, "-c", PAPER, "--substeps", "1000000000"],
            "RK4 steps",
        ),
        (
            ["validate", TWIN, "--results", PAPER, "-c", PAPER, "--decimate", "100000"],
            "anti-alias filter",
        ),
        (["sweep", TWIN, "--methods", ","], "nothing to run"),
        (["sweep", TWIN, "--seed", str(2**64 - 1), "--restarts", "2"], "64-bit key"),
    ],
)
def test_sizes_that_cannot_run_are_refused_with_the_estimate(
    tmp_path: Path, args: list[str], needle: str
) -> None:
    out = installed(*args, "--out", str(tmp_path / "o.h5" if args[0] != "simulate" else tmp_path))
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2 and len(lines) == 1 and needle in lines[0], out.stderr
    assert list(tmp_path.iterdir()) == []  # refused before anything was written


def _exit_raises(monkeypatch: pytest.MonkeyPatch) -> None:
    def exit_now(code: int) -> None:  # os._exit would end pytest itself
        raise SystemExit(code)

    monkeypatch.setattr(fricjax.cli, "_exit_now", exit_now)


def test_a_full_disk_is_one_line_exit_1_and_the_earlier_file_survives(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from fricjax.io import atomic

    out = tmp_path / "twin.h5"
    out.write_bytes(Path(TWIN).read_bytes())  # an earlier output
    before = out.read_bytes()

    def full(fh, data: bytes) -> None:
        fh.write(data[: len(data) // 2])
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(atomic, "_write_fully", full)
    with pytest.raises(SystemExit) as exc:
        main(["twin", str(out), "--seed", "1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == EXIT["machine"] == 1
    assert err == [
        f"error: {out}: cannot write (No space left on device); free some space and run again"
    ]
    assert out.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["twin.h5"]


def test_ctrl_c_in_the_polish_keeps_the_search_best_and_exits_3(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    import fricjax.identify

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(fricjax.identify, "_polish", interrupted)
    _exit_raises(monkeypatch)
    res = tmp_path / "r.h5"
    args = [
        "identify",
        TWIN,
        "-c",
        PAPER,
        "--method",
        "rdsa",
        "--chains",
        "4",
        "--max-levels",
        "10",
        "--no-separable",
        "--quiet",
        "--out",
        str(res),
    ]
    with pytest.raises(SystemExit) as exc:
        main(args)
    assert exc.value.code == EXIT["partial"] == 3
    assert "holds the search's best point, not polished" in capsys.readouterr().err
    with h5py.File(res) as f:
        run = f["runs/rdsa"]
        assert run.attrs["interrupted"] and not run.attrs["refined"]
        # the search's best point is what was kept: its cost, not a refined one
        assert run.attrs["cost"] == run.attrs["cost_search"]


@pytest.mark.slow
def test_sigint_during_a_simulation_exits_130_with_a_line(tmp_path: Path) -> None:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "FRICJAX_COMPILATION_CACHE": "0"}
    proc = subprocess.Popen(
        [
            str(SCRIPT),
            "simulate",
            TWIN,
            "--params",
            PAPER,
            "-c",
            PAPER,
            "--substeps",
            "400",
            "--out",
            str(tmp_path / "sim"),
        ],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        proc.wait(timeout=8)  # still importing, compiling or simulating
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode in (EXIT["interrupted"], 0), err  # 0: finished before the signal
    if proc.returncode:
        assert err.strip().splitlines()[-1] == "interrupted" and "Traceback" not in err
