"""Bad input files end in a clean refusal or a correct answer (issue 41).

Property-based over the four kinds of file a user hands fricjax: recordings (HDF5 and CSV),
configs, parameter files and results files, each written with random corruptions. The
property is always the same and never "it ran": either a :class:`FricjaxError` whose one
line names the file and the field at fault, or a result equal to what the file holds.
The readers are called in-process; a few subprocess checks pin the command line's exit
status and its one line on stderr.
"""

from __future__ import annotations

import json
import math
import os
import re
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fricjax.api import read_params
from fricjax.config import load_config
from fricjax.data.preprocess import PreprocessSettings
from fricjax.data.recording import MAX_STEP_JITTER, read_recording
from fricjax.errors import FricjaxError
from fricjax.identify import IdentifySettings
from fricjax.io.results import ResultsFile, RunResult, read_results, write_results
from fricjax.params import check_values
from fricjax.problem import build_problem
from fricjax.report.show import show_results

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "configs" / "paper.toml"
TWIN = ROOT / "data" / "paper_twin.h5"
FUZZ = settings(
    max_examples=40,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)


def outcome(fn: Callable[[], Any]) -> tuple[bool, Any]:
    """(True, value) or (False, the one-line message); any other exception fails the test."""
    try:
        return True, fn()
    except FricjaxError as err:
        message = str(err)
        assert "\n" not in message and message, message
        return False, message


def assert_refused(ok: bool, message: Any, *parts: str) -> None:
    assert not ok, f"accepted, expected a refusal naming {parts}"
    for part in parts:
        assert part in message, f"{part!r} not in {message!r}"


# ------------------------------------------------------------------------------ recordings

#: Corruptions that must be refused, with the field their message names (HDF5 / CSV).
REFUSED = {
    "nan_x": "x",
    "inf_x": "x",
    "nan_t": "t",
    "non_monotone_t": "t",
    "jitter_t": "t",
    "x_shorter": "x",
    "x_missing": "x",
    "x_strings": "x",
    "t_sample_indices": "t",
    "x_times_1e300": "x",
    "too_short": "t",
    "semicolon": "header",
}
#: Corruptions a reader must accept, reading back exactly the samples written.
ACCEPTED = ("none", "bom", "crlf", "bom_crlf", "blank_lines")
HDF5_ONLY = {"x_strings", "t_sample_indices"}
CSV_ONLY = {"bom", "crlf", "bom_crlf", "blank_lines", "semicolon"}


