"""MAT import: variable mapping, exact time grid, resampling, refusals, EMPS data."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.io

from fricjax.data.importers import EMPS_MAP, import_mat
from fricjax.data.recording import read_recording, validate, write_recording
from fricjax.errors import FricjaxError

N = 500
DT = 1e-3


def float32_clock(n: int = N, dt: float = DT, t0: float = 0.0) -> np.ndarray:
    """A k·dt clock stored in single precision, as in the EMPS files (jitter ~1e-8 s)."""
    return (t0 + np.arange(n) * dt).astype(np.float32).astype(np.float64)


def write_mat(path: Path, **variables: np.ndarray) -> Path:
    scipy.io.savemat(path, {k: np.asarray(v) for k, v in variables.items()})
    return path


def assert_one_line(err: pytest.ExceptionInfo[FricjaxError], *parts: str) -> None:
    msg = str(err.value)
    assert "\n" not in msg
    for part in parts:
        assert part in msg, f"{part!r} not in {msg!r}"


def test_jittered_clock_rebuilt_as_exact_grid(tmp_path: Path) -> None:
    t = float32_clock(t0=2.0)
    jitter = np.max(np.abs(np.diff(t) - DT)) / DT
    assert jitter > 1e-6  # the raw base would be refused by layout v1
    # Affine signals: linear interpolation onto the grid must reproduce them exactly
    # (to rounding), which checks both the weights and the end extrapolation.
    qm = 0.1 + 0.05 * t
    vir = -3.0 + 2.0 * t
    path = write_mat(tmp_path / "run.mat", t=t[:, None], qm=qm[:, None], vir=vir[:, None])
    rec = import_mat(path, mass=95.0, u_unit="V")
    k = np.arange(N)
    assert rec.dt == pytest.approx(DT, rel=1e-12)
    np.testing.assert_array_equal(rec.t, t[0] + k * 1e-3)  # the round step, exactly
    np.testing.assert_allclose(rec.x, 0.1 + 0.05 * rec.t, rtol=0, atol=1e-15)
    np.testing.assert_allclose(rec.u, -3.0 + 2.0 * rec.t, rtol=0, atol=1e-14)
    assert rec.F is None and rec.mass == 95.0 and rec.u_unit == "V"
    assert rec.source == "run.mat" and rec.name == "run" and rec.path == str(path)
    dev = np.max(np.abs(t - rec.t))
    assert f"max |t - grid| = {dev:.3g} s" in rec.notes
    assert "x, u linearly interpolated" in rec.notes
    assert validate(rec) is rec


def test_resampling_error_bounded_by_slope_times_time_shift(tmp_path: Path) -> None:
    t = float32_clock(n=2000)
    x = np.sin(2 * np.pi * 5.0 * t)  # |dx/dt| <= 10*pi
    rec = import_mat(write_mat(tmp_path / "s.mat", t=t, qm=x, vir=x), mass=1.0)
    shift = np.max(np.abs(t - rec.t))
    err = np.max(np.abs(rec.x - np.sin(2 * np.pi * 5.0 * rec.t)))
    # First-order error slope*shift plus the curvature term of linear interpolation.
    assert err <= 10 * np.pi * shift + (2 * np.pi * 5.0) ** 2 * DT**2 / 8


def test_uniform_clock_passes_values_through_unchanged(tmp_path: Path) -> None:
    t = np.arange(N) * DT
    rng = np.random.default_rng(7)
    x, u, F = rng.standard_normal((3, N))
    path = write_mat(tmp_path / "u.mat", time=t, pos=x, drive=u, force=F)
    rec = import_mat(path, mapping={"t": "time", "x": "pos", "u": "drive", "F": "force"})
    for got, want in ((rec.t, t), (rec.x, x), (rec.u, u), (rec.F, F)):
        assert got.tobytes() == want.tobytes()
    assert "not resampled" in rec.notes and rec.mass is None


def test_given_dt_is_used(tmp_path: Path) -> None:
    t = float32_clock(dt=1 / 3000)
    path = write_mat(tmp_path / "d.mat", t=t, qm=t)
    tx = {"t": "t", "x": "qm"}
    rec = import_mat(path, mapping=tx, dt=1 / 3000)
    np.testing.assert_array_equal(rec.t, np.arange(N) * (1 / 3000))
    # A step with no short decimal form is still found when dt is not given: the
    # estimated grid stays on the true clock to within a tenth of the float32 jitter.
    true = np.arange(N) / 3000
    est = import_mat(path, mapping=tx).t
    assert np.max(np.abs(est - true)) <= 1.1 * np.max(np.abs(t - true))
    assert abs(est[-1] - true[-1]) <= 0.1 * np.max(np.abs(t - true)) + 1e-15
    with pytest.raises(FricjaxError) as err:
        import_mat(path, mapping=tx, dt=1e-3)
    assert_one_line(err, "d.mat", "variable 't'", "too far from uniform")


def test_far_from_uniform_clock_refused(tmp_path: Path) -> None:
    t = np.arange(N) * DT
    t[100:] += 0.3 * DT  # a dropped-sample-like jump: not float rounding
    path = write_mat(tmp_path / "gap.mat", t=t, qm=np.zeros(N), vir=np.zeros(N))
    with pytest.raises(FricjaxError) as err:
        import_mat(path)
    assert_one_line(err, "gap.mat", "variable 't'", "too far from uniform", "limit 0.01")


def test_missing_variable_lists_available(tmp_path: Path) -> None:
    path = write_mat(tmp_path / "m.mat", t=np.arange(N) * DT, qm=np.zeros(N), kp=160.18)
    with pytest.raises(FricjaxError) as err:
        import_mat(path)
    assert_one_line(err, "m.mat", "variable 'vir'", "missing", "available: kp, qm, t")


@pytest.mark.parametrize(
    "variables,field,text",
    [
        ({"qm": np.zeros((N, 2))}, "variable 'qm'", "expected a vector"),
        ({"qm": np.zeros(N - 3)}, "variable 'qm'", f"length {N - 3} differs"),
        ({"qm": np.array(["ab"] * N)}, "variable 'qm'", "wrong dtype"),
        ({"qm": np.where(np.arange(N) == 9, np.nan, 0.0)}, "variable 'qm'", "NaN at index 9"),
        ({"t": np.arange(N)[::-1] * DT}, "variable 't'", "not strictly increasing at index 1"),
    ],
)
def test_malformed_variables_refused(
    tmp_path: Path, variables: dict, field: str, text: str
) -> None:
    base = {"t": np.arange(N) * DT, "qm": np.zeros(N), "vir": np.zeros(N)}
    path = write_mat(tmp_path / "bad.mat", **{**base, **variables})
    with pytest.raises(FricjaxError) as err:
        import_mat(path)
    assert_one_line(err, "bad.mat", field, text)


def test_bad_file_mapping_and_mass(tmp_path: Path) -> None:
    fake = tmp_path / "fake.mat"
    fake.write_bytes(b"not a mat file at all" * 10)
    with pytest.raises(FricjaxError) as err:
        import_mat(fake)
    assert_one_line(err, "fake.mat", "cannot read as a MAT file")
    with pytest.raises(FricjaxError) as err:
        import_mat(tmp_path / "absent.mat")
    assert_one_line(err, "absent.mat", "no such file")
    good = write_mat(tmp_path / "g.mat", t=np.arange(N) * DT, qm=np.zeros(N))
    with pytest.raises(FricjaxError) as err:
        import_mat(good, mapping={"t": "t", "y": "qm"})
    assert_one_line(err, "g.mat", "mapping 'y'", "unknown field")
    with pytest.raises(FricjaxError) as err:
        import_mat(good, mapping={"t": "t", "x": "qm"}, mass=0.0)
    # a MAT file holds no mass: the caller's value (the --mass flag) is blamed
    assert_one_line(err, "--mass", "positive finite")


@pytest.fixture(scope="module")
def emps_mat(emps_dir: Path) -> Path:
    return emps_dir / "DATA_EMPS.mat"


def test_emps_import(emps_mat: Path, tmp_path: Path) -> None:
    raw = scipy.io.loadmat(emps_mat)
    qm, vir = raw["qm"].ravel(), raw["vir"].ravel()
    rec = import_mat(emps_mat, mass=95.1089, u_unit="V")
    assert rec.n == 24841 and rec.dt == 1e-3
    np.testing.assert_array_equal(rec.t, np.arange(24841) * 1e-3)
    # The clock error is float32 rounding, 3.2e-8 s; moving |v| <= 0.13 m/s samples by
    # that much changes x by < 5e-9 m, a tenth of the 5e-8 m encoder step.
    assert np.max(np.abs(raw["t"].ravel() - rec.t)) < 3.3e-8
    assert np.max(np.abs(rec.x - qm)) < 5e-9
    assert np.max(np.abs(rec.u - vir)) < 1e-3 * np.max(np.abs(vir))
    assert rec.source == "DATA_EMPS.mat" and rec.u_unit == "V" and rec.F is None
    assert dict(EMPS_MAP) == {"t": "t", "x": "qm", "u": "vir"}
    back = read_recording(write_recording(rec, tmp_path / "emps.h5"))
    assert back.sha256() == rec.sha256() and back.notes == rec.notes


def test_reference_variable_mapped_to_r_and_resampled(tmp_path: Path) -> None:
    t = float32_clock()
    qg = 0.2 - 0.03 * t  # affine: linear interpolation onto the grid is exact
    path = write_mat(tmp_path / "cl.mat", t=t, qm=qg + 1e-6, qg=qg[:, None])
    rec = import_mat(path, mapping={"t": "t", "x": "qm", "r": "qg"})
    np.testing.assert_allclose(rec.r, 0.2 - 0.03 * rec.t, rtol=0, atol=1e-15)
    assert "x, r linearly interpolated" in rec.notes and rec.u is None
    with pytest.raises(FricjaxError) as err:
        import_mat(path, mapping={"t": "t", "x": "qm", "q": "qg"})
    assert_one_line(err, "mapping 'q'", "allowed: t, x, u, F, r")


def test_emps_reference_is_qg(emps_mat: Path) -> None:
    raw = scipy.io.loadmat(emps_mat)
    rec = import_mat(emps_mat, mapping={**EMPS_MAP, "r": "qg"}, u_unit="V")
    # qg moves at most 0.13 m/s: the 3.2e-8 s clock shift moves it by < 5e-9 m.
    assert np.max(np.abs(rec.r - raw["qg"].ravel())) < 5e-9
