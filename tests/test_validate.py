"""Validation metrics (IDIM equation error, simulation error), the DIDIM fit and the
``fricjax validate`` command, on a synthetic closed-loop run with known parameters."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from fricjax.config import load_config
from fricjax.data.recording import Recording, write_recording
from fricjax.errors import FricjaxError
from fricjax.io.results import ResultsFile, RunResult, provenance, write_results
from fricjax.model.closed_loop import EMPS_CONTROLLER, CascadePD, simulate_closed_loop
from fricjax.problem import build_problem
from fricjax.validate import (
    equation_error,
    fit_simulation_error,
    format_validation,
    initial_state,
    open_loop_rmse,
    parse_controller,
    simulation_error,
    simulation_rmse,
    validate_model,
    validate_recording,
)

ROOT = Path(__file__).resolve().parents[1]
EMPS_TOML = ROOT / "configs" / "emps.toml"
N = 3000
DT = 1e-3
TRUTH = {"gain": 35.15065188, "offset": -3.1648, "Fc": 20.3935, "Fv": 203.5034, "mass": 95.1}


@pytest.fixture(scope="module")
def cfg():
    return load_config(EMPS_TOML)


@pytest.fixture(scope="module")
def closed_loop_rec(cfg) -> Recording:
    """3 s of the EMPS loop tracking a 1 Hz, 2 cm sine with 2 V pulses, noise-free.

    The body rests (held by Coulomb friction) for the first 50 ms, so the record's first
    samples give the initial state exactly and a re-simulation can reproduce it.
    """
    t = np.arange(N) * DT
    moving = np.maximum(t - 0.05, 0.0)
    ref = 0.05 + 0.02 * np.sin(2 * np.pi * moving)
    pulses = 2.0 * ((moving % 0.5) < 0.1) * (t >= 0.05)
    p = {k: jnp.asarray(v) for k, v in TRUTH.items()}
    traj = simulate_closed_loop(cfg.model, p, t, ref, 0.05, 0.0, EMPS_CONTROLLER, pulses)
    assert np.all(np.asarray(traj.x)[:50] == 0.05)
    return Recording(
        t=t, x=np.asarray(traj.x), u=np.asarray(traj.u), r=ref, u_unit="V", name="loop"
    )


def test_closed_loop_resimulation_reproduces_the_record_at_the_truth(cfg, closed_loop_rec):
    s = simulation_error(closed_loop_rec, cfg, TRUTH, controller=EMPS_CONTROLLER)
    assert s.mode == "closed-loop" and s.n == N - 2 * 49
    # [%]: the same loop and input w; the simulation starts at the first kept sample with
    # the preprocessed velocity there (as `fricjax simulate` does), whose filter error is all
    # that separates it from the record
    assert s.position < 1e-3 and s.force < 0.2
    # v and a of the record come from the filter, the simulated ones are exact
    assert s.velocity < 0.5 and s.acceleration < 10.0
    off = simulation_error(
        closed_loop_rec, cfg, {**TRUTH, "Fv": 1.1 * TRUTH["Fv"]}, controller=EMPS_CONTROLLER
    )
    assert off.force > 10 * s.force + 0.1  # a 10 % viscous error shows in the force
    assert off.position < 0.01  # but hardly in the position: the loop absorbs it


def test_equation_error_is_the_idim_relative_error(cfg, closed_loop_rec):
    problem = build_problem(closed_loop_rec, cfg)
    p = {k: jnp.asarray(v) for k, v in TRUTH.items()}
    r = np.asarray(problem.model.residual(p, problem.signals, jnp.asarray(problem.a)))
    tau = TRUTH["gain"] * problem.u
    m = equation_error(closed_loop_rec, cfg, TRUTH)
    assert m.tau == "g·u" and m.n == problem.n and m.decimate == 1
    assert m.rel_error == pytest.approx(np.linalg.norm(r) / np.linalg.norm(tau), rel=1e-12)
    assert m.error_norm == pytest.approx(np.linalg.norm(r), rel=1e-12)
    assert m.ems == pytest.approx(np.mean(r**2), rel=1e-12)
    assert m.error_std == pytest.approx(np.std(r), rel=1e-12)
    m10 = equation_error(closed_loop_rec, cfg, TRUTH, decimate_by=10)
    assert m10.n == -(-problem.n // 10) and m10.decimate == 10
    # Even at the truth the sampled loop leaves an equation error: the held drive has
    # content above the 100 Hz filter that m·a lacks; decimation (40 Hz) removes most.
    assert m10.rel_error < 0.6 * m.rel_error
    worse = equation_error(closed_loop_rec, cfg, {**TRUTH, "mass": 80.0}, decimate_by=10)
    assert worse.rel_error > 3 * m10.rel_error


def test_harmonic_drive_model_uses_m_a_as_tau(paper_config, twin_path):
    from fricjax.data.recording import read_recording
    from fricjax.data.twin import read_truth

    rec = read_recording(twin_path)
    truth = {k: v for k, v in read_truth(twin_path).items() if isinstance(v, int | float)}
    v = validate_model(rec, paper_config, truth, simulate_run=False)
    problem = build_problem(rec, paper_config)
    r = problem.residual(problem.theta(truth))
    assert v.equation.tau == "m·a" and v.simulation is None
    assert v.equation.rel_error == pytest.approx(
        np.linalg.norm(r) / np.linalg.norm(rec.mass * problem.a), rel=1e-9
    )


def test_open_loop_when_there_is_no_controller(cfg, closed_loop_rec):
    s = simulation_error(closed_loop_rec, cfg, TRUTH)
    assert s.mode == "open-loop" and s.force is None
    text = format_validation(validate_model(closed_loop_rec, cfg, TRUTH, decimate_by=10))
    assert "open-loop" in text and "decimated by 10" in text and "relative error" in text


@pytest.mark.slow  # ~20 s: LM through 3000 closed-loop steps, forward-mode Jacobian
def test_didim_fit_recovers_the_generating_parameters(cfg, closed_loop_rec):
    start = {**TRUTH, "Fv": 180.0, "Fc": 25.0, "offset": 0.0, "mass": 110.0}
    fit = fit_simulation_error(closed_loop_rec, cfg, start, EMPS_CONTROLLER)
    for k in ("Fv", "Fc", "offset", "mass"):
        assert fit.params[k] == pytest.approx(TRUTH[k], rel=1e-8), k
    assert fit.cost < 1e-10  # N², from 1e5 at the start


def test_missing_parameter_and_reference_refused(cfg, closed_loop_rec):
    with pytest.raises(FricjaxError) as err:
        equation_error(closed_loop_rec, cfg, {"gain": 35.0, "Fc": 1.0}, source="p.toml")
    assert str(err.value).startswith("p.toml: offset: missing")
    from dataclasses import replace

    with pytest.raises(FricjaxError) as err:
        fit_simulation_error(replace(closed_loop_rec, r=None), cfg, TRUTH, EMPS_CONTROLLER)
    assert "/r: missing" in str(err.value) and "\n" not in str(err.value)


def test_parse_controller():
    assert parse_controller("emps") == EMPS_CONTROLLER
    assert parse_controller("kp=2, kv=3") == CascadePD(2.0, 3.0, 10.0)
    assert parse_controller(None) is None
    for text, msg in (
        ("kp=1", "kv: missing"),
        ("kp=1,kv=x", "kv: not a number"),
        ("kp=1,kv=2,ki=3", "'ki=3' is not one of"),
        ("kp=1,kv=2,u_max=0", "u_max"),
    ):
        with pytest.raises(FricjaxError, match=msg):
            parse_controller(text)


def _results_file(path: Path, cfg_text: str) -> Path:
    names = ["offset", "Fc", "Fv", "mass"]
    d = len(names)
    run = RunResult(
        label="csaa",
        method="csaa",
        names=names,
        units=["N", "N", "N*s/m", "kg"],
        value=np.array([TRUTH[k] for k in names]),
        lower=np.zeros(d),
        upper=np.ones(d),
        fixed={"gain": TRUTH["gain"]},
        cost=1.0,
        ems=1.0,
        cost_search=1.0,
        ems_search=1.0,
        std=np.zeros(d),
        rel_std=np.zeros(d),
        corr=np.eye(d),
        flags=[""] * d,
        chain_x=np.zeros((1, d)),
        chain_cost=np.ones(1),
        traces={k: np.zeros((1, 1)) for k in ("best_cost", "current_cost", "acceptance")}
        | {k: np.zeros(1) for k in ("temperature", "n_evals", "wall_time")},
        minima_x=np.zeros((1, d)),
        minima_cost=np.ones(1),
        minima_count=np.ones(1, int),
    )
    attrs = provenance(
        kind="identify",
        recording_name="loop",
        recording_path="",
        recording_sha256="",
        config_text=cfg_text,
        config_path="emps.toml",
    )
    return write_results(ResultsFile(runs=[run], attrs=attrs), path)


def test_config_comes_from_the_results_file(cfg, closed_loop_rec, tmp_path):
    rec_path = write_recording(closed_loop_rec, tmp_path / "loop.h5")
    res = _results_file(tmp_path / "r.h5", EMPS_TOML.read_text())
    v = validate_recording(
        rec_path, res, decimate_by=10, controller=EMPS_CONTROLLER, out=tmp_path / "m.json"
    )
    direct = validate_model(closed_loop_rec, cfg, TRUTH, decimate_by=10, controller=EMPS_CONTROLLER)
    assert v.equation == direct.equation and v.simulation == direct.simulation
    saved = json.loads((tmp_path / "m.json").read_text())
    assert saved["equation"]["rel_error"] == v.equation.rel_error
    assert saved["params"]["Fv"] == TRUTH["Fv"]


def test_cli_validate(closed_loop_rec, tmp_path):
    rec_path = write_recording(closed_loop_rec, tmp_path / "loop.h5")
    params = tmp_path / "p.toml"
    params.write_text("".join(f"{k} = {v!r}\n" for k, v in TRUTH.items()))

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-m", "fricjax.cli", "validate", *args],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=300,
        )

    out = run(
        str(rec_path),
        "--results",
        str(params),
        "--config",
        str(EMPS_TOML),
        "--decimate",
        "10",
        "--controller",
        "emps",
        "--no-simulate",
    )
    assert out.returncode == 0, out.stderr
    assert "relative error" in out.stdout and "291, decimated by 10" in out.stdout
    bad = run(str(rec_path), "--results", str(params))
    assert bad.returncode == 2
    assert bad.stderr.strip() == f"error: {params}: holds no config; give --config"


def test_the_benchmark_rmse_scores_only_the_samples_after_the_initialisation_window():
    y = np.linspace(0.0, 0.2, 500)
    y_sim = y + 0.003  # 3 mm everywhere after the window
    y_sim[:20] += 5.0  # what the window holds is not scored
    assert simulation_rmse(y_sim, y, 20) == pytest.approx(0.003, rel=1e-12)
    assert simulation_rmse(y_sim, y, 0) > 1.0
    with pytest.raises(FricjaxError, match="n_init"):
        simulation_rmse(y_sim, y[:-1], 20)


def test_the_initial_state_is_the_quadratic_through_the_first_samples_only():
    t = np.arange(100) * DT
    x = 0.01 + 0.05 * t + 0.5 * 1.3 * t**2
    x[20:] = 99.0  # samples after the window are never read
    x0, v0 = initial_state(t, x, 20)
    assert x0 == pytest.approx(0.01, abs=1e-12) and v0 == pytest.approx(0.05, abs=1e-9)


def test_open_loop_rmse_is_small_at_the_truth_and_grows_with_a_friction_error(cfg, closed_loop_rec):
    """The recorded controller output drives the plant open loop; the position is set once
    from x[:20] (the body rests there) and never fed back."""
    at_truth = open_loop_rmse(closed_loop_rec, cfg, TRUTH)
    off = open_loop_rmse(closed_loop_rec, cfg, {**TRUTH, "Fv": 1.1 * TRUTH["Fv"]})
    # the loop held u over each period, the open-loop simulation interpolates it linearly:
    # a small drift at the truth, none of it from the parameters
    assert at_truth < 1e-4  # [m]
    assert off > 5 * at_truth  # 0.52 mm against 0.05 mm
