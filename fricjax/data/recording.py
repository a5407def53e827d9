"""Recordings of a sliding body: the in-memory type, validation, and HDF5 / CSV I/O.

A recording is the sampled motion of one body, ``x(t_k)`` for ``t_k = t_0 + k·dt``
(k = 0 … n−1), with optionally the measured drive input ``u(t_k)`` and the measured
force on the body ``F(t_k)``. Identification fits ``m·ẍ = F_model(t, x, ẋ, u)`` (seed
paper, eq. 1) to it, so it needs the moving mass ``m`` too.

HDF5 layout v1 (``docs/formats.md``):

=================  ================  ==========================================
path               type              meaning
=================  ================  ==========================================
``/t``             float64 [n]       time, s, strictly increasing, uniform step
``/x``             float64 [n]       displacement, m
``/u``             float64 [n] opt.  measured drive input, unit in attr ``u_unit``
``/F``             float64 [n] opt.  measured force on the body, N
``/r``             float64 [n] opt.  reference position of a closed-loop rig, m
attr ``mass``      float             moving mass, kg
attr ``axis``      str, optional     ``"linear"`` (default) or ``"rotary"``: x, r in rad,
                                     F in N·m, mass a moment of inertia in kg·m²
                                     (:mod:`fricjax.units`)
attrs ``name``,    str, optional     provenance
``source``,
``u_unit``,
``notes``
``/truth``         group, optional   generating parameters of synthetic data
=================  ================  ==========================================

``/r`` extends layout v1 (nothing renamed): the set point a position controller tracked
(EMPS ``qg``), needed to re-simulate a closed-loop run; files without it read as before.

The same recording as CSV: a header ``t,x[,u][,F][,r]`` and one sample a row; the mass then
comes from the caller.

``/truth`` is written here (:func:`write_recording`) but never read here: identification
and diagnosis must not see the answer, so only benchmark code opens that group.
"""

from __future__ import annotations

import hashlib
import io
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, TextIO

import h5py
import numpy as np
from jaxtyping import Float

from fricjax.errors import FricjaxError, where
from fricjax.io.atomic import write_hdf5_atomic, write_text_atomic
from fricjax.params import MASS_DOMAIN

__all__ = [
    "MAX_STEP_JITTER",
    "Recording",
    "read_recording",
    "require_mass",
    "validate",
    "write_recording",
]

#: Largest relative deviation of a time step from the mean step, max_k |Δt_k − dt| / dt,
#: that still counts as a uniform time base (conventions: "relative jitter < 1e-6").
MAX_STEP_JITTER = 1e-6

#: Smallest mean time step [s] taken as a time base (1 ns: 1 GHz sampling); below it the
#: time is in the wrong unit, and filter lengths in samples (∝ 1/dt) no longer fit memory.
MIN_STEP = 1e-9

#: Largest size of a force-like quantity (a, F, u) times √n: its squares must sum to a
#: finite float64 (max ≈ 1.8e308), with room for the mass and the model's terms.
MAX_MAGNITUDE = 1e150

_SIGNALS = ("t", "x", "u", "F", "r")
_HDF5_SUFFIXES = (".h5", ".hdf5")
_CSV_SUFFIX = ".csv"
_TEXT_ATTRS = ("name", "source", "u_unit", "notes", "axis")
_MASS_ATTR = "attr 'mass'"
#: How messages name a mass given by the caller (``--mass`` on the command line).
MASS_FLAG = "--mass"

# SI unit each dataset must carry if it says anything about its unit, and factors that
# turn common wrong units into it (for the hint in the error message).
_EXPECTED_UNIT = {"t": "s", "x": "m", "F": "N", "r": "m"}
_UNIT_NAMES = {"s": "seconds", "m": "metres", "N": "newtons"}
_TO_SI = {
    "t": {"ms": 1e-3, "us": 1e-6, "µs": 1e-6, "ns": 1e-9, "min": 60.0, "h": 3600.0},
    "x": {"mm": 1e-3, "cm": 1e-2, "um": 1e-6, "µm": 1e-6, "nm": 1e-9, "in": 0.0254},
    "F": {"kN": 1e3, "mN": 1e-3, "lbf": 4.4482216152605},
}
_TO_SI["r"] = _TO_SI["x"]
# On a rotary axis (attr axis = "rotary") positions are angles and forces torques.
_ROTARY_UNIT = {"x": "rad", "r": "rad", "F": "N·m"}
_UNIT_NAMES.update({"rad": "radians", "N·m": "newton metres"})