def _signals(n: int, dt: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    t = 0.5 + np.arange(n) * dt
    x = 0.01 * np.sin(2 * np.pi * 3.0 * t) + 1e-6 * rng.standard_normal(n)
    return t, x


def _write_hdf5(path: Path, kind: str, t: np.ndarray, x: np.ndarray, i: int) -> None:
    t, x = t.copy(), x.copy()
    with h5py.File(path, "w") as f:
        f.attrs["mass"] = 95.0
        if kind == "t_sample_indices":
            t = np.arange(t.shape[0], dtype=np.int64)
        f["t"] = t
        if kind == "x_missing":
            return
        if kind == "x_strings":
            f["x"] = np.array([f"{v:.6g}" for v in x], dtype=h5py.string_dtype())
            return
        f["x"] = x[:-3] if kind == "x_shorter" else x


def _csv_text(kind: str, t: np.ndarray, x: np.ndarray) -> bytes:
    rows = [f"{float(a)!r},{float(b)!r}" for a, b in zip(t, x, strict=True)]
    header = "t,x"
    if kind == "x_shorter":  # the last three rows lack their x
        rows[-3:] = [f"{float(a)!r}," for a in t[-3:]]
    if kind == "x_missing":
        header, rows = "t", [f"{float(a)!r}" for a in t]
    if kind == "blank_lines":
        rows.insert(len(rows) // 2, "")
        rows.append("")
    newline = "\r\n" if "crlf" in kind else "\n"
    text = newline.join([header, *rows]) + newline
    if kind == "semicolon":
        text = text.replace(",", ";").replace(".", ",")
    if "bom" in kind:
        text = "\ufeff" + text
    return text.encode()


def _corrupt(kind: str, t: np.ndarray, x: np.ndarray, i: int) -> tuple[np.ndarray, np.ndarray]:
    t, x = t.copy(), x.copy()
    if kind == "nan_x":
        x[i] = np.nan
    elif kind == "inf_x":
        x[i] = -np.inf
    elif kind == "nan_t":
        t[i] = np.nan
    elif kind == "non_monotone_t":
        t[i], t[i - 1] = t[i - 1], t[i]
    elif kind == "jitter_t":
        t[i] += 1e-3 * (t[1] - t[0])
    elif kind == "x_times_1e300":
        x *= 1e300
    elif kind == "too_short":
        t, x = t[:10], x[:10]
    return t, x


@st.composite
def recordings(draw: st.DrawFn) -> tuple[str, str, int, float, int, int]:
    fmt = draw(st.sampled_from(["h5", "csv"]))
    kinds = [
        k
        for k in (*REFUSED, *ACCEPTED)
        if not (fmt == "h5" and k in CSV_ONLY) and not (fmt == "csv" and k in HDF5_ONLY)
    ]
    kind = draw(st.sampled_from(kinds))
    n = draw(st.integers(20, 400))
    dt = draw(st.sampled_from([1e-4, 1e-3, 2.5e-3, 0.01]))
    i = draw(st.integers(1, n - 1))
    seed = draw(st.integers(0, 2**16))
    return fmt, kind, n, dt, i, seed


@FUZZ
@given(case=recordings())
def test_a_corrupted_recording_is_refused_naming_the_field_or_read_exactly(
    tmp_path: Path, case: tuple[str, str, int, float, int, int]
) -> None:
    fmt, kind, n, dt, i, seed = case
    t, x = _signals(n, dt, seed)
    t, x = _corrupt(kind, t, x, i)
    path = tmp_path / f"rec_{kind}.{fmt}"
    if fmt == "h5":
        _write_hdf5(path, kind, t, x, i)
    else:
        path.write_bytes(_csv_text(kind, t, x))
    ok, value = outcome(lambda: read_recording(path, mass=95.0))
    if kind in REFUSED:
        field = REFUSED[kind]
        label = field if field == "header" else (f"/{field}" if fmt == "h5" else f"'{field}'")
        assert_refused(ok, value, str(path), label)
        return
    assert ok, value
    # exactly the samples written, on a time base that meets layout v1
    assert np.array_equal(value.t, t) and np.array_equal(value.x, x)
    steps = np.diff(value.t)
    assert (steps > 0).all()
    assert np.max(np.abs(steps - value.dt)) / value.dt < MAX_STEP_JITTER
    assert value.mass == 95.0


def test_a_dangling_external_link_is_refused_naming_the_dataset(tmp_path: Path) -> None:
    path = tmp_path / "link.h5"
    t, _ = _signals(50, 1e-3, 0)
    with h5py.File(path, "w") as f:
        f["t"] = t
        f["x"] = h5py.ExternalLink(str(tmp_path / "gone.h5"), "/x")
        f.attrs["mass"] = 1.0
    ok, value = outcome(lambda: read_recording(path))
    assert_refused(ok, value, str(path), "/x", "gone.h5")


def test_a_record_too_short_for_the_preprocessing_blames_the_recording(tmp_path: Path) -> None:
    """trim = 20 at each end needs 43 samples: 41 are refused naming the recording and the
    minimum, 43 accepted (derivatives of the 3 kept samples)."""
    cfg = load_config(PAPER)
    t, x = _signals(43, 1e-3, 1)
    for n in (16, 41):
        path = tmp_path / f"short{n}.csv"
        path.write_bytes(_csv_text("none", t[:n], x[:n]))
        rec = read_recording(path, mass=95.0)
        ok, value = outcome(lambda rec=rec: build_problem(rec, cfg))
        assert_refused(ok, value, f"{path}: /t: {n} samples", "at least 43")
    path = tmp_path / "short43.csv"
    path.write_bytes(_csv_text("none", t, x))
    assert build_problem(read_recording(path, mass=95.0), cfg).n == 3


def test_a_bad_mass_flag_is_blamed_on_the_flag_not_the_file() -> None:
    ok, value = outcome(lambda: read_recording(TWIN, mass=-5.0))
    assert_refused(ok, value, "--mass", "-5")
    assert str(TWIN) not in value and "attr" not in value


def test_an_empty_mat_file_is_refused(tmp_path: Path) -> None:
    from fricjax.data.importers import import_mat

    path = tmp_path / "empty.mat"
    path.write_bytes(b"")
    ok, value = outcome(lambda: import_mat(path))
    assert_refused(ok, value, str(path), "empty")


# --------------------------------------------------------------------------------- configs

_BASE = PAPER.read_text()


def _toml(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float) and not math.isfinite(value):
        return "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    return str(value)


def _with_key(table: str, key: str, value: Any) -> str:
    """paper.toml with ``[table].key = value`` (replacing the key if the table sets it)."""
    line = f"{key} = {_toml(value)}"
    head = f"[{table}]\n"
    start = _BASE.index(head) + len(head)
    end = _BASE.find("\n[", start)
    end = len(_BASE) if end < 0 else end
    body = re.sub(rf"(?m)^{key} = .*$", "", _BASE[start:end])
    return _BASE[:start] + line + "\n" + body + _BASE[end:]


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_real(v: Any) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


#: (table, key, valid?, read back): what each key accepts, and where its value lands.
CONFIG_KEYS: dict[str, tuple[str, Callable[[Any], bool], Callable[[Any], Any]]] = {
    "order": ("preprocess", lambda v: _is_int(v) and v >= 1, lambda s: s[0].order),
    # the twin's 272 samples keep at least 3 after trimming
    "trim": ("preprocess", lambda v: _is_int(v) and 0 <= v <= 134, lambda s: s[0].trim),
    "stencil": ("preprocess", lambda v: _is_int(v) and v in (2, 4), lambda s: s[0].stencil),
    "decimate": ("preprocess", lambda v: _is_int(v) and v >= 1, lambda s: s[0].decimate),
    # below Nyquist (500 Hz) and at least one period over the twin's 0.271 s
    "cutoff_hz": (
        "preprocess",
        lambda v: _is_real(v) and 1 / 0.271 <= v < 500,
        lambda s: s[0].cutoff_hz,
    ),
    "method": ("preprocess", lambda v: v in ("butterworth", "savgol"), lambda s: s[0].method),
    "chains": ("search", lambda v: _is_int(v) and v >= 1, lambda s: s[1].chains),
    "refine_top": ("search", lambda v: _is_int(v) and v >= 1, lambda s: s[1].refine_top),
    "seed": ("search", _is_int, lambda s: s[1].seed),
    "refine": ("search", lambda v: isinstance(v, bool), lambda s: s[1].refine),
    "separable": ("search", lambda v: isinstance(v, bool), lambda s: s[1].separable),
}
config_values = st.one_of(
    st.integers(-10, 600),
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.sampled_from([1e-9, 3.0, 4.0, 100.0, 499.9, 2.0, 0.5, 10.5]),
    st.booleans(),
    st.text(alphabet="abcdefghijklmnopqrstuvwxyz", max_size=8),
    st.sampled_from(["butterworth", "savgol", "many", "no", "ten"]),
    st.lists(st.integers(0, 5), max_size=3),
)


def _settings(path: Path) -> tuple[PreprocessSettings, IdentifySettings, np.ndarray]:
    cfg = load_config(path)
    pre = PreprocessSettings.from_dict(cfg.table("preprocess"), source=cfg.source)
    ident = IdentifySettings.from_tables(cfg.tables, source=cfg.source)
    # the preprocessing meets the recording: a cutoff is checked against its record
    return pre, ident, np.asarray(build_problem(read_recording(TWIN), cfg).a)


@FUZZ
@given(key=st.sampled_from(sorted(CONFIG_KEYS)), value=config_values)
def test_a_config_value_is_used_as_written_or_refused_naming_the_key(
    tmp_path: Path, key: str, value: Any
) -> None:
    table, valid, read_back = CONFIG_KEYS[key]
    path = tmp_path / "fuzz.toml"
    path.write_text(_with_key(table, key, value))
    ok, result = outcome(lambda: _settings(path))
    if key == "refine_top" and ok:
        # the separable search polishes the budget's refine_top; [search]'s is still checked
        assert valid(value)
        return
    if key == "chains" and ok:
        assert valid(value) and result[1].separable  # the budget's chains: 8
        assert result[1].chains == 8
        return
    if valid(value):
        assert ok, result
        assert read_back(result) == value
        assert np.isfinite(result[2]).all()  # an acceleration, not NaN from a bad filter
    else:
        assert_refused(ok, result, str(path), key)


def _without_table(name: str) -> str:
    start = _BASE.index(f"[{name}]\n")
    end = _BASE.find("\n[", start + 1)
    return _BASE[:start] + _BASE[end + 1 :]


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ("preprocess = 5\n" + _without_table("preprocess"), "[preprocess]"),
        (_BASE.replace("harmonics = 10", 'harmonics = "ten"'), "[model.harmonic_drive].harmonics"),
        (_BASE.replace("harmonics = 10", "harmonics = 10.5"), "[model.harmonic_drive].harmonics"),
        (_BASE.replace('delta = { unit = "1", value = 1.0 }', "delta = -1.0"), "[params].delta"),
        (_BASE.replace('delta = { unit = "1", value = 1.0 }', "delta = 0.0"), "[params].delta"),
        (_BASE.replace("[params]\n", "[params]\nmass = 0\n"), "[params].mass"),
        (_BASE.replace("lower = 0.02, upper = 0.5", "lower = 0.0, upper = 0.5"), "[params].vs"),
        (_BASE + "\n[model.harmonic_drive.x]\n", "[model.harmonic_drive]"),
    ],
)
def test_a_bad_config_is_refused_naming_the_key(tmp_path: Path, text: str, field: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    ok, value = outcome(lambda: load_config(path))
    assert_refused(ok, value, str(path), field)


def test_binary_garbage_is_not_a_config(tmp_path: Path) -> None:
    path = tmp_path / "garbage.toml"
    path.write_bytes(bytes(range(256)))
    ok, value = outcome(lambda: load_config(path))
    assert_refused(ok, value, str(path), "not UTF-8")


# ------------------------------------------------------------------------ parameter files


@pytest.fixture(scope="module")
def twin_problem_spec():
    return build_problem(read_recording(TWIN), load_config(PAPER)).spec


param_values = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=64),
    st.integers(-(2**40), 2**40),
    st.booleans(),
    st.text(max_size=4),
    st.none(),
)


