"""``fricjax simulate`` (fricjax.simulation, api.simulate_recording): metrics, files, the
closed loop, and one-line errors with exit status 2."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import h5py
import jax.numpy as jnp
import numpy as np
import pytest

from fricjax.api import simulate_recording
from fricjax.cli import main
from fricjax.config import load_config
from fricjax.data.recording import Recording, read_recording, write_recording
from fricjax.data.twin import DEFAULT_NOISE_STD, PAPER_TRUTH
from fricjax.errors import FricjaxError
from fricjax.model.closed_loop import EMPS_CONTROLLER, simulate_closed_loop
from fricjax.simulation import signal_metrics, simulate_against

ROOT = Path(__file__).resolve().parents[1]
TWIN = ROOT / "data" / "paper_twin.h5"
PAPER = ROOT / "configs" / "paper.toml"
EMPS_TOML = ROOT / "configs" / "emps.toml"
EMPS_TRUTH = {"gain": 35.15065188, "offset": -3.1648, "Fc": 20.3935, "Fv": 203.5034, "mass": 95.1}


def _toml(path: Path, params: dict[str, float]) -> Path:
    path.write_text("".join(f"{k} = {v!r}\n" for k, v in params.items()))
    return path


@pytest.fixture(scope="module")
def truth_file(tmp_path_factory) -> Path:
    # the test hands the twin's truth over as a parameter file: simulate never reads /truth
    return _toml(tmp_path_factory.mktemp("params") / "truth.toml", PAPER_TRUTH)


@pytest.fixture(scope="module")
def cli_run(truth_file, tmp_path_factory):
    out = tmp_path_factory.mktemp("sim")
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "fricjax.cli",
            "simulate",
            str(TWIN),
            "--params",
            str(truth_file),
            "--config",
            str(PAPER),
            "--out",
            str(out),
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    return proc, out


def test_metrics_definitions():
    y = np.array([1.0, 2.0, 3.0, 4.0])
    m = signal_metrics(y + np.array([0.1, -0.1, 0.1, -0.1]), y, "m")
    assert m.rms == pytest.approx(0.1)
    assert m.relative == pytest.approx(100 * 0.2 / np.sqrt(30))
    assert m.fit == pytest.approx(100 * (1 - 0.2 / np.sqrt(5)))
    assert signal_metrics(y, y).fit == 100.0 and signal_metrics(np.full(4, 2.5), y).fit == 0.0


def test_cli_simulate_at_the_truth_fits_x_to_the_noise(cli_run):
    proc, out = cli_run
    assert proc.returncode == 0, proc.stderr
    rows = {line.split()[0]: line.split() for line in proc.stdout.splitlines() if line.strip()}
    assert float(rows["x"][-2]) > 99.0  # fit % (measured 99.54 %: the misfit is the noise)
    assert "open-loop" in proc.stdout and "samples 20..251" in proc.stdout
    metrics = json.loads((out / "simulation.json").read_text())["metrics"]
    # the misfit of x is the 24 µm noise plus the filtered v0's error
    assert DEFAULT_NOISE_STD < metrics["x"]["rms"] < 1.5 * DEFAULT_NOISE_STD
    assert metrics["x"]["fit"] == pytest.approx(float(rows["x"][-2]), abs=0.01)
    assert set(metrics) == {"x", "v", "a", "force"}
    assert metrics["force"]["relative"] == pytest.approx(metrics["a"]["relative"])
    assert (out / "simulation.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_simulation_h5_holds_the_series(cli_run):
    _, out = cli_run
    rec = read_recording(TWIN)
    with h5py.File(out / "simulation.h5", "r") as f:
        t = f["t"][()]
        np.testing.assert_array_equal(t, rec.t[20:252])
        np.testing.assert_array_equal(f["recorded/x"][()], rec.x[20:252])
        sim, res = f["simulated/x"][()], f["residual/x"][()]
        np.testing.assert_array_equal(res, sim - f["recorded/x"][()])
        assert sim[0] == rec.x[20]  # starts at the recorded position of the first kept sample
        assert f["simulated/force"].attrs["unit"] == "N" and f.attrs["mode"] == "open-loop"
        assert json.loads(f.attrs["params"])["Fv"] == PAPER_TRUTH["Fv"]


def test_wrong_parameters_show_in_the_fit():
    cfg = load_config(PAPER)
    rec = read_recording(TWIN)
    good = simulate_against(rec, cfg, PAPER_TRUTH)
    bad = simulate_against(rec, cfg, {**PAPER_TRUTH, "Fv": 1.2 * PAPER_TRUTH["Fv"]})
    assert bad.metrics["x"].fit < good.metrics["x"].fit - 1.0
    assert bad.metrics["v"].rms > 3 * good.metrics["v"].rms


def test_closed_loop_reproduces_a_loop_record(tmp_path):
    """2 s of the EMPS loop (noise-free, at rest for 50 ms): the closed-loop simulation at
    the generating parameters replays position and controller output to rounding."""
    t = np.arange(2000) * 1e-3
    moving = np.maximum(t - 0.05, 0.0)
    ref = 0.05 + 0.02 * np.sin(2 * np.pi * moving)
    p = {k: jnp.asarray(v) for k, v in EMPS_TRUTH.items()}
    traj = simulate_closed_loop(
        load_config(EMPS_TOML).model, p, t, ref, 0.05, 0.0, EMPS_CONTROLLER, substeps=4
    )
    rec = Recording(t=t, x=np.asarray(traj.x), u=np.asarray(traj.u), r=ref, u_unit="V")
    path = write_recording(rec, tmp_path / "loop.h5")
    params = _toml(tmp_path / "p.toml", EMPS_TRUTH)
    report = simulate_recording(path, params=params, config=EMPS_TOML, controller="emps")
    assert report.mode == "closed-loop" and report.files == {}
    assert set(report.metrics) == {"x", "v", "a", "force", "actuation"}
    # the record starts moving at 50 ms, after the trimmed 49 samples: v0 from the filter
    # is the only difference; the loop absorbs it
    assert report.metrics["x"].fit > 99.9 and report.metrics["actuation"].fit > 99.0
    with pytest.raises(FricjaxError, match="/r: missing"):
        simulate_recording(
            write_recording(Recording(t=t, x=rec.x, u=rec.u, u_unit="V"), tmp_path / "nr.h5"),
            params=params,
            config=EMPS_TOML,
            controller="emps",
        )


def _cli(monkeypatch, capsys, *args: str) -> tuple[int, str]:
    monkeypatch.setattr(sys, "argv", ["fricjax", "simulate", *args])
    with pytest.raises(SystemExit) as exc:
        main()
    return int(exc.value.code), capsys.readouterr().err.strip()


def test_bad_input_exits_2_with_one_line(monkeypatch, capsys, tmp_path, truth_file):
    rec = str(TWIN)
    bad_name = _toml(tmp_path / "bad.toml", {**PAPER_TRUTH, "Fx": 1.0})
    cases = [
        ((rec,), "error: simulate: --results/--params: give exactly one of them (neither given)"),
        (
            (rec, "--results", str(tmp_path / "r.h5"), "--params", str(truth_file)),
            "error: simulate: --results/--params: give exactly one of them (both given)",
        ),
        ((rec, "--results", str(tmp_path / "r.h5")), f"error: {tmp_path / 'r.h5'}: results file"),
        ((rec, "--params", str(truth_file)), f"error: {truth_file}: holds no config"),
        (
            (rec, "--params", str(bad_name), "--config", str(PAPER)),
            f"error: {bad_name}: Fx: unknown parameter of the model",
        ),
        (
            (rec, "--params", str(truth_file), "-c", str(PAPER), "--controller", "emps"),
            f"error: {rec}: /r: missing",
        ),
        (
            (rec, "--params", str(truth_file), "-c", str(PAPER), "--substeps", "0"),
            "error: command line: fricjax simulate: Invalid value for '--substeps'",
        ),
    ]
    for args, message in cases:
        code, err = _cli(monkeypatch, capsys, *args)
        assert code == 2 and err.startswith(message), (args, err)
        assert "\n" not in err