@dataclass(frozen=True, eq=False)
class Recording:
    """One sampled motion record (HDF5 layout v1), immutable.

    Arrays are stored as read-only copies; real-valued inputs are converted to float64 so
    that checksums and files do not depend on the caller's dtype. Anything else (strings,
    complex, bool) is kept as given so that :func:`validate` can refuse it by name.
    Equality is identity (arrays have no single truth value); compare :meth:`sha256`.

    Attributes:
        t: time, s, shape [n], strictly increasing with a uniform step.
        x: displacement of the moving body, m, shape [n].
        u: measured drive input, unit ``u_unit``, shape [n], or None.
        F: measured force on the body, N, shape [n], or None.
        mass: moving mass m, kg, or None when the caller supplies it (CSV) or the model
            config makes it a free parameter.
        name, source, u_unit, notes: provenance text.
        path: the file it was read from ("" if built in memory); error messages name it.
        r: reference (set-point) position of a closed-loop rig, m, shape [n], or None.
        axis: ``"linear"``, ``"rotary"`` (x in rad, F in N·m, mass in kg·m²), or ``""``
            when the file does not say (the config's ``[model].axis`` decides).
    """

    t: Float[np.ndarray, " n"]
    x: Float[np.ndarray, " n"]
    u: Float[np.ndarray, " n"] | None = None
    F: Float[np.ndarray, " n"] | None = None
    mass: float | None = None
    name: str = ""
    source: str = ""
    u_unit: str = ""
    notes: str = ""
    path: str = ""
    r: Float[np.ndarray, " n"] | None = None
    axis: str = ""

    def __post_init__(self) -> None:
        for key in _SIGNALS:
            value = getattr(self, key)
            if value is not None:
                object.__setattr__(self, key, _frozen_array(value))
        if isinstance(self.mass, np.generic):
            object.__setattr__(self, "mass", self.mass.item())
        if isinstance(self.path, os.PathLike):
            object.__setattr__(self, "path", os.fspath(self.path))

    @property
    def n(self) -> int:
        """Number of samples n."""
        return int(np.shape(self.t)[0]) if np.ndim(self.t) else 0

    @property
    def dt(self) -> float:
        """Mean time step dt = (t_{n−1} − t_0) / (n − 1), s (nan when n < 2)."""
        if self.n < 2:
            return math.nan
        return float((self.t[-1] - self.t[0]) / (self.n - 1))

    @property
    def duration(self) -> float:
        """Time span t_{n−1} − t_0, s (0 when n < 2)."""
        if self.n < 2:
            return 0.0
        return float(self.t[-1] - self.t[0])

    def sha256(self) -> str:
        """Hex SHA-256 of the numeric content (t, x, u, F, mass, and r when present).

        Hashes the little-endian float64 bytes of each signal (an absent signal and an
        empty one hash differently) and the exact value of the mass, so the checksum is
        the same for a recording and its HDF5 or CSV copy (both store float64 exactly),
        and changes if any sample changes by one ulp. Provenance text is not hashed.
        """
        h = hashlib.sha256(b"fricjax-recording-v1\0")
        for key in _SIGNALS:
            value = getattr(self, key)
            if value is None and key == "r":
                continue  # the /r extension leaves checksums of files without it unchanged
            if value is None:
                h.update(f"{key}:absent;".encode())
            else:
                data = np.ascontiguousarray(np.asarray(value, dtype="<f8"))
                h.update(f"{key}:{data.shape};".encode())
                h.update(data.tobytes())
        mass = "absent" if self.mass is None else float(self.mass).hex()
        h.update(f"mass:{mass};".encode())
        return h.hexdigest()

    def slice(self, start: int, stop: int) -> Recording:
        """Samples ``start:stop`` (Python slice rules) as a new recording.

        Used to hold out part of a run for validation; ``t`` keeps its absolute values.
        Raises FricjaxError when the slice selects no sample.
        """
        idx = range(self.n)[start:stop]
        if len(idx) == 0:
            raise FricjaxError(
                f"{where(self.path, 'slice')}: [{start}:{stop}] selects no sample "
                f"of a recording with {self.n} samples"
            )
        sl = slice(idx.start, idx.stop)
        note = f"samples {idx.start}:{idx.stop} of {self.n}"
        return replace(
            self,
            t=self.t[sl],
            x=self.x[sl],
            u=None if self.u is None else self.u[sl],
            F=None if self.F is None else self.F[sl],
            r=None if self.r is None else self.r[sl],
            notes=f"{self.notes}; {note}" if self.notes else note,
        )


