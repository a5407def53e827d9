"""Recording type, validation and HDF5 / CSV I/O (HDF5 layout v1)."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest

import fricjax.data.recording as recording
from fricjax.data.recording import (
    Recording,
    read_recording,
    require_mass,
    validate,
    write_recording,
)
from fricjax.errors import FricjaxError

N = 200
DT = 1e-3


def make_rec(*, u: bool = True, F: bool = True, mass: float | None = 12.5) -> Recording:
    """A recording whose samples use all 53 mantissa bits, so any rounding shows."""
    rng = np.random.default_rng(1234)
    t = 0.25 + np.arange(N) * DT
    x = 0.01 * np.sin(2 * np.pi * 3.0 * t) + 1e-7 * rng.standard_normal(N)
    x[3] = -0.0
    x[4] = 5e-310  # subnormal
    return Recording(
        t=t,
        x=x,
        u=rng.standard_normal(N) * 3.0 if u else None,
        F=rng.standard_normal(N) * 1e3 if F else None,
        mass=mass,
        name="bench-1",
        source="synthetic, seed 1234",
        u_unit="V",
        notes="first line of notes; ü unicode",
    )


def same_bits(a: np.ndarray | None, b: np.ndarray | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    return a.dtype == b.dtype == np.float64 and a.tobytes() == b.tobytes()


def assert_one_line(err: pytest.ExceptionInfo[FricjaxError], *parts: str) -> None:
    msg = str(err.value)
    assert "\n" not in msg
    for part in parts:
        assert part in msg, f"{part!r} not in {msg!r}"


def leftovers(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir() if p.name.endswith(".tmp"))


# ------------------------------------------------------------------ type and properties


def test_properties_n_dt_duration() -> None:
    rec = make_rec()
    assert rec.n == N
    assert rec.dt == pytest.approx(DT, rel=1e-12)
    assert rec.duration == pytest.approx((N - 1) * DT, rel=1e-12)
    assert math.isnan(Recording(t=[0.0], x=[0.0]).dt)


def test_arrays_are_float64_read_only_copies() -> None:
    t = np.arange(32)  # integers: stored as float64
    x = np.zeros(32)
    rec = Recording(t=t, x=x)
    assert rec.t.dtype == np.float64 and rec.x.dtype == np.float64
    assert not rec.x.flags.writeable
    x[0] = 1.0  # the caller's array stays the caller's
    assert rec.x[0] == 0.0 and x.flags.writeable


def test_slice_is_exact_subrecording() -> None:
    rec = make_rec()
    part = rec.slice(50, 150)
    assert part.n == 100
    for key in ("t", "x", "u", "F"):
        assert same_bits(getattr(part, key), getattr(rec, key)[50:150])
    assert part.mass == rec.mass and part.name == rec.name
    assert "samples 50:150 of 200" in part.notes
    assert rec.slice(-20, None).n == 20  # type: ignore[arg-type]
    validate(part)
    with pytest.raises(FricjaxError) as err:
        rec.slice(150, 50)
    assert_one_line(err, "slice", "selects no sample")


def test_sha256_detects_one_ulp_and_mass() -> None:
    rec = make_rec()
    x = rec.x.copy()
    x[100] = np.nextafter(x[100], np.inf)
    assert replace(rec, x=x).sha256() != rec.sha256()
    assert replace(rec, mass=12.500000000000002).sha256() != rec.sha256()
    assert replace(rec, F=None).sha256() != rec.sha256()
    # Provenance is not content.
    assert replace(rec, name="other", notes="").sha256() == rec.sha256()
    assert len(rec.sha256()) == 64


# -------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("suffix", [".h5", ".hdf5"])
def test_hdf5_round_trip_preserves_every_field(tmp_path: Path, suffix: str) -> None:
    rec = make_rec()
    path = write_recording(rec, tmp_path / f"rec{suffix}")
    back = read_recording(path)
    for key in ("t", "x", "u", "F"):
        assert same_bits(getattr(back, key), getattr(rec, key)), key
    for key in ("mass", "name", "source", "u_unit", "notes"):
        assert getattr(back, key) == getattr(rec, key), key
    assert back.path == str(path)
    assert back.sha256() == rec.sha256()


def test_hdf5_round_trip_optional_fields_absent(tmp_path: Path) -> None:
    rec = make_rec(u=False, F=False, mass=None)
    back = read_recording(write_recording(rec, tmp_path / "rec.h5"))
    assert back.u is None and back.F is None and back.mass is None
    with h5py.File(tmp_path / "rec.h5", "r") as f:
        assert sorted(f.keys()) == ["t", "x"]
        assert f["t"].attrs["unit"] == "s" and f["x"].attrs["unit"] == "m"


@pytest.mark.parametrize("u,F", [(True, True), (False, False), (False, True), (True, False)])
def test_csv_round_trip_is_bit_exact(tmp_path: Path, u: bool, F: bool) -> None:
    rec = make_rec(u=u, F=F)
    path = write_recording(rec, tmp_path / "rec.csv")
    header = path.read_text().splitlines()[0]
    assert header == ",".join(k for k, on in (("t", 1), ("x", 1), ("u", u), ("F", F)) if on)
    back = read_recording(path, mass=rec.mass)
    for key in ("t", "x", "u", "F"):
        assert same_bits(getattr(back, key), getattr(rec, key)), key
    assert back.mass == rec.mass
    assert back.name == "rec"  # CSV carries no provenance; the name is the file stem
    assert read_recording(path).mass is None


def test_sha256_equal_across_memory_hdf5_csv(tmp_path: Path) -> None:
    rec = make_rec()
    h5 = read_recording(write_recording(rec, tmp_path / "a.h5"))
    csv = read_recording(write_recording(rec, tmp_path / "a.csv"), mass=rec.mass)
    assert rec.sha256() == h5.sha256() == csv.sha256()


def test_mass_argument_overrides_hdf5_attr(tmp_path: Path) -> None:
    path = write_recording(make_rec(mass=12.5), tmp_path / "rec.h5")
    assert read_recording(path, mass=3.0).mass == 3.0
    assert read_recording(path).mass == 12.5


def test_csv_reader_tolerates_spaces_and_blank_lines(tmp_path: Path) -> None:
    rows = "\n".join(f"{k * 0.5!r}, {k * 0.25!r}" for k in range(20))
    path = tmp_path / "r.csv"
    path.write_text(f"\n t , x \n{rows}\n\n")
    rec = read_recording(path, mass=1.0)
    assert rec.n == 20 and rec.dt == 0.5 and rec.x[-1] == 19 * 0.25


# ------------------------------------------------------------------------------- writing


def test_atomic_write_leaves_no_temp_file(tmp_path: Path) -> None:
    for name in ("a.h5", "a.csv"):
        write_recording(make_rec(), tmp_path / name)
        write_recording(make_rec(), tmp_path / name)  # overwrite
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.csv", "a.h5"]


@pytest.mark.parametrize("name", ["old.h5", "old.csv"])
def test_interrupted_write_keeps_previous_file(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, name: str
) -> None:
    path = tmp_path / name
    old = make_rec()
    write_recording(old, path)
    before = path.read_bytes()

    def half_h5(f: h5py.File, rec: Recording, truth: object) -> None:
        f.create_dataset("t", data=rec.t)
        raise KeyboardInterrupt("killed midway")

    def half_csv(fh: object, rec: Recording) -> None:
        fh.write("t,x\n0,0\n")  # type: ignore[attr-defined]
        raise KeyboardInterrupt("killed midway")

    monkeypatch.setattr(recording, "_write_hdf5_body", half_h5)
    monkeypatch.setattr(recording, "_write_csv_body", half_csv)
    new = replace(old, x=old.x + 1.0)
    with pytest.raises(KeyboardInterrupt):
        write_recording(new, path)
    assert path.read_bytes() == before
    assert leftovers(tmp_path) == []
    monkeypatch.undo()
    assert read_recording(path, mass=old.mass).sha256() == old.sha256()


def test_failed_rename_keeps_previous_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = write_recording(make_rec(), tmp_path / "r.h5")
    before = path.read_bytes()

    def no_replace(src: object, dst: object) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(recording.os, "replace", no_replace)
    with pytest.raises(OSError, match="disk full"):
        write_recording(replace(make_rec(), mass=1.0), path)
    assert path.read_bytes() == before and leftovers(tmp_path) == []


def test_write_refuses_invalid_recording_naming_target(tmp_path: Path) -> None:
    rec = make_rec()
    x = rec.x.copy()
    x[7] = np.nan
    with pytest.raises(FricjaxError) as err:
        write_recording(replace(rec, x=x), tmp_path / "out.h5")
    assert_one_line(err, "out.h5", "/x", "NaN at index 7")
    assert list(tmp_path.iterdir()) == []


def test_truth_written_as_attrs_and_subgroups(tmp_path: Path) -> None:
    truth = {
        "Fc": 20.5,
        "n_harmonics": 3,
        "model": "stribeck",
        "phases": np.array([0.1, 0.2, 0.3]),
        "effects": {"position_bump": {"x0": 0.1, "width": 0.01, "height": 5.0}},
    }
    path = write_recording(make_rec(), tmp_path / "syn.h5", truth=truth)
    with h5py.File(path, "r") as f:
        g = f["truth"]
        assert g.attrs["Fc"] == 20.5 and g.attrs["n_harmonics"] == 3
        assert g.attrs["model"] == "stribeck"
        np.testing.assert_array_equal(g.attrs["phases"], [0.1, 0.2, 0.3])
        assert g["effects/position_bump"].attrs["width"] == 0.01


def test_reading_never_opens_truth(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = write_recording(make_rec(), tmp_path / "syn.h5", truth={"Fc": 1.0, "sub": {"a": 2}})
    seen: list[str] = []
    orig_get, orig_contains = h5py.Group.__getitem__, h5py.Group.__contains__

    def get(self: h5py.Group, name: object) -> object:
        seen.append(str(name))
        return orig_get(self, name)

    def contains(self: h5py.Group, name: object) -> bool:
        seen.append(str(name))
        return orig_contains(self, name)

    monkeypatch.setattr(h5py.Group, "__getitem__", get)
    monkeypatch.setattr(h5py.Group, "__contains__", contains)
    rec = read_recording(path)
    assert seen and not any("truth" in s for s in seen)
    assert not any("truth" in f.lower() for f in vars(rec))


def test_truth_refused_for_csv_and_bad_values(tmp_path: Path) -> None:
    with pytest.raises(FricjaxError) as err:
        write_recording(make_rec(), tmp_path / "r.csv", truth={"Fc": 1.0})
    assert_one_line(err, "r.csv", "/truth", "CSV cannot store truth")
    with pytest.raises(FricjaxError) as err:
        write_recording(make_rec(), tmp_path / "r.h5", truth={"M": np.eye(2)})
    assert_one_line(err, "r.h5", "/truth/M", "unsupported truth value")
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------- refusing bad HDF5 files


def good_h5_content() -> dict[str, np.ndarray]:
    t = np.arange(64) * 1e-3
    return {"t": t, "x": np.sin(t), "u": np.cos(t), "F": np.ones(64)}


def _set(d: dict, key: str, idx: int, value: float) -> dict:
    d[key] = d[key].copy()
    d[key][idx] = value
    return d


def _jitter(d: dict) -> dict:
    d["t"] = d["t"].copy()
    d["t"][30] += 1e-3 * 3e-5  # EMPS-like float32 rounding of one sample
    return d


BAD_H5 = [
    # id, edit of the datasets, root attrs, dataset attrs, expected field, expected text
    ("no_t", lambda d: {k: v for k, v in d.items() if k != "t"}, {}, {}, "/t", "missing dataset"),
    ("no_x", lambda d: {k: v for k, v in d.items() if k != "x"}, {}, {}, "/x", "missing dataset"),
    ("x_str", lambda d: {**d, "x": np.array([b"a"] * 64)}, {}, {}, "/x", "wrong dtype"),
    ("F_complex", lambda d: {**d, "F": d["F"] + 1j}, {}, {}, "/F", "wrong dtype"),
    ("x_2d", lambda d: {**d, "x": d["x"].reshape(64, 1)}, {}, {}, "/x", "expected 1-D"),
    ("x_nan", lambda d: _set(d, "x", 17, np.nan), {}, {}, "/x", "contains NaN at index 17"),
    ("F_inf", lambda d: _set(d, "F", 40, -np.inf), {}, {}, "/F", "contains inf at index 40"),
    ("u_short", lambda d: {**d, "u": d["u"][:-1]}, {}, {}, "/u", "length 63 differs"),
    ("too_few", lambda d: {k: v[:10] for k, v in d.items()}, {}, {}, "/t", "only 10 samples"),
    (
        "t_back",
        lambda d: _set(d, "t", 20, d["t"][19]),
        {},
        {},
        "/t",
        "not strictly increasing at index 20",
    ),
    ("t_jitter", _jitter, {}, {}, "/t", "step not uniform: worst relative deviation 3e-05"),
    ("mass_neg", lambda d: d, {"mass": -2.0}, {}, "attr 'mass'", "positive finite"),
    ("mass_nan", lambda d: d, {"mass": np.nan}, {}, "attr 'mass'", "positive finite"),
    ("mass_str", lambda d: d, {"mass": "heavy"}, {}, "attr 'mass'", "positive finite"),
    ("x_mm", lambda d: d, {}, {"x": {"unit": "mm"}}, "/x", "wrong units 'mm'"),
    ("t_ms", lambda d: d, {}, {"t": {"unit": "ms"}}, "/t", "wrong units 'ms'"),
    ("name_num", lambda d: d, {"name": 3.0}, {}, "attr 'name'", "must be a string"),
]


@pytest.mark.parametrize(
    "edit,root_attrs,ds_attrs,field,text", [c[1:] for c in BAD_H5], ids=[c[0] for c in BAD_H5]
)
def test_bad_hdf5_is_refused_in_one_line(
    tmp_path: Path, edit, root_attrs, ds_attrs, field: str, text: str
) -> None:
    path = tmp_path / "broken_rec.h5"
    with h5py.File(path, "w") as f:
        for key, value in edit(good_h5_content()).items():
            ds = f.create_dataset(key, data=value)
            for a, v in ds_attrs.get(key, {}).items():
                ds.attrs[a] = v
        f.attrs["mass"] = 10.0
        for a, v in root_attrs.items():
            f.attrs[a] = v
    with pytest.raises(FricjaxError) as err:
        read_recording(path)
    assert_one_line(err, "broken_rec.h5", field, text)


def test_wrong_units_message_suggests_conversion(tmp_path: Path) -> None:
    path = tmp_path / "mm.h5"
    with h5py.File(path, "w") as f:
        f["t"] = np.arange(32) * 1e-3
        f["x"] = np.zeros(32)
        f["x"].attrs["unit"] = "mm"
    with pytest.raises(FricjaxError) as err:
        read_recording(path)
    assert_one_line(err, "multiply by 0.001", "metres")


def test_nonuniform_message_gives_worst_deviation_and_suggests_resampling() -> None:
    t = np.arange(64) * 1e-3
    t[10] += 2e-9  # relative deviation 2e-6 on steps 9->10 and 10->11
    with pytest.raises(FricjaxError) as err:
        validate(Recording(t=t, x=np.zeros(64)))
    assert_one_line(err, "<memory>: /t", "worst relative deviation 2e-06", "resample")


def test_jitter_below_limit_is_accepted() -> None:
    t = np.arange(64) * 1e-3
    t[10] += 5e-10  # 5e-7 relative < 1e-6
    rec = Recording(t=t, x=np.zeros(64))
    assert validate(rec) is rec


def test_min_samples_is_configurable() -> None:
    rec = make_rec().slice(0, 8)
    assert validate(rec, min_samples=8) is rec
    with pytest.raises(FricjaxError) as err:
        validate(rec)
    assert_one_line(err, "/t", "only 8 samples, at least 16 needed")


def test_unknown_suffix_missing_file_and_not_hdf5(tmp_path: Path) -> None:
    with pytest.raises(FricjaxError) as err:
        read_recording(tmp_path / "rec.txt")
    assert_one_line(err, "rec.txt", "unknown recording format '.txt'")
    with pytest.raises(FricjaxError) as err:
        write_recording(make_rec(), tmp_path / "rec.npz")
    assert_one_line(err, "rec.npz", "unknown recording format")
    with pytest.raises(FricjaxError) as err:
        read_recording(tmp_path / "absent.h5")
    assert_one_line(err, "absent.h5", "no such file")
    (tmp_path / "fake.h5").write_text("t,x\n")
    with pytest.raises(FricjaxError) as err:
        read_recording(tmp_path / "fake.h5")
    assert_one_line(err, "fake.h5", "not a readable HDF5 file")


# ------------------------------------------------------------------ refusing bad CSV files


def csv_text(header: str = "t,x,u", edit: dict[int, str] | None = None) -> str:
    """30 valid data rows; ``edit`` replaces data row i (0-based) by the given text."""
    rows = [f"{k * 1e-3!r},{k * 1e-6!r},{k * 0.5!r}" for k in range(30)]
    for i, line in (edit or {}).items():
        rows[i] = line
    return header + "\n" + "\n".join(rows) + "\n"


BAD_CSV = [
    ("no_t", csv_text("x,u,F"), "column 't'", "missing from header"),
    ("no_x", csv_text("t,u,F"), "column 'x'", "missing from header"),
    ("unknown", csv_text("t,x,v"), "column 'v'", "unknown column name"),
    ("dup", csv_text("t,x,x"), "column 'x'", "more than once"),
    (
        "unparsable",
        csv_text(edit={5: "0.005,5e-6;,2.5"}),
        "column 'x'",
        "data row 6 (line 7): cannot parse '5e-6;'",
    ),
    ("short_row", csv_text(edit={30 - 1: "0.029,2e-5"}), "line 31", "data row 30 has 2 values"),
    ("empty", "\n\n", "header", "empty file"),
    ("nan", csv_text(edit={25: "0.025,nan,12.5"}), "column 'x'", "contains NaN at index 25"),
]


@pytest.mark.parametrize("text,field,msg", [c[1:] for c in BAD_CSV], ids=[c[0] for c in BAD_CSV])
def test_bad_csv_is_refused_in_one_line(tmp_path: Path, text: str, field: str, msg: str) -> None:
    path = tmp_path / "broken.csv"
    path.write_text(text)
    with pytest.raises(FricjaxError) as err:
        read_recording(path, mass=1.0)
    assert_one_line(err, "broken.csv", field, msg)


def test_csv_mass_argument_checked(tmp_path: Path) -> None:
    path = write_recording(make_rec(), tmp_path / "r.csv")
    with pytest.raises(FricjaxError) as err:
        read_recording(path, mass=-1.0)
    # the flag is at fault, not the file
    assert_one_line(err, "--mass", "positive finite")
    assert "r.csv" not in str(err.value)


# ---------------------------------------------------------------------------- require_mass


def test_require_mass() -> None:
    rec = make_rec(mass=None)
    with pytest.raises(FricjaxError) as err:
        require_mass(replace(rec, path="data/run3.csv"))
    assert str(err.value) == (
        "data/run3.csv: attr 'mass': missing "
        "(give --mass or make mass a free parameter in the config)"
    )
    for bad in (0.0, -1.0, np.nan, np.inf, True):
        with pytest.raises(FricjaxError) as err:
            require_mass(replace(rec, mass=bad))
        assert_one_line(err, "<memory>: attr 'mass'", "positive finite")
    assert require_mass(replace(rec, mass=np.float32(2.5))) == 2.5
    assert isinstance(require_mass(replace(rec, mass=3)), float)


# ------------------------------------------------- optional reference position /r


def with_reference(rec: Recording) -> Recording:
    return replace(rec, r=rec.x + 1e-4 * np.cos(np.arange(rec.n)))


def test_reference_round_trips_hdf5_and_csv_bit_exact(tmp_path: Path) -> None:
    rec = with_reference(make_rec())
    for name in ("rec.h5", "rec.csv"):
        back = read_recording(write_recording(rec, tmp_path / name), mass=rec.mass)
        assert same_bits(back.r, rec.r), name
        assert back.sha256() == rec.sha256(), name
    with h5py.File(tmp_path / "rec.h5", "r") as f:
        assert f["r"].attrs["unit"] == "m"
    assert (tmp_path / "rec.csv").read_text().splitlines()[0] == "t,x,u,F,r"
    part = rec.slice(10, 30)
    assert same_bits(part.r, rec.r[10:30])


def test_reference_absent_leaves_checksum_of_layout_v1_unchanged() -> None:
    # The v1 checksum of a file without /r, written out independently of the class.
    import hashlib

    rec = make_rec()
    h = hashlib.sha256(b"fricjax-recording-v1\0")
    for key in ("t", "x", "u", "F"):
        data = np.asarray(getattr(rec, key), dtype="<f8")
        h.update(f"{key}:{data.shape};".encode())
        h.update(data.tobytes())
    h.update(f"mass:{float(rec.mass).hex()};".encode())
    assert rec.r is None and rec.sha256() == h.hexdigest()
    assert with_reference(rec).sha256() != rec.sha256()


def test_reference_is_validated_like_the_other_signals(tmp_path: Path) -> None:
    rec = with_reference(make_rec())
    r = rec.r.copy()
    r[7] = np.nan
    with pytest.raises(FricjaxError) as err:
        validate(replace(rec, r=r, path="rec.h5"))
    assert_one_line(err, "rec.h5", "/r", "NaN at index 7")
    with pytest.raises(FricjaxError) as err:
        validate(replace(rec, r=rec.r[:-1], path="rec.h5"))
    assert_one_line(err, "/r", "length 199 differs")
    path = write_recording(rec, tmp_path / "mm.h5")
    with h5py.File(path, "r+") as f:
        f["r"].attrs["unit"] = "mm"
    with pytest.raises(FricjaxError) as err:
        read_recording(path)
    assert_one_line(err, "mm.h5", "/r", "wrong units 'mm'", "multiply by 0.001")


def test_rotary_axis_attr_round_trips_and_rotary_units_need_it(tmp_path: Path) -> None:
    t = np.arange(20) / 100.0
    rec = Recording(t=t, x=0.5 * t, F=np.ones(20), mass=0.02, axis="rotary")
    path = write_recording(rec, tmp_path / "r.h5")
    with h5py.File(path) as f:
        assert f["x"].attrs["unit"] == "rad" and f["F"].attrs["unit"] == "N·m"
        assert f.attrs["axis"] == "rotary"
    assert read_recording(path).axis == "rotary"
    linear = write_recording(Recording(t=t, x=0.5 * t, mass=1.0), tmp_path / "l.h5")
    assert read_recording(linear).axis == ""  # not stated: the config decides
    with h5py.File(linear, "a") as f:
        f["x"].attrs["unit"] = "rad"
    with pytest.raises(FricjaxError, match="is rotary; set root attr axis = 'rotary'"):
        read_recording(linear)
