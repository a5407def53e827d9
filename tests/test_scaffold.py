"""init-config: a starting config from the recording's own scale, accepted by identify."""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from fricjax.api import config_or_default, init_config, load
from fricjax.config import parse_config
from fricjax.data.recording import Recording, write_recording
from fricjax.errors import FricjaxError
from fricjax.identify import IdentifySettings, identify
from fricjax.model.drive import MeasuredInput
from fricjax.model.friction import CoulombViscous
from fricjax.model.simulate import simulate
from fricjax.model.system import Model
from fricjax.report.show import undetermined
from fricjax.scaffold import scaffold_config

TRUTH = {"gain": 1.0, "offset": 0.0, "Fc": 15.0, "Fv": 20.0, "mass": 20.0}


def load_cell_axis(tmp_path: Path, *, axis: str = "") -> Path:
    """A 20 kg (or kg·m²) slide pushed by a measured force, Coulomb 15 N + viscous 20 N·s/m,
    8 s at 1 kHz (7 reversals); 1 µm noise on x, 0.05 N on the load cell."""
    t = np.arange(8000) / 1000.0
    force = 80.0 * np.sin(2 * np.pi * 0.5 * t) + 30.0 * np.sin(2 * np.pi * 1.3 * t + 0.4)
    model = Model((MeasuredInput(), CoulombViscous()))
    p = {k: jnp.asarray(v) for k, v in TRUTH.items()}
    traj = simulate(model, p, jnp.asarray(t), 0.0, 0.0, jnp.asarray(force), substeps=8)
    rng = np.random.default_rng(0)
    rec = Recording(
        t=t,
        x=np.asarray(traj.x) + rng.normal(0.0, 1e-6, t.shape),
        F=force + rng.normal(0.0, 0.05, t.shape),
        mass=TRUTH["mass"],
        name="load_cell_axis",
        axis=axis,
    )
    return write_recording(rec, tmp_path / "axis.h5")


@pytest.fixture(scope="module")
def axis_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return load_cell_axis(tmp_path_factory.mktemp("scaffold"))


def test_scaffolded_config_identifies_a_coulomb_viscous_axis_within_2_percent(
    axis_file: Path, tmp_path: Path
) -> None:
    text, path = init_config(axis_file, tmp_path / "c.toml")
    assert path.read_text() == text
    _, cfg, problem = load(axis_file, path)
    # every bound contains the truth: the scale reasoning does not cut the answer off
    for name in ("offset", "Fc", "Fv"):
        q = cfg.spec[name]
        assert q.lower <= TRUTH[name] <= q.upper, name
    settings = IdentifySettings.from_tables(cfg.tables, source=cfg.source)
    run = identify(problem, dataclasses.replace(settings, fast_compile=True))
    assert abs(run.params["Fc"] / TRUTH["Fc"] - 1) < 0.02
    assert abs(run.params["Fv"] / TRUTH["Fv"] - 1) < 0.02
    assert abs(run.params["offset"]) < 0.02 * TRUTH["Fc"]
    assert undetermined(run) == {}


def test_scaffold_bounds_follow_the_recording_scale(axis_file: Path) -> None:
    raw = tomllib.loads(scaffold_config(axis_file, friction=["coulomb", "viscous", "stribeck"]))
    params = raw["params"]
    # the force scale is the largest force the record shows (max |F| ~ 110 N here)
    assert 100.0 < params["Fc"]["upper"] < 130.0
    v_max = params["vs"]["upper"]
    assert params["Fv"]["upper"] == pytest.approx(params["Fc"]["upper"] / v_max, rel=1e-5)
    assert raw["model"]["measured_input"] == {"signal": "F"}
    assert raw["model"]["terms"] == ["measured_input", "stribeck_friction"]
    harmonic = tomllib.loads(scaffold_config(axis_file, drive="harmonic", harmonics=2))
    # x is dominated by the 0.5 Hz line of the force: ω_d within a bin (1/8 Hz) of π rad/s
    assert abs(harmonic["params"]["omega"]["init"] - np.pi) < 2 * np.pi / 8
    parse_config(harmonic)  # accepted


def test_rotary_scaffold_writes_rotary_units(tmp_path: Path) -> None:
    path = load_cell_axis(tmp_path, axis="rotary")
    raw = tomllib.loads(scaffold_config(path))
    assert raw["model"]["axis"] == "rotary"
    assert raw["params"]["Fc"]["unit"] == "N·m"
    assert raw["params"]["Fv"]["unit"] == "N·m·s/rad"
    assert parse_config(raw).axis.kind == "rotary"


@pytest.mark.parametrize(
    ("kwargs", "needle"),
    [
        ({"friction": ["viscous"]}, "must include coulomb"),
        ({"friction": ["coulomb", "drag"]}, "unknown term 'drag'"),
        ({"drive": "pneumatic"}, "--drive: must be one of"),
        ({"harmonics": 0}, "--harmonics"),
    ],
)
def test_scaffold_mistakes_are_one_line(axis_file: Path, kwargs: dict, needle: str) -> None:
    with pytest.raises(FricjaxError, match=needle):
        scaffold_config(axis_file, **kwargs)


def test_missing_config_is_refused_for_a_measured_recording(
    axis_file: Path, twin_path: Path
) -> None:
    with pytest.raises(FricjaxError, match="fricjax init-config") as err:
        config_or_default(axis_file, None)
    assert "/F" in str(err.value) and "26-parameter" in str(err.value)
    assert config_or_default(twin_path, None).name == "paper.toml"  # no input: the paper model
    assert config_or_default(axis_file, "mine.toml") == Path("mine.toml")