def _frozen_array(value: Any) -> np.ndarray:
    arr = np.asarray(value)
    # astype and copy both copy, so freezing never touches the caller's array.
    arr = arr.astype(np.float64) if arr.dtype.kind in "fiu" else arr.copy()
    arr.flags.writeable = False
    return arr


def _is_csv(path: str) -> bool:
    return path.lower().endswith(_CSV_SUFFIX)


def _label(rec: Recording, key: str) -> str:
    """How a field is named in messages: HDF5 path, CSV column, or the mass attribute."""
    if key == "mass":
        return "mass" if _is_csv(rec.path) else _MASS_ATTR
    return f"column '{key}'" if _is_csv(rec.path) else f"/{key}"


def validate(rec: Recording, *, min_samples: int = 16) -> Recording:
    """Check ``rec`` against HDF5 layout v1 and return it unchanged.

    Checks, in order: every signal is real-valued and 1-D; x, u, F have the length of t;
    n ≥ ``min_samples``; no NaN or inf (first index reported); t strictly increasing;
    t in seconds, not sample indices (integers in steps of 1) nor a step below
    :data:`MIN_STEP`; no signal so large that its squares overflow (:data:`MAX_MAGNITUDE`);
    uniform step, max_k |Δt_k − dt| / dt < 1e-6 with dt the mean step; mass, if given,
    a positive finite number of kg.

    Raises:
        FricjaxError: one line naming the file (``rec.path``), the field and the defect.
    """
    return validate_arrays(rec, min_samples=min_samples, labels=None, check_uniform=True)


def validate_arrays(
    rec: Recording,
    *,
    min_samples: int,
    labels: Mapping[str, str] | None,
    check_uniform: bool,
) -> Recording:
    def name(key: str) -> str:
        return where(rec.path, labels[key] if labels and key in labels else _label(rec, key))

    present = [k for k in _SIGNALS if getattr(rec, k) is not None]
    for key in present:
        arr = np.asarray(getattr(rec, key))
        if arr.dtype.kind not in "fiu":
            raise FricjaxError(f"{name(key)}: wrong dtype {arr.dtype} (expected float64 numbers)")
        if arr.ndim != 1:
            raise FricjaxError(f"{name(key)}: has shape {arr.shape}, expected 1-D [n]")
    n = rec.t.shape[0]
    for key in present[1:]:
        m = getattr(rec, key).shape[0]
        if m != n:
            raise FricjaxError(
                f"{name(key)}: length {m} differs from {_label(rec, 't')} length {n}"
            )
    if n < min_samples:
        raise FricjaxError(f"{name('t')}: only {n} samples, at least {min_samples} needed")
    for key in present:
        arr = getattr(rec, key)
        bad = ~np.isfinite(arr)
        if bad.any():
            i = int(np.argmax(bad))
            what = "NaN" if np.isnan(arr[i]) else "inf"
            raise FricjaxError(f"{name(key)}: contains {what} at index {i}")
    t = rec.t
    step = np.diff(t)
    if n > 1 and not (step > 0).all():
        i = int(np.argmax(step <= 0)) + 1
        raise FricjaxError(
            f"{name('t')}: not strictly increasing at index {i} "
            f"(t[{i - 1}] = {float(t[i - 1])!r} s, t[{i}] = {float(t[i])!r} s)"
        )
    if n > 1 and float(t[1] - t[0]) == 1.0 and np.all(t == np.round(t)):
        raise FricjaxError(
            f"{name('t')}: t looks like sample indices, not seconds (integers from "
            f"{float(t[0]):g} in steps of 1): store time in seconds, t_k = t_0 + k*dt"
        )
    if n > 1 and float(t[-1] - t[0]) / (n - 1) < MIN_STEP:
        raise FricjaxError(
            f"{name('t')}: time step {float(t[-1] - t[0]) / (n - 1):.3g} s is below "
            f"{MIN_STEP:g} s (a sample rate above {1 / MIN_STEP:g} Hz): wrong units of t?"
        )
    _check_scale(rec, name)
    if check_uniform and n > 2:
        dt = (t[-1] - t[0]) / (n - 1)
        dev = np.abs(step - dt) / dt
        i = int(np.argmax(dev))
        if dev[i] >= MAX_STEP_JITTER:
            raise FricjaxError(
                f"{name('t')}: step not uniform: worst relative deviation {dev[i]:.3g} "
                f"(step {i} -> {i + 1}, mean step {dt:.9g} s; allowed < {MAX_STEP_JITTER:g}); "
                "resample onto the exact grid t_k = t_0 + k*dt, e.g. with "
                "fricjax.data.importers.import_mat"
            )
    if rec.mass is not None:
        check_mass(rec.mass, name("mass"))
    if rec.axis not in ("", "linear", "rotary"):
        raise FricjaxError(
            f"{where(rec.path, 'attr axis')}: must be 'linear' or 'rotary', got {rec.axis!r}"
        )
    return rec


