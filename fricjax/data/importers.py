"""Import recordings from other formats into :class:`~fricjax.data.recording.Recording`.

MATLAB files (``.mat``, v4 to v7.2, read with :func:`scipy.io.loadmat`) name their signals
freely, so :func:`import_mat` maps MAT variables onto the fields t, x, u, F. Many
recorders store time in single precision: the EMPS benchmark's ``t`` deviates from
k·1 ms by up to 3.2e-8 s, a step jitter of 4e-5 relative, which layout v1 refuses
(< 1e-6). Such a nearly uniform time base is rebuilt as the exact grid

    t_k = t_0 + k·dt,   k = 0 … n−1,

and x, u, F are moved onto it by linear interpolation, y(t_k) ≈ y_i + (t_k − t_i)·
(y_{i+1} − y_i)/(t_{i+1} − t_i). With |t − grid| ≤ 3.2e-8 s and |ẋ| ≤ 0.13 m/s this
changes the EMPS position by at most ~4e-9 m, below its 5e-8 m encoder resolution.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path

import numpy as np
import scipy.io
from jaxtyping import Float
from scipy.io.matlab import MatReadError

from fricjax.data.recording import (
    MASS_FLAG,
    MAX_STEP_JITTER,
    Recording,
    check_mass,
    validate_arrays,
)
from fricjax.errors import FricjaxError, where

__all__ = ["EMPS_MAP", "MAX_GRID_DEVIATION", "import_mat"]

#: Variables of the EMPS benchmark files (Janot, Gautier & Brunot 2019): time ``t`` [s],
#: motor position on the load side ``qm`` [m], controller output ``vir`` [V].
EMPS_MAP: Mapping[str, str] = {"t": "t", "x": "qm", "u": "vir"}

#: Largest max_k |t_k − grid_k| / dt that is still treated as jitter of a uniform clock and
#: resampled; beyond it the samples are not on a clock and the import is refused.
MAX_GRID_DEVIATION = 1e-2

_FIELDS = ("t", "x", "u", "F", "r")


def import_mat(
    path: str | Path,
    *,
    mapping: Mapping[str, str] = EMPS_MAP,
    mass: float | None = None,
    u_unit: str = "",
    name: str | None = None,
    dt: float | None = None,
) -> Recording:
    """Read a MAT file as a validated recording, on an exact uniform time grid.

    Args:
        path: ``.mat`` file (v4 to v7.2).
        mapping: field → MAT variable; ``t`` and ``x`` required, ``u``, ``F`` and ``r``
            (reference position of a closed-loop rig, e.g. EMPS ``qg``) optional.
            Variables may be vectors or (n, 1) / (1, n) columns.
        mass: moving mass, kg (MAT files carry none).
        u_unit: unit of the drive input u (e.g. "V" for EMPS ``vir``).
        name: recording name; the file stem if None.
        dt: time step of the rebuilt grid, s; estimated from ``t`` if None.

    The time base is kept as it is when its step jitter max_k |Δt_k − dt̄| / dt̄ is below
    1e-6 and ``dt`` is not given. Otherwise it is replaced by t_k = t_0 + k·dt, with dt
    the least-squares slope of t against k rounded to the fewest significant digits
    (6 or more) that keep the grid on the clock (see :func:`_grid_step`), and the other
    signals are linearly interpolated onto it. The notes record the maximum |t − grid|.

    Raises:
        FricjaxError: unreadable file, missing or malformed variable (the message lists
            the variables available), time base too far from uniform
            (max |t − grid| ≥ 1e-2·dt), or any layout v1 violation.
    """
    path = Path(path)
    for key in mapping:
        if key not in _FIELDS:
            raise FricjaxError(
                f"{where(path, f'mapping {key!r}')}: unknown field (allowed: t, x, u, F, r)"
            )
    for key in ("t", "x"):
        if key not in mapping:
            raise FricjaxError(f"{where(path, f'mapping {key!r}')}: missing (t and x are needed)")
    if mass is not None:  # a MAT file holds no mass: a bad one is the caller's flag
        mass = check_mass(mass, MASS_FLAG)
    if not path.is_file():
        raise FricjaxError(f"{where(path)}: no such file")
    if path.stat().st_size == 0:
        raise FricjaxError(f"{where(path)}: empty file (0 bytes), not a MAT file")
    try:
        data = scipy.io.loadmat(path)
    except (ValueError, NotImplementedError, OSError, TypeError, MatReadError) as exc:
        raise FricjaxError(
            f"{where(path)}: cannot read as a MAT file v4-v7.2 ({exc}); "
            "v7.3 files are HDF5: save with -v7 or convert"
        ) from None
    available = sorted(k for k in data if not k.startswith("__"))
    labels = {key: f"variable {var!r}" for key, var in mapping.items()}
    labels["mass"] = "mass"
    signals: dict[str, np.ndarray] = {}
    for key, var in mapping.items():
        if var not in data:
            raise FricjaxError(
                f"{where(path, labels[key])}: missing (mapped to field {key!r}); "
                f"available: {', '.join(available) or 'none'}"
            )
        signals[key] = _vector(path, labels[key], data[var])

    rec = Recording(
        **signals,
        mass=mass,
        name=path.stem if name is None else name,
        source=path.name,
        u_unit=u_unit,
        path=str(path),
    )
    # Everything but uniformity first, so the grid is built only on finite, increasing t.
    validate_arrays(rec, min_samples=16, labels=labels, check_uniform=False)

    t = rec.t
    n = rec.n
    steps = np.diff(t)
    mean_step = (t[-1] - t[0]) / (n - 1)
    jitter = float(np.max(np.abs(steps - mean_step)) / mean_step)
    mapped = ", ".join(f"{k} = {v!r}" for k, v in mapping.items())
    if dt is None and jitter < MAX_STEP_JITTER:
        notes = f"imported from {path.name} ({mapped}); time base uniform, not resampled"
        return validate_arrays(
            replace(rec, notes=notes), min_samples=16, labels=labels, check_uniform=True
        )

    step = _grid_step(t) if dt is None else float(dt)
    if not np.isfinite(step) or step <= 0:
        raise FricjaxError(f"{where(path, 'dt')}: must be a positive finite step in s, got {dt!r}")
    grid = t[0] + np.arange(n) * step
    deviation = float(np.max(np.abs(t - grid)))
    if deviation >= MAX_GRID_DEVIATION * step:
        raise FricjaxError(
            f"{where(path, labels['t'])}: time base too far from uniform to resample: "
            f"max |t - grid| = {deviation:.3g} s = {deviation / step:.3g} of the step "
            f"dt = {step:.9g} s (limit {MAX_GRID_DEVIATION:g}); resample the signals "
            "onto a uniform clock before import, or give the right dt"
        )
    moved = {k: _interp(grid, t, getattr(rec, k)) for k in ("x", "u", "F", "r") if k in signals}
    notes = (
        f"imported from {path.name} ({mapped}); time base rebuilt as t_k = t_0 + k*dt "
        f"with t_0 = {float(t[0])!r} s, dt = {step!r} s (max |t - grid| = {deviation:.3g} s, "
        f"step jitter was {jitter:.3g}); {', '.join(moved)} linearly interpolated onto it"
    )
    out = replace(rec, t=grid, notes=notes, **moved)
    return validate_arrays(out, min_samples=16, labels=labels, check_uniform=True)


def _vector(path: Path, label: str, value: object) -> np.ndarray:
    """A MAT variable as a float64 vector: (n,), (n, 1) and (1, n) are accepted."""
    arr = np.asarray(value)
    if arr.dtype.kind not in "fiu":
        raise FricjaxError(f"{where(path, label)}: wrong dtype {arr.dtype} (expected real numbers)")
    if arr.ndim == 2 and 1 in arr.shape:
        arr = arr.reshape(-1)
    if arr.ndim != 1:
        raise FricjaxError(f"{where(path, label)}: has shape {arr.shape}, expected a vector [n]")
    return arr.astype(np.float64)


def _grid_step(t: Float[np.ndarray, " n"]) -> float:
    """Clock step dt, s, of a jittered time base t [n].

    The least-squares slope of t against k averages the jitter out (its error is about
    jitter / n^1.5); rounding it to 6 significant digits recovers a round design step such
    as 1 ms exactly. More digits are kept while rounding would move the end of the grid,
    (n − 1)·|dt_rounded − slope|, by more than a tenth of the jitter max_k |t_k − (t_0 +
    k·slope)|, so a step like 1/3 ms is not cut into a drifting clock.
    """
    n = t.shape[0]
    k = np.arange(n, dtype=np.float64)
    kc = k - k.mean()
    slope = float(np.dot(kc, t - t.mean()) / np.dot(kc, kc))
    jitter = float(np.max(np.abs(t - (t[0] + k * slope))))
    allowed = 0.1 * jitter + 1e-15 * float(np.max(np.abs(t)))
    for digits in range(6, 18):
        candidate = float(f"{slope:.{digits}g}")
        if abs(candidate - slope) * (n - 1) <= allowed:
            return candidate
    return slope


def _interp(
    grid: Float[np.ndarray, " n"], t: Float[np.ndarray, " n"], y: Float[np.ndarray, " n"]
) -> Float[np.ndarray, " n"]:
    """Linear interpolation of y(t) at ``grid``, extrapolating the end segments linearly.

    np.interp would hold the end values instead; a grid point that falls a jitter's width
    outside [t_0, t_{n−1}] should follow the signal's slope.
    """
    i = np.clip(np.searchsorted(t, grid, side="right"), 1, t.shape[0] - 1)
    t0, t1 = t[i - 1], t[i]
    w = (grid - t0) / (t1 - t0)
    return y[i - 1] + w * (y[i] - y[i - 1])
