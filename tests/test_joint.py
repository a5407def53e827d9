"""Joint fit of several recordings (fricjax.joint): shared parameters recovered, each
recording's own offset recovered, σ from the joint Jacobian shrinking with the data, one
recording exactly the single fit, the weights each recording's residual scale, and every
usage mistake one line with exit 2."""

from __future__ import annotations

import dataclasses
import tomllib
from pathlib import Path

import h5py
import numpy as np
import pytest

from fricjax.api import identify_recording, identify_recordings, load, read_params
from fricjax.cli import main
from fricjax.config import load_config, parse_config
from fricjax.data.recording import Recording, read_recording, write_recording
from fricjax.data.twin import AXIS_TRUTH, axis_twin, stroke_twin
from fricjax.errors import FricjaxError
from fricjax.io.results import read_results
from fricjax.joint import (
    joint_problem,
    member_params,
    members_of,
    split_name,
)
from fricjax.problem import build_problem
from fricjax.report.show import drift_lines, run_summary, show_results
from fricjax.validate import validate_recording

#: Each twin's own offset [N]; everything else is AXIS_TRUTH, shared.
OFFSETS = (6.0, -4.0)
#: x noise [m]; with CONFIG's 200 Hz filter and weighed mass the equation error's own
#: biases stay within half a σ of each recording's fit (measured).
NOISE = 2e-6
ROOT = Path(__file__).resolve().parents[1]
#: The axis with a weighed mass and one drive offset per recording.
CONFIG = ROOT / "configs" / "axis_joint.toml"
SHARED = ("Fc", "Fv")


def write_twins(folder: Path) -> list[Path]:
    paths = []
    for seed, offset in enumerate(OFFSETS):
        rec, _ = axis_twin(
            seed=seed, noise_std=NOISE, truth={**AXIS_TRUTH, "offset": offset}, name=f"run{seed}"
        )
        paths.append(write_recording(rec, folder / f"run{seed}.h5"))
    return paths


@pytest.fixture(scope="module")
def fitted(tmp_path_factory: pytest.TempPathFactory):
    folder = tmp_path_factory.mktemp("joint")
    paths = write_twins(folder)
    config = CONFIG
    run, out = identify_recordings(paths, config, out=folder / "joint.h5")
    single, single_out = identify_recording(paths[0], config, out=folder / "single.h5")
    return folder, paths, config, run, out, single, single_out


def test_shared_parameters_and_each_offset_recovered_within_2_sigma(fitted) -> None:
    *_, run, _, _, _ = fitted
    value = dict(zip(run.names, run.value, strict=True))
    std = dict(zip(run.names, run.std, strict=True))
    assert run.names == ["Fc", "Fv", "offset[1]", "offset[2]"]
    for name in SHARED:
        assert abs(value[name] - AXIS_TRUTH[name]) < 2 * std[name], name
    for k, offset in enumerate(OFFSETS, 1):
        assert abs(value[f"offset[{k}]"] - offset) < 2 * std[f"offset[{k}]"]
    # the two offsets are told apart: 10 N apart, more than 3 σ of their difference
    gap = value["offset[1]"] - value["offset[2]"]
    assert gap > 3 * np.hypot(std["offset[1]"], std["offset[2]"])


def test_sigma_of_shared_parameters_shrinks_about_1_over_sqrt2(fitted) -> None:
    _, paths, config, run, _, single, _ = fitted
    second, _ = identify_recording(paths[1], config, out=paths[1].with_name("second.h5"))
    joint = dict(zip(run.names, run.std, strict=True))
    for name in SHARED:
        alone = np.array([r.std[r.names.index(name)] for r in (single, second)])
        # the information of the two recordings adds: σ⁻² = σ_1⁻² + σ_2⁻² (to the weights'
        # and linearisation's few per cent), ≈ σ/√2 for two recordings of equal information
        np.testing.assert_allclose(joint[name], np.sum(alone**-2.0) ** -0.5, rtol=0.05)
        assert 0.6 < joint[name] / alone.mean() < 0.8, name


def test_each_recording_is_weighted_by_its_own_residual_scale(fitted) -> None:
    *_, run, _, single, _ = fitted
    members = members_of(run)
    d = len(single.names)
    # member 1's s_k is the residual scale of the single fit of the same recording
    s1 = np.sqrt(single.cost / (members[0]["n"] - d))
    np.testing.assert_allclose(members[0]["sigma"], s1, rtol=1e-9)
    # weights right => the weighted cost per residual entry is 1 within its sampling error
    n = sum(m["n"] for m in members)
    assert abs(run.ems - 1.0) < 3 * np.sqrt(2.0 / n)


def test_joint_cost_and_residual_are_the_weighted_sums_of_the_members(fitted) -> None:
    _, paths, config, *_ = fitted
    cfg = load_config(config)
    problems = [load(p, cfg)[2] for p in paths]
    jp = joint_problem(problems, ("offset",), [2.0, 5.0])
    theta = np.array([21.0, 190.0, 1.5, -2.5])  # Fc, Fv, offset[1], offset[2]
    own = [np.array([1.5, 21.0, 190.0]), np.array([-2.5, 21.0, 190.0])]
    expected = problems[0].cost(own[0]) / 4.0 + problems[1].cost(own[1]) / 25.0
    r = np.asarray(jp.residual_fn(theta))
    np.testing.assert_allclose(float(jp.cost_fn(theta)), expected, rtol=1e-10)
    np.testing.assert_allclose(r @ r, expected, rtol=1e-10)
    assert r.shape == (problems[0].n + problems[1].n,)