def _check_scale(rec: Recording, name: Any) -> None:
    """Refuse signals whose size overflows float64 downstream: the cost sums squares of
    forces m·a with a ~ Δ²x/dt² (at most 4·max|x|/dt²), so max|x|·4/dt² (and max|F|, max|u|)
    must stay below :data:`MAX_MAGNITUDE` ≈ √(float64 max / n)."""
    n = rec.n
    if n < 2:
        return
    dt = rec.dt
    for key in _SIGNALS:
        arr = getattr(rec, key)
        if arr is None or key == "t":
            continue
        size = float(np.max(np.abs(arr)))
        moving = key in ("x", "r")
        scale = 4.0 * size / dt**2 if moving else size
        if scale * math.sqrt(n) > MAX_MAGNITUDE:
            what = f" give accelerations up to ~{scale:.3g} m/s^2 (4*max|x|/dt^2)," * moving
            raise FricjaxError(
                f"{name(key)}: values up to {size:.3g}{what} too large to square and sum "
                f"in float64 (limit {MAX_MAGNITUDE:g}/sqrt(n)): wrong units?"
            )


def check_mass(mass: Any, label: str) -> float:
    ok = isinstance(mass, int | float | np.integer | np.floating) and not isinstance(
        mass, bool | np.bool_
    )
    if not ok or not math.isfinite(float(mass)) or float(mass) <= 0:
        raise FricjaxError(f"{label}: must be a positive finite number of kg, got {mass!r}")
    if not MASS_DOMAIN.contains(float(mass)):
        raise FricjaxError(
            f"{label}: {float(mass):g} kg is outside the physical range of a moving mass "
            f"({MASS_DOMAIN}): a typo or a wrong unit?"
        )
    return float(mass)


def require_mass(rec: Recording) -> float:
    """The moving mass m, kg, or a FricjaxError saying how to supply it.

    Raises:
        FricjaxError: mass missing, or not a positive finite number.
    """
    label = where(rec.path, _MASS_ATTR)
    if rec.mass is None:
        raise FricjaxError(
            f"{label}: missing (give --mass or make mass a free parameter in the config)"
        )
    return check_mass(rec.mass, label)


# ----------------------------------------------------------------------------- reading