@st.composite
def params_documents(draw: st.DrawFn) -> Any:
    names = ["mass", "vs", "delta", "omega", "Fc", "F0", "phi_1"]
    return draw(
        st.one_of(
            st.dictionaries(st.sampled_from(names), param_values, max_size=4),
            st.lists(param_values, max_size=3),
            param_values,
        )
    )


@FUZZ
@given(doc=params_documents())
def test_a_params_file_gives_its_values_or_is_refused_naming_the_key(
    tmp_path: Path, twin_problem_spec, doc: Any
) -> None:
    path = tmp_path / "p.json"
    path.write_text(json.dumps(doc))  # NaN and Infinity as JSON's extensions write them
    spec = twin_problem_spec

    def bound() -> dict[str, float]:
        named = read_params(path)
        check_values(named, spec, str(path))
        return named

    ok, value = outcome(bound)
    if not isinstance(doc, dict):
        assert_refused(ok, value, str(path), "top level")
        return
    if ok:
        assert value == {k: float(v) for k, v in doc.items()}
        for k, v in value.items():  # finite and physical: positive mass, vs, delta, omega
            assert math.isfinite(v) and spec[k].domain.contains(v)
        return
    bad = [
        k
        for k, v in doc.items()
        if not (isinstance(v, int | float) and not isinstance(v, bool))
        or not math.isfinite(v)
        or not spec[k].domain.contains(float(v))
    ]
    assert bad, value
    assert str(path) in value and any(f": {k}:" in value for k in bad), value


