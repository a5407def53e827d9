"""A second sensor at another rate, brought onto the motion's time grid (``fricjax merge``).

A load cell logged at 2 kHz beside a 1.5 kHz drive log must be sampled at the motion's
times ``t_k`` before the equation error can compare it with ``m·a``. Method (stated in the
merged recording's ``notes``):

1. **Anti-alias** (only when the sensor is faster than the motion grid): a zero-phase
   Butterworth low-pass of order :data:`AA_ORDER` applied forward and backward
   (:func:`fricjax.data.filters.filtfilt_lowpass`, odd end padding) at
   ``f_aa = AA_FRACTION · f_motion`` (0.4 × the motion rate, i.e. 80 % of its Nyquist
   frequency). Gain ``|H|² = 1/(1 + (w/w_aa)^(2·order))``: ≥ 0.9999 below 0.2·f_motion,
   ≤ 1e-4 above 0.55·f_motion, so nothing above the motion's Nyquist frequency folds back.
2. **Interpolation**: a not-a-knot cubic spline through the (filtered) sensor samples,
   evaluated at the motion's times. Error on a sinusoid of frequency f sampled at f_s: of
   order ``(2πf/f_s)⁴/384`` of its amplitude (2e-7 at 20 Hz and 2 kHz).

Motion samples outside the sensor's time span are dropped (no extrapolation), and the
number dropped is stated. The sensor's clock must be the motion's clock (same t = 0); a
constant delay between the two loggers is not estimated here.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
from jaxtyping import Float

from fricjax.data.filters import filtfilt_lowpass
from fricjax.data.recording import Recording, read_recording
from fricjax.errors import FricjaxError, where

#: Anti-alias cutoff as a fraction of the motion's sampling rate.
AA_FRACTION = 0.4
#: Order of the anti-alias Butterworth (applied twice: zero phase).
AA_ORDER = 8
#: Largest relative step jitter of the sensor's clock the anti-alias filter accepts (it
#: assumes the mean step).
MAX_SENSOR_JITTER = 0.01


def resample_onto(
    t_src: Float[np.ndarray, " m"],
    y_src: Float[np.ndarray, " m"],
    t_dst: Float[np.ndarray, " n"],
    *,
    source: str = "sensor",
) -> tuple[Float[np.ndarray, " k"], slice, str]:
    """The sensor ``y_src`` [any unit] sampled at ``t_src`` [s], brought onto ``t_dst`` [s].

    Returns:
        ``(y [k], keep, method)``: ``y`` at ``t_dst[keep]``, ``keep`` the contiguous
        motion samples inside the sensor's span, ``method`` one line for the notes.

    Raises:
        FricjaxError: mismatched or non-finite arrays, time not increasing, a sensor clock
            jitter above 1 %, or no overlap of the two time spans.
    """
    t_src = np.asarray(t_src, dtype=np.float64)
    y_src = np.asarray(y_src, dtype=np.float64)
    t_dst = np.asarray(t_dst, dtype=np.float64)
    if t_src.ndim != 1 or t_src.shape != y_src.shape or t_src.shape[0] < 4:
        raise FricjaxError(f"{where(source)}: need t and the signal as 1-D arrays of >= 4 samples")
    for name, arr in (("t", t_src), ("signal", y_src)):
        if not np.isfinite(arr).all():
            i = int(np.argmax(~np.isfinite(arr)))
            raise FricjaxError(f"{where(source, name)}: not finite at index {i}")
    steps = np.diff(t_src)
    if not (steps > 0).all():
        i = int(np.argmax(steps <= 0)) + 1
        raise FricjaxError(f"{where(source, 't')}: not strictly increasing at index {i}")
    dt_src = float((t_src[-1] - t_src[0]) / (t_src.shape[0] - 1))
    jitter = float(np.max(np.abs(steps - dt_src)) / dt_src)
    if jitter > MAX_SENSOR_JITTER:
        raise FricjaxError(
            f"{where(source, 't')}: clock jitter {jitter:.2g} of the mean step "
            f"(> {MAX_SENSOR_JITTER:g}); the anti-alias filter needs a near-uniform sensor clock"
        )
    inside = np.flatnonzero((t_dst >= t_src[0]) & (t_dst <= t_src[-1]))
    if inside.size < 4:
        raise FricjaxError(
            f"{where(source, 't')}: spans {t_src[0]:g}..{t_src[-1]:g} s, which holds fewer "
            f"than 4 motion samples (motion {t_dst[0]:g}..{t_dst[-1]:g} s); same clock?"
        )
    keep = slice(int(inside[0]), int(inside[-1]) + 1)
    fs_src = 1.0 / dt_src
    fs_dst = 1.0 / float((t_dst[-1] - t_dst[0]) / (t_dst.shape[0] - 1))
    cutoff = AA_FRACTION * fs_dst
    y = y_src
    if cutoff < 0.5 * fs_src:
        n_sections = (AA_ORDER + 1) // 2
        padlen = min(max(3 * (2 * n_sections + 1), math.ceil(3 * fs_src / cutoff)), y.shape[0] - 1)
        y = filtfilt_lowpass(y, AA_ORDER, cutoff, fs_src, padlen)
        filt = (
            f"anti-aliased by a zero-phase order-{AA_ORDER} Butterworth at {cutoff:.6g} Hz "
            f"(0.4 x {fs_dst:.6g} Hz)"
        )
    else:
        filt = "not filtered (sensor no faster than the motion)"
    from scipy.interpolate import CubicSpline

    out = CubicSpline(t_src, y, bc_type="not-a-knot")(t_dst[keep])
    dropped = t_dst.shape[0] - (keep.stop - keep.start)
    method = (
        f"{fs_src:.6g} Hz sensor {filt}, then cubic-spline interpolated onto the {fs_dst:.6g} Hz "
        f"motion grid; {dropped} motion samples outside the sensor's span dropped"
    )
    return out, keep, method


def read_sensor_csv(path: str | Path, column: str) -> tuple[np.ndarray, np.ndarray]:
    """``(t [s], column)`` from a CSV with a header naming ``t`` and ``column``."""
    path = Path(path)
    try:
        lines = path.read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise FricjaxError(f"{where(path)}: cannot read as UTF-8 text ({exc})") from None
    rows = [line for line in lines if line.strip()]
    if not rows:
        raise FricjaxError(f"{where(path, 'header')}: empty file")
    header = [c.strip() for c in rows[0].split(",")]
    for name in ("t", column):
        if name not in header:
            raise FricjaxError(
                f"{where(path, f'column {name!r}')}: missing from header {rows[0]!r}"
            )
    try:
        data = np.loadtxt(rows[1:], delimiter=",", dtype=np.float64, ndmin=2, comments=None)
    except ValueError as exc:
        raise FricjaxError(f"{where(path)}: cannot parse the data rows ({exc})") from None
    if data.shape[1] != len(header):
        raise FricjaxError(f"{where(path)}: rows have {data.shape[1]} values, header {len(header)}")
    return data[:, header.index("t")], data[:, header.index(column)]


def merge_sensor(
    motion: str | Path | Recording,
    sensor: str | Path,
    *,
    column: str = "F",
    as_signal: str = "F",
    u_unit: str = "",
    mass: float | None = None,
) -> Recording:
    """The motion recording with the sensor's ``column`` resampled onto its grid as ``/F``
    (``as_signal="F"``, newtons) or ``/u`` (``"u"``, unit ``u_unit``); the method is
    appended to the notes (module docstring)."""
    rec = motion if isinstance(motion, Recording) else read_recording(motion, mass=mass)
    if mass is not None:
        rec = replace(rec, mass=mass)
    if as_signal not in ("F", "u"):
        raise FricjaxError(f"--as: must be F or u, got {as_signal!r}")
    t_src, y_src = read_sensor_csv(sensor, column)
    y, keep, method = resample_onto(t_src, y_src, rec.t, source=str(sensor))
    part = rec.slice(keep.start, keep.stop) if (keep.start, keep.stop) != (0, rec.n) else rec
    note = f"{as_signal} from {Path(sensor).name} column {column!r}: {method}"
    extra = {"F": y} if as_signal == "F" else {"u": y, "u_unit": u_unit or rec.u_unit}
    return replace(part, **extra, notes=f"{part.notes}; {note}" if part.notes else note, path="")