def test_a_fixed_value_that_differs_between_recordings_is_stored_per_recording(fitted) -> None:
    _, paths, *_ = fitted
    text = CONFIG.read_text(encoding="utf-8").replace('mass = { unit = "kg", value = 95.0 }', "")
    cfg = parse_config(tomllib.loads(text))  # the mass now comes from each recording
    recs = [
        dataclasses.replace(read_recording(p), mass=m)
        for p, m in zip(paths, (95.0, 96.0), strict=True)
    ]
    jp = joint_problem([build_problem(r, cfg) for r in recs], ("offset",), [1.0, 1.0])
    assert jp.fixed() == {"gain": 35.0, "mass[1]": 95.0, "mass[2]": 96.0}
    assert member_params({**jp.fixed(), "Fc": 20.0}, 1) == {"gain": 35.0, "mass": 96.0, "Fc": 20.0}


def test_one_recording_is_the_single_identify_bit_for_bit(fitted) -> None:
    folder, paths, config, *_, single, single_out = fitted
    run, out = identify_recordings([paths[0]], config, out=folder / "one.h5")
    np.testing.assert_array_equal(run.value, single.value)
    np.testing.assert_array_equal(run.std, single.std)
    assert run.cost == single.cost
    assert read_results(out).attrs["kind"] == read_results(single_out).attrs["kind"] == "identify"


def test_drift_check_names_the_per_recording_parameter_that_moved(fitted) -> None:
    *_, run, _, _, _ = fitted
    lines = drift_lines(run)
    assert lines[0].startswith("Drift: offset differs between the recordings")
    # the same run with offset[2] moved to 0.5 σ of offset[1]: no drift
    i, j = run.names.index("offset[1]"), run.names.index("offset[2]")
    value = run.value.copy()
    value[j] = value[i] + 0.5 * run.std[j]
    assert drift_lines(dataclasses.replace(run, value=value))[0].startswith("No drift of offset")


def test_validate_picks_the_member_that_is_the_recording(fitted) -> None:
    _, paths, _, run, out, *_ = fitted
    members = members_of(run)
    for k, path in enumerate(paths):
        report = validate_recording(path, out, simulate_run=False)
        # validate's EMS at q = 1 is the joint fit's EMS of that recording, in N²
        np.testing.assert_allclose(report.equation.ems, members[k]["ems"], rtol=1e-9)
        assert report.params["offset"] == pytest.approx(
            run.value[run.names.index(f"offset[{k + 1}]")]
        )
    # member 1's parameters on recording 2: its offset is 10 N off, the EMS grows by ~100 N²
    other = validate_recording(paths[1], out, simulate_run=False, member=1)
    assert other.equation.ems > members[1]["ems"] + 50.0


def test_member_names_round_trip() -> None:
    assert split_name("Fc[2]") == ("Fc", 1) and split_name("Fc") == ("Fc", None)
    assert split_name("x[0]") == ("x[0]", None)  # members count from 1
    params = {"Fc": 1.0, "offset[1]": 2.0, "offset[2]": 3.0, "mass[2]": 9.0}
    assert member_params(params, 1) == {"Fc": 1.0, "offset": 3.0, "mass": 9.0}


def test_show_lists_the_recordings_and_their_weights(fitted) -> None:
    *_, run, out, _, _ = fitted
    text = show_results(out)
    for k, m in enumerate(members_of(run), 1):
        row = next(line for line in text.splitlines() if line.split()[:2] == [str(k), m["name"]])
        assert f"{m['sigma']:.4g}" in row
    assert "EMS [1]" in text  # the joint cost is dimensionless
    # σ is the sandwich of both recordings' x noise; these twins' residuals are that noise
    assert run.attrs["sigma_method"] == "sandwich" and "[1] x noise" in run.attrs["sigma_noise"]
    assert abs(run.attrs["dispersion"] - 1.0) < 0.2
    assert "sandwich: [0] x noise" in run_summary(run)  # what identify prints


@pytest.mark.parametrize(
    ("joint_table", "needle"),
    [
        ('per_recording = ["Fk"]', "'Fk' is not a parameter of the model"),
        ('per_recording = ["gain"]', "'gain' is fixed in [params]"),
        ('per_recording = "offset"', "must be a list of parameter names"),
        ("offsets = []", "[joint].offsets: unknown key"),
    ],
)
def test_a_bad_joint_table_is_one_line(fitted, joint_table, needle, capsys) -> None:
    folder, paths, *_ = fitted
    bad = folder / "bad.toml"
    bad.write_text(
        CONFIG.read_text(encoding="utf-8").replace('per_recording = ["offset"]', joint_table),
        encoding="utf-8",
    )
    with pytest.raises(SystemExit) as exc:
        main(["identify", *map(str, paths), "-c", str(bad), "--out", str(folder / "x.h5")])
    err = capsys.readouterr().err.strip().splitlines()
    assert exc.value.code == 2 and len(err) == 1 and needle in err[0], err