# -------------------------------------------------------------------------- results files

NAMES = ["F0", "vs", "omega"]


def _run() -> RunResult:
    d, c, levels, m = 3, 4, 5, 2
    rng = np.random.default_rng(7)
    return RunResult(
        label="csaa",
        method="csaa",
        names=list(NAMES),
        units=["N", "m/s", "rad/s"],
        value=np.array([400.0, 0.2, 30.0]),
        lower=np.array([200.0, 0.02, 18.0]),
        upper=np.array([600.0, 0.5, 50.0]),
        fixed={"delta": 1.0, "mass": 95.0},
        cost=1.0e6,
        ems=4.5e3,
        cost_search=1.1e6,
        ems_search=4.7e3,
        std=np.array([1.0, np.nan, 0.1]),
        rel_std=np.array([0.0025, np.nan, 0.003]),
        corr=np.eye(d),
        flags=["", "not identifiable", ""],
        chain_x=rng.uniform(size=(c, d)),
        chain_cost=rng.uniform(size=c),
        traces={
            "best_cost": rng.uniform(size=(levels, c)),
            "current_cost": rng.uniform(size=(levels, c)),
            "acceptance": rng.uniform(size=(levels, c)),
            "temperature": rng.uniform(size=levels),
            "n_evals": np.arange(levels, dtype=np.float64),
            "wall_time": np.arange(levels, dtype=np.float64),
        },
        minima_x=rng.uniform(size=(m, d)),
        minima_cost=rng.uniform(size=m),
        minima_count=np.array([3, 1]),
        attrs={"wall_time": 1.5, "levels": levels, "objective": "equation error"},
    )