def read_recording(path: str | Path, *, mass: float | None = None) -> Recording:
    """Read and validate a recording from ``.h5``/``.hdf5`` (layout v1) or ``.csv``.

    Args:
        path: the file; its suffix picks the format.
        mass: moving mass, kg; overrides the HDF5 attribute (which is then not read) and
            is the only source of mass for CSV files. A bad one is blamed on ``--mass``.

    Never opens the ``/truth`` group.

    Raises:
        FricjaxError: unreadable file, unknown suffix, or any layout violation.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (*_HDF5_SUFFIXES, _CSV_SUFFIX):
        raise FricjaxError(
            f"{where(path)}: unknown recording format {path.suffix or '(no suffix)'!r} "
            "(expected .h5, .hdf5 or .csv)"
        )
    if not path.is_file():
        raise FricjaxError(f"{where(path)}: no such file")
    if mass is not None:
        # checked as the flag it came from: the file's own mass attribute is not read
        mass = check_mass(mass, MASS_FLAG)
    rec = _read_csv(path) if suffix == _CSV_SUFFIX else _read_hdf5(path, read_mass=mass is None)
    if mass is not None:
        rec = replace(rec, mass=mass)
    return validate(rec)


def _read_hdf5(path: Path, *, read_mass: bool) -> Recording:
    try:
        f = h5py.File(path, "r")
    except OSError as exc:
        raise FricjaxError(f"{where(path)}: not a readable HDF5 file ({exc})") from None
    with f:
        axis = _text_attr(path, f.attrs, "axis")
        signals: dict[str, np.ndarray | None] = {}
        for key in _SIGNALS:
            # `key in f` checks the link only; /truth is never looked up at all.
            if key not in f:
                if key in ("t", "x"):
                    raise FricjaxError(f"{where(path, '/' + key)}: missing dataset")
                signals[key] = None
                continue
            try:
                ds = f[key]
            except (KeyError, OSError):
                link = f.get(key, getlink=True)
                target = (
                    f"external link to {link.filename}:{link.path}"
                    if isinstance(link, h5py.ExternalLink)
                    else f"soft link to {link.path}"
                    if isinstance(link, h5py.SoftLink)
                    else "object"
                )
                raise FricjaxError(
                    f"{where(path, '/' + key)}: cannot be opened ({target} that does not resolve)"
                ) from None
            if not isinstance(ds, h5py.Dataset):
                raise FricjaxError(f"{where(path, '/' + key)}: is a group, expected a dataset")
            if ds.dtype.kind not in "fiu":
                raise FricjaxError(
                    f"{where(path, '/' + key)}: wrong dtype {ds.dtype} (expected float64 numbers)"
                )
            if key == "t" and ds.dtype.kind in "iu":
                raise FricjaxError(
                    f"{where(path, '/t')}: integer dtype {ds.dtype}: t looks like sample "
                    "indices, not seconds (store float64 seconds, t_k = t_0 + k*dt)"
                )
            _check_unit(path, key, ds, axis)
            try:
                signals[key] = ds[()]
            except (OSError, ValueError, TypeError) as exc:
                raise FricjaxError(f"{where(path, '/' + key)}: unreadable data ({exc})") from None
        attrs = f.attrs
        text = {k: _text_attr(path, attrs, k) for k in _TEXT_ATTRS}
        mass = _mass_attr(path, attrs) if read_mass else None
    return Recording(**signals, mass=mass, **text, path=str(path))


def _check_unit(path: Path, key: str, ds: h5py.Dataset, axis: str = "") -> None:
    expected = (_ROTARY_UNIT if axis == "rotary" else _EXPECTED_UNIT).get(key)
    if expected is None or "unit" not in ds.attrs:
        return
    unit = ds.attrs["unit"]
    unit = unit.decode() if isinstance(unit, bytes) else str(unit)
    if unit.strip() == expected:
        return
    if axis != "rotary" and unit.strip() in ("rad", "N·m", "N*m", "Nm", "N.m"):
        raise FricjaxError(
            f"{where(path, '/' + key)}: unit {unit!r} is rotary; set root attr "
            "axis = 'rotary' (x, r in rad, F in N·m, mass in kg·m²)"
        )
    factor = _TO_SI[key].get(unit.strip()) if axis != "rotary" else None
    hint = (
        f"multiply by {factor:g} to convert {unit} to {expected}"
        if factor is not None
        else f"convert to {_UNIT_NAMES[expected]}"
    )
    raise FricjaxError(
        f"{where(path, '/' + key)}: wrong units {unit!r} (expected {expected!r}, "
        f"{_UNIT_NAMES[expected]}; {hint} and set attr unit = {expected!r})"
    )


def _text_attr(path: Path, attrs: h5py.AttributeManager, key: str) -> str:
    if key not in attrs:
        return path.stem if key == "name" else ""
    value = attrs[key]
    if isinstance(value, bytes):
        return value.decode("utf-8", errors="replace")
    if isinstance(value, str):
        return value
    shown = value.item() if isinstance(value, np.generic) else value
    raise FricjaxError(f"{where(path, f'attr {key!r}')}: must be a string, got {shown!r}")


def _mass_attr(path: Path, attrs: h5py.AttributeManager) -> float | None:
    if "mass" not in attrs:
        return None
    raw = attrs["mass"]
    arr = np.asarray(raw)
    if arr.size != 1 or arr.dtype.kind not in "fiu":
        raise FricjaxError(
            f"{where(path, _MASS_ATTR)}: must be a positive finite number of kg, got {raw!r}"
        )
    return arr.reshape(()).item()


def _read_csv(path: Path) -> Recording:
    try:
        # utf-8-sig: Excel's "CSV UTF-8" starts with a byte-order mark
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise FricjaxError(f"{where(path)}: cannot read as UTF-8 text ({exc})") from None
    lines = text.splitlines()
    header_at = next((i for i, line in enumerate(lines) if line.strip()), None)
    if header_at is None:
        raise FricjaxError(
            f"{where(path, 'header')}: empty file, expected a header t,x[,u][,F][,r]"
        )
    if ";" in lines[header_at]:
        # Excel in a decimal-comma locale: ';' between fields, ',' in numbers. Refused, not
        # guessed: "1,234" could be 1.234 or 1234, and a wrong guess scales x silently.
        raise FricjaxError(
            f"{where(path, 'header')}: fields separated by ';' (a decimal-comma export); "
            "fricjax reads ',' between fields and '.' as decimal point: export with the "
            "decimal point '.' (or convert: sed -e 's/,/./g' -e 's/;/,/g')"
        )
    columns = [c.strip() for c in lines[header_at].split(",")]
    for c in columns:
        if c not in _SIGNALS:
            raise FricjaxError(
                f"{where(path, f'column {c!r}')}: unknown column name "
                "(allowed: t, x, u, F, r; header must be t,x[,u][,F][,r])"
            )
        if columns.count(c) > 1:
            raise FricjaxError(f"{where(path, f'column {c!r}')}: appears more than once")
    for c in ("t", "x"):
        if c not in columns:
            raise FricjaxError(
                f"{where(path, f'column {c!r}')}: missing from header {lines[header_at]!r}"
            )
    data = _parse_csv_rows(path, lines, header_at, len(columns))
    signals = {c: data[:, j] for j, c in enumerate(columns)}
    return Recording(**signals, name=path.stem, path=str(path))


def _parse_csv_rows(path: Path, lines: list[str], header_at: int, ncol: int) -> np.ndarray:
    body = lines[header_at + 1 :]
    if not any(line.strip() for line in body):
        return np.zeros((0, ncol))
    try:
        # np.loadtxt parses '%.17g' text back to the identical float64.
        data = np.loadtxt(body, delimiter=",", dtype=np.float64, ndmin=2, comments=None)
        if data.shape[0] == 0 or data.shape[1] == ncol:
            return data.reshape(-1, ncol)
    except ValueError:
        pass
    # Slow path only to say exactly which row is bad.
    names = [c.strip() for c in lines[header_at].split(",")]
    rows: list[list[float]] = []
    for offset, line in enumerate(body):
        lineno = header_at + 2 + offset
        if not line.strip():
            continue
        cells = line.split(",")
        row = len(rows) + 1
        if len(cells) != ncol:
            raise FricjaxError(
                f"{where(path, f'line {lineno}')}: data row {row} has {len(cells)} values, "
                f"header has {ncol}"
            )
        values = []
        for cell, col in zip(cells, names, strict=True):
            try:
                values.append(float(cell))
            except ValueError:
                raise FricjaxError(
                    f"{where(path, f'column {col!r}')}: data row {row} (line {lineno}): "
                    f"cannot parse {cell.strip()!r} as a number"
                ) from None
        rows.append(values)
    return np.asarray(rows, dtype=np.float64).reshape(-1, ncol)


# ----------------------------------------------------------------------------- writing


def write_recording(
    rec: Recording, path: str | Path, *, truth: Mapping[str, Any] | None = None
) -> Path:
    """Validate ``rec`` and write it atomically to ``.h5``/``.hdf5`` or ``.csv``.

    The file is written to a temporary name in the target directory and moved over
    ``path`` with ``os.replace``, so a reader sees the old file or the complete new one.

    Args:
        rec: the recording; checked with :func:`validate` (messages name ``path``).
        path: target file; the suffix picks the format. CSV stores t, x, u, F, r only
            (17 significant digits, exact); mass and provenance are HDF5-only.
        truth: HDF5 only: generating parameters and effects, stored as attrs of group
            ``/truth``. Values: float, int, bool, str, or 1-D float arrays; a nested
            mapping becomes a subgroup.

    Returns:
        The path written.

    Raises:
        FricjaxError: invalid recording, unknown suffix, truth given for CSV, or an
            unsupported truth value.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in (*_HDF5_SUFFIXES, _CSV_SUFFIX):
        raise FricjaxError(
            f"{where(path)}: unknown recording format {path.suffix or '(no suffix)'!r} "
            "(expected .h5, .hdf5 or .csv)"
        )
    validate(replace(rec, path=str(path)))
    if truth is not None:
        if suffix == _CSV_SUFFIX:
            raise FricjaxError(f"{where(path, '/truth')}: CSV cannot store truth; use .h5")
        _check_truth(path, truth, "/truth")
    if suffix == _CSV_SUFFIX:
        text = io.StringIO(newline="\n")
        _write_csv_body(text, rec)
        return write_text_atomic(path, text.getvalue())
    return write_hdf5_atomic(path, lambda f: _write_hdf5_body(f, rec, truth))


