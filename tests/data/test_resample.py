"""A second sensor at another rate, resampled onto the motion's grid."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fricjax.data.recording import Recording, read_recording, write_recording
from fricjax.data.resample import merge_sensor, resample_onto
from fricjax.errors import FricjaxError


def band(t: np.ndarray) -> np.ndarray:
    """The force the load cell should report [N]: lines at 3, 17 and 60 Hz."""
    return (
        30.0 * np.sin(2 * np.pi * 3.0 * t)
        + 10.0 * np.sin(2 * np.pi * 17.0 * t + 0.5)
        + 4.0 * np.sin(2 * np.pi * 60.0 * t + 1.0)
    )


def test_a_2khz_load_cell_on_a_1_5khz_grid_matches_within_1e_6_and_drops_the_alias() -> None:
    # 2 kHz sensor with a 900 Hz vibration that a 1.5 kHz grid cannot hold (its Nyquist
    # frequency is 750 Hz): sampled plainly it would fold to 600 Hz at full amplitude.
    t_sensor = np.arange(8000) / 2000.0
    y = band(t_sensor) + 5.0 * np.sin(2 * np.pi * 900.0 * t_sensor)
    t_motion = np.arange(5990) / 1500.0
    out, keep, method = resample_onto(t_sensor, y, t_motion)
    assert keep == slice(0, 5990)
    assert "anti-aliased" in method and "600 Hz" in method and "cubic-spline" in method
    err = out - band(t_motion[keep])
    inner = slice(75, -75)  # 50 ms from the ends: the filter's end transient
    assert np.max(np.abs(err[inner])) < 1e-6 * 44.0  # 44 N peak of the band
    plain = np.interp(t_motion, t_sensor, y) - band(t_motion)
    assert np.max(np.abs(plain[inner])) > 4.0  # what anti-aliasing removed


def test_a_slower_sensor_is_interpolated_and_the_span_is_cropped() -> None:
    t_sensor = 0.1 + np.arange(1000) / 500.0  # 500 Hz, starts 0.1 s late
    t_motion = np.arange(2200) / 1000.0
    out, keep, method = resample_onto(t_sensor, band(t_sensor), t_motion)
    assert keep.start == 100 and t_motion[keep.stop - 1] <= t_sensor[-1]
    # 100 before the sensor starts (0.1 s), 101 after it ends (2.098 s)
    assert "not filtered" in method and "201 motion samples" in method
    # cubic spline on 500 Hz samples: (2π·60/500)^4/384 = 8.4e-4 of the 4 N line at 60 Hz
    # (3.4e-3 N) in the interior; the not-a-knot ends are ten times worse
    err = np.abs(out - band(t_motion[keep]))
    assert np.max(err[20:-20]) < 5e-3
    assert np.max(err) < 0.05


def test_merge_writes_f_on_the_motion_grid_and_states_the_method(tmp_path: Path) -> None:
    t = np.arange(3000) / 1500.0
    motion = write_recording(
        Recording(t=t, x=0.01 * np.sin(2 * np.pi * t), mass=2.0), tmp_path / "m.h5"
    )
    t_s = np.arange(4000) / 2000.0
    sensor = tmp_path / "load.csv"
    rows = (f"{a:.17g},{b:.17g}" for a, b in zip(t_s, band(t_s), strict=True))
    sensor.write_text("t,F\n" + "\n".join(rows))
    merged = merge_sensor(motion, sensor)
    path = write_recording(merged, tmp_path / "rec.h5")
    back = read_recording(path)
    assert back.n == merged.n and back.F is not None
    assert "load.csv column 'F'" in back.notes and "anti-aliased" in back.notes
    inner = slice(75, -75)
    assert np.max(np.abs(back.F[inner] - band(back.t)[inner])) < 1e-4
    with pytest.raises(FricjaxError, match="column 'Fz'"):
        merge_sensor(motion, sensor, column="Fz")