def _results_attrs() -> dict[str, Any]:
    return {"format": "fricjax-results-v1", "kind": "identify", "config": _BASE}


#: Mutations of /runs/csaa/<entry>: (entry named in the message, mutation, must refuse?).
def _replace(key: str, data: Any) -> Callable[[h5py.Group], None]:
    def mutate(g: h5py.Group) -> None:
        del g[key]
        g[key] = data

    return mutate


def _set(key: str, index: int, value: float) -> Callable[[h5py.Group], None]:
    def mutate(g: h5py.Group) -> None:
        g[key][index] = value

    return mutate


def _attr(owner: str, key: str, value: Any) -> Callable[[h5py.Group], None]:
    def mutate(g: h5py.Group) -> None:
        (g[owner] if owner else g).attrs[key] = value

    return mutate


def _delete(key: str) -> Callable[[h5py.Group], None]:
    def mutate(g: h5py.Group) -> None:
        del g[key]

    return mutate


MUTATIONS: dict[str, tuple[str, Callable[[h5py.Group], None], bool]] = {
    "value_short": ("params/value", _replace("params/value", [1.0]), True),
    "value_strings": (
        "params/value",
        _replace("params/value", np.array(["a", "b", "c"], dtype=h5py.string_dtype())),
        True,
    ),
    "value_nan": ("params/value", _set("params/value", 0, np.nan), True),
    "value_inf": ("params/value", _set("params/value", 0, np.inf), True),
    "lower_nan": ("params/lower", _set("params/lower", 0, np.nan), True),
    "names_numbers": ("params/names", _replace("params/names", [1.0, 2.0, 3.0]), True),
    "names_long": (
        "params/units",
        _replace("params/names", np.array(["a", "b", "c", "d"], dtype=h5py.string_dtype())),
        True,
    ),
    "corr_shape": ("params/corr", _replace("params/corr", np.eye(2)), True),
    "no_upper": ("params/upper", _delete("params/upper"), True),
    "no_traces": ("traces/best_cost", _delete("traces"), True),
    "cost_nan": ("cost", _attr("", "cost", np.nan), True),
    "cost_string": ("cost", _attr("", "cost", "cheap"), True),
    "fixed_inf": ("delta", _attr("fixed", "delta", np.inf), True),
    "wall_time_string": ("wall_time", _attr("", "wall_time", "slow"), True),
    "std_nan": ("", _set("params/std", 0, np.nan), False),  # σ not computed: legal
    "chain_cost_inf": ("", _set("chains/cost", 0, np.inf), False),  # a diverged chain
}