def test_rotary_axis_is_carried_to_every_label(tmp_path: Path) -> None:
    """A rotary load-cell axis: inspect, identify's summary and its tables say rad, N·m,
    kg·m² and (N·m)², never m or N."""
    from fricjax.api import inspect_recording
    from fricjax.report.show import run_summary

    path = load_cell_axis(tmp_path, axis="rotary")
    summary, _ = inspect_recording(path, png=tmp_path / "r.png")
    assert summary["axis"] == "rotary"
    assert {"moment of inertia [kg·m²]", "x range [rad]", "v range [rad/s]"} <= set(summary)
    assert "J·α range [N·m]" in summary and "measured F [N·m]" in summary
    assert not any(k.endswith(("[m]", "[m/s]", "[N]", "[kg]")) for k in summary)
    _, cfg_path = init_config(path, tmp_path / "r.toml")
    _, cfg, problem = load(path, cfg_path)
    assert problem.spec["mass"].unit == "kg·m²"
    settings = IdentifySettings.from_tables(cfg.tables, source=cfg.source)
    run = identify(problem, dataclasses.replace(settings, fast_compile=True))
    run.attrs["axis"] = cfg.axis.kind  # as identify_recording stores it
    shown = run_summary(run)
    assert "EMS [(N·m)²]" in shown and "N·m·s/rad" in shown
    assert "[N²]" not in shown and "N*s/m" not in shown
    # the same physics in other units: the same numbers
    assert abs(run.params["Fc"] / TRUTH["Fc"] - 1) < 0.02


def test_a_linear_config_refuses_rotary_units_and_a_mismatched_recording(tmp_path: Path) -> None:
    raw = tomllib.loads(scaffold_config(load_cell_axis(tmp_path, axis="rotary")))
    del raw["model"]["axis"]
    with pytest.raises(FricjaxError, match=r"wrong unit 'N·m.*axis = 'rotary' takes"):
        parse_config(raw)
    path = load_cell_axis(tmp_path, axis="rotary")
    with pytest.raises(FricjaxError, match="recording is 'rotary', --axis 'linear'"):
        scaffold_config(path, axis="linear")


def test_cli_init_config_then_identify_without_config_exits_2(axis_file: Path, tmp_path: Path):
    import subprocess
    import sys

    def run(*args: str) -> subprocess.CompletedProcess[str]:
        cmd = [sys.executable, "-m", "fricjax.cli", *args]
        return subprocess.run(cmd, capture_output=True, text=True, timeout=300)

    out = run("identify", str(axis_file))
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2 and len(lines) == 1 and "fricjax init-config" in lines[0]
    cfg = tmp_path / "c.toml"
    made = run("init-config", str(axis_file), "--out", str(cfg), "--friction", "coulomb")
    assert made.returncode == 0, made.stderr
    assert 'Fv = { unit = "N·s/m", value = 0.0 }' in cfg.read_text()
    again = run("init-config", str(axis_file), "--out", str(cfg))
    assert again.returncode == 2 and "exists" in again.stderr


EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def test_a_load_cell_csv_scaffold_hands_off_and_identify_is_not_fooled_by_stick_slip(
    tmp_path: Path,
) -> None:
    """The own-axis path of a newcomer: a CSV (no mass, no unit of u) of a 12 kg axis with
    a Stribeck drop (examples/axis.csv: Fc 8, Fs 14 N, vs 0.02 m/s, Fv 60 N·s/m)."""
    from fricjax.report.show import determination

    text, path = init_config(
        EXAMPLES / "axis.csv",
        tmp_path / "c.toml",
        friction="coulomb,viscous,stribeck",
        mass=12.0,
        u_unit="N",
    )
    # the mass travels in the config (the printed next command needs no --mass), the load
    # cell's gain is fixed at 1, and the 1-D search is sized like the shipped configs
    assert 'mass = { unit = "kg", value = 12 }' in text
    assert 'gain = { unit = "N/N", value = 1.0 }' in text
    assert "steps_per_level = 4" in text
    _, cfg, problem = load(EXAMPLES / "axis.csv", path)
    settings = dataclasses.replace(
        IdentifySettings.from_tables(cfg.tables, source=cfg.source), fast_compile=True
    )
    # by equation error the stick-slip record is misfitted far beyond its noise, and the
    # summary says so instead of calling the estimate determined
    biased = identify(problem, dataclasses.replace(settings, objective="equation"))
    assert biased.attrs["dispersion"] > 4.0
    said = determination(biased)
    assert "does NOT fit this record" in said and "determined by this record" not in said
    # the default refines by output error itself and recovers the plant
    run = identify(problem, settings)
    assert "refined_by_output_error" in run.attrs
    truth = {"Fc": 8.0, "Fs": 14.0, "vs": 0.02, "Fv": 60.0}
    for name, value in truth.items():
        assert abs(run.params[name] / value - 1) < 0.03, (name, run.params[name])
    assert "does NOT fit" not in determination(run)


def test_a_unitless_u_gets_a_free_gain_and_a_hint() -> None:
    text = scaffold_config(EXAMPLES / "axis.csv", mass=12.0)
    assert 'gain = { unit = "N/u"' in text and "--u-unit N" in text