def test_recordings_of_different_kinds_or_a_joint_file_misused_are_one_line(fitted, capsys) -> None:
    folder, paths, config, _, out, *_ = fitted
    rec = read_recording(paths[0])
    no_u = write_recording(Recording(t=rec.t, x=rec.x, mass=95.0, name="no_u"), folder / "no_u.h5")
    cases = [
        (["identify", str(paths[0]), str(no_u), "-c", str(config)], "records /u, "),
        (["identify", str(paths[0]), str(paths[0]), "-c", str(config)], "the same recording"),
        (["cost", str(paths[0]), "-c", str(config), "--params", str(out)], "a joint fit of 2"),
        (["validate", str(paths[0]), "--results", str(out), "--member", "3"], "not a recording"),
    ]
    for args, needle in cases:
        with pytest.raises(SystemExit) as exc:
            main(args)
        err = capsys.readouterr().err.strip().splitlines()
        assert exc.value.code == 2 and len(err) == 1 and needle in err[0], (args, err)
    with pytest.raises(FricjaxError, match="single-recording fit"):
        read_params(folder / "single.h5", member=1)
    with h5py.File(out) as f:
        assert f.attrs["kind"] == "joint"


#: Two strokes of one axis (fricjax.data.twin.stroke_twin) whose Coulomb level differs with
#: the direction (Fc ± asym_dFc), each moving one way only: alone a stroke cannot tell Fc
#: from asym_dFc (both constant forces), together they can.
STROKE_TRUTH = {**AXIS_TRUTH, "Fc": 20.0, "asym_dFc": 4.0, "asym_dFv": 0.0}
STROKES = """
[model]
terms = ["measured_input", "coulomb_viscous", "asymmetric_friction"]

[params]
gain = { unit = "N/V", value = 35.0 }
offset = { unit = "N", value = 0.0 }
Fc = { unit = "N", lower = 0.0, upper = 100.0, init = 50.0 }
Fv = { unit = "N*s/m", lower = 0.0, upper = 1000.0, init = 500.0 }
asym_dFc = { unit = "N", lower = -20.0, upper = 20.0, init = 0.0 }
asym_dFv = { unit = "N*s/m", value = 0.0 }
mass = { unit = "kg", value = 95.0 }

[preprocess]
method = "butterworth"
order = 4
cutoff_hz = 200.0
trim = 20

[search]
chains = 8
seed = 0
refine_top = 2

[anneal]
K = 10.0
alpha = 0.8
steps_per_level = 5
t_min_rel = 1e-4
patience = 5
rel_tol = 1e-4
max_levels = 100
"""


def write_stroke(path: Path, direction: float, seed: int) -> Path:
    dfc = STROKE_TRUTH["asym_dFc"]
    rec = stroke_twin(direction, asym_dfc=dfc, noise_std=NOISE, seed=seed, name=f"stroke{seed}")
    return write_recording(rec, path)


@pytest.mark.slow  # ~25 s on 2 cores: a full (not separable) search, three times
def test_opposite_strokes_jointly_determine_the_asymmetry_one_stroke_cannot(
    tmp_path: Path,
) -> None:
    config = tmp_path / "strokes.toml"
    config.write_text(STROKES, encoding="utf-8")
    paths = [write_stroke(tmp_path / f"s{k}.h5", d, k) for k, d in enumerate((1.0, -1.0))]
    alone, _ = identify_recording(paths[0], config, out=tmp_path / "alone.h5")
    for name in ("Fc", "asym_dFc"):
        assert np.isinf(alone.std[alone.names.index(name)])  # a constant force either way
    run, _ = identify_recordings(paths, config, out=tmp_path / "joint.h5")
    for name in ("Fc", "asym_dFc"):
        i = run.names.index(name)
        # one fixed noise draw: within 3 σ (a 2 σ band misses one draw in 22 by design)
        assert np.isfinite(run.std[i]) and abs(run.value[i] - STROKE_TRUTH[name]) < 3 * run.std[i]
    # the asymmetry is seen: Fc + asym_dFc forward and Fc − asym_dFc backward differ
    i = run.names.index("asym_dFc")
    assert run.value[i] > 10 * run.std[i]


def test_the_command_line_gives_the_api_result(fitted, capsys, monkeypatch) -> None:
    folder, paths, config, run, *_ = fitted
    monkeypatch.setenv("FRICJAX_COMPILATION_CACHE", "0")  # no cache folder for a test
    out = folder / "cli.h5"
    main(["identify", *map(str, paths), "-c", str(config), "--out", str(out), "--quiet"])
    text = capsys.readouterr().out
    back = read_results(out).runs[0]
    np.testing.assert_array_equal(back.value, run.value)  # same seed, same answer
    np.testing.assert_array_equal(back.std, run.std)
    assert "Drift: offset differs" in text and f"results: {out}" in text