@FUZZ
@given(
    # at most one mutation per entry, so that each one is seen
    kinds=st.lists(
        st.sampled_from(sorted(MUTATIONS)),
        max_size=2,
        unique_by=lambda k: MUTATIONS[k][0] or k,
    ),
    runs_shape=st.sampled_from(["group", "group", "group", "empty", "dataset"]),
)
def test_a_results_file_reads_as_written_or_is_refused_naming_the_entry(
    tmp_path: Path, kinds: list[str], runs_shape: str
) -> None:
    path = tmp_path / "r.results.h5"
    written = _run()
    write_results(ResultsFile(runs=[written], attrs=_results_attrs()), path)
    with h5py.File(path, "r+") as f:
        if runs_shape != "group":
            del f["runs"]
            if runs_shape == "empty":
                f.create_group("runs")
            else:
                f["runs"] = [1.0]
        else:
            for kind in kinds:
                MUTATIONS[kind][1](f["runs/csaa"])
    ok, value = outcome(lambda: read_results(path))
    must_refuse = [k for k in kinds if MUTATIONS[k][2]]
    if runs_shape != "group":
        assert_refused(ok, value, str(path), "/runs")
        return
    if must_refuse:
        assert not ok, f"accepted a results file with {must_refuse}"
        named = [MUTATIONS[k][0] for k in must_refuse]
        assert str(path) in value and any(n in value for n in named), value
        return
    assert ok, value
    (run,) = value.runs
    assert run.params == written.params and run.cost == written.cost
    assert np.array_equal(run.corr, written.corr)


def test_a_non_physical_value_in_a_results_file_is_refused_by_show(tmp_path: Path) -> None:
    path = tmp_path / "r.results.h5"
    write_results(ResultsFile(runs=[_run()], attrs=_results_attrs()), path)
    assert "F0" in show_results(path)  # the clean file is shown
    with h5py.File(path, "r+") as f:
        f["runs/csaa/params/value"][1] = -0.1  # vs < 0: the Stribeck curve is undefined
    ok, value = outcome(lambda: show_results(path))
    assert_refused(ok, value, str(path), "vs", "-0.1")


# ------------------------------------------------------------------- the command line


def _cli(*args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "FRICJAX_COMPILATION_CACHE": "0"}
    script = Path(sys.executable).parent / "fricjax"
    return subprocess.run(
        [str(script), *map(str, args)], capture_output=True, text=True, env=env, cwd=ROOT
    )