def _write_csv_body(fh: TextIO, rec: Recording) -> None:
    keys = [k for k in _SIGNALS if getattr(rec, k) is not None]
    fh.write(",".join(keys) + "\n")
    table = np.column_stack([np.asarray(getattr(rec, k), dtype=np.float64) for k in keys])
    # 17 significant digits: enough to round-trip every float64 exactly.
    np.savetxt(fh, table, fmt="%.17g", delimiter=",")


def _write_hdf5_body(f: h5py.File, rec: Recording, truth: Mapping[str, Any] | None) -> None:
    units = {"t": "s", **(_ROTARY_UNIT if rec.axis == "rotary" else _EXPECTED_UNIT)}
    for key in _SIGNALS:
        value = getattr(rec, key)
        if value is None:
            continue
        ds = f.create_dataset(key, data=np.asarray(value, dtype=np.float64))
        if key in units:
            ds.attrs["unit"] = units[key]
    if rec.mass is not None:
        f.attrs["mass"] = float(rec.mass)
    for key in _TEXT_ATTRS:
        if key != "axis" or rec.axis:
            f.attrs[key] = str(getattr(rec, key))
    if truth is not None:
        _write_truth(f.create_group("truth"), truth)


def _check_truth(path: Path, truth: Mapping[str, Any], at: str) -> None:
    for key, value in truth.items():
        label = where(path, f"{at}/{key}" if isinstance(key, str) else at)
        if not isinstance(key, str) or not key or "/" in key:
            raise FricjaxError(f"{label}: truth key {key!r} must be a non-empty str without '/'")
        if isinstance(value, Mapping):
            _check_truth(path, value, f"{at}/{key}")
        elif isinstance(value, str | bool | int | float | np.integer | np.floating | np.bool_):
            continue
        else:
            arr = np.asarray(value)
            if arr.ndim != 1 or arr.dtype.kind not in "fiu":
                raise FricjaxError(
                    f"{label}: unsupported truth value of type {type(value).__name__} "
                    "(use float, int, str, a 1-D float array or a nested mapping)"
                )


def _write_truth(group: h5py.Group, truth: Mapping[str, Any]) -> None:
    for key, value in truth.items():
        if isinstance(value, Mapping):
            _write_truth(group.create_group(key), value)
        elif isinstance(value, str | bool | np.bool_):
            group.attrs[key] = value
        elif isinstance(value, int | np.integer):
            group.attrs[key] = np.int64(value)
        elif isinstance(value, float | np.floating):
            group.attrs[key] = np.float64(value)
        else:
            group.attrs[key] = np.asarray(value, dtype=np.float64)