def test_the_command_line_refuses_bad_files_in_one_line_with_status_2(tmp_path: Path) -> None:
    results = tmp_path / "r.results.h5"
    write_results(ResultsFile(runs=[_run()], attrs=_results_attrs()), results)
    with h5py.File(results, "r+") as f:
        del f["runs/csaa/params/value"]
        f["runs/csaa/params/value"] = [1.0]
    params = tmp_path / "p.json"
    params.write_text("[1, 2]")
    cases = [
        (("show", results), f"{results}: /runs/csaa/params/value"),
        (("cost", TWIN, "-c", PAPER, "--params", params), f"{params}: top level"),
        (("cost", TWIN, "-c", PAPER, "--mass", "-5"), "--mass: must be a positive"),
    ]
    for args, expected in cases:
        proc = _cli(*args)
        assert proc.returncode == 2, proc.stderr
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
        assert lines[0].startswith("error: ") and expected in lines[0], lines[0]


# ------------------------------------------ values that overflow, names a model does not take


def _truth_with(tmp_path: Path, **changes: float) -> Path:
    """The twin's generating parameters as a TOML parameter file, with ``changes``."""
    from fricjax.data.twin import PAPER_TRUTH

    values = {**PAPER_TRUTH, **changes}
    path = tmp_path / "p.toml"
    path.write_text("".join(f"{k} = {v!r}\n" for k, v in values.items()))
    return path


def test_an_overflowing_parameter_is_an_error_never_a_printed_answer(tmp_path: Path) -> None:
    from fricjax.api import cost_at, simulate_recording

    params = _truth_with(tmp_path, Fv=1e300)  # finite and positive, but the force overflows
    ok, value = outcome(lambda: cost_at(TWIN, PAPER, params=params))
    assert_refused(ok, value, str(params), "not finite", "Fv = 1e+300")
    out = tmp_path / "sim"
    ok, value = outcome(lambda: simulate_recording(TWIN, params=params, config=PAPER, out=out))
    assert_refused(ok, value, str(params), "not finite", "Fv = 1e+300")
    assert not out.exists() or not any(out.iterdir())  # nothing written full of NaN
    # the same file at the truth's Fv gives a finite cost: the refusal is the value's
    ok, value = outcome(lambda: cost_at(TWIN, PAPER, params=_truth_with(tmp_path)))
    assert ok and math.isfinite(value["cost"])


def test_show_refuses_a_parameter_name_the_model_does_not_take(tmp_path: Path) -> None:
    path = tmp_path / "r.results.h5"
    write_results(ResultsFile(runs=[_run()], attrs=_results_attrs()), path)
    with h5py.File(path, "r+") as f:
        names = [n.decode() for n in f["runs/csaa/params/names"][()]]
        names[0] = "Fq"
        del f["runs/csaa/params/names"]
        f["runs/csaa/params/names"] = np.array(names, dtype=h5py.string_dtype())
    ok, value = outcome(lambda: show_results(path))
    assert_refused(ok, value, str(path), "/runs/csaa/params/names", "'Fq'")


def test_a_mass_beyond_any_rig_is_refused_naming_it() -> None:
    ok, value = outcome(lambda: read_recording(TWIN, mass=1e300))
    assert_refused(ok, value, "--mass", "1e+300", "physical range")
    ok, value = outcome(lambda: read_recording(TWIN, mass=1e8))  # the largest accepted
    assert ok and value.mass == 1e8


def test_twin_refuses_a_duration_it_cannot_simulate_in_one_line(tmp_path: Path) -> None:
    for duration in ("nan", "1e9", "-1"):
        proc = _cli("twin", tmp_path / "t.h5", "--duration", duration)
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2 and len(lines) == 1, proc.stderr
        # the range accepted at 1 kHz: two samples to 1e8 RK4 steps of 16 per sample
        assert lines[0].startswith("error: twin: --duration") and "6250 s" in lines[0], lines
        if duration == "1e9":
            assert "1e+12 samples" in lines[0] and "GiB" in lines[0], lines  # the memory
    assert not (tmp_path / "t.h5").exists()
