"""Velocity, acceleration and measured force from a displacement record (seed paper §4.1).

The seed paper obtains velocity "by differencing the displacement signal" and removes the
high-frequency error of the difference with a Butterworth low-pass; acceleration follows
the same way, and the measured force of the cost (seed eq. 11) is ``F = m·a``. This module
does that once per recording, in numpy/scipy float64 (it is not part of the jitted hot
loop), with a Savitzky–Golay alternative:

* ``"butterworth"``: ``v = L(D x)``, ``a = L(D v)``, with ``D`` the central difference
  (:func:`numpy.gradient`, second-order one-sided at the ends) and ``L`` a Butterworth
  low-pass of order ``order`` applied forward and backward (:func:`scipy.signal.sosfiltfilt`):
  zero phase, magnitude ``|H(f)|² = 1 / (1 + (w(f)/w(f_c))^(2·order))`` with
  ``w(f) = tan(π·f/fs)`` (digital Butterworth, bilinear transform).
* ``"savgol"``: ``v``, ``a`` = first and second derivative of the least-squares polynomial
  of degree ``savgol_polyorder`` over ``savgol_window`` samples
  (:func:`scipy.signal.savgol_filter`, ``deriv=1, 2``, ``delta = dt``), applied to ``x``.

Both are linear, zero-phase operators on ``x``; :func:`noise_gains` gives their white-noise
gains ``σ_v/σ_x`` [1/s] and ``σ_a/σ_x`` [1/s²] away from the ends.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from typing import Any, Literal, NamedTuple

import numpy as np
from jaxtyping import Float

from fricjax.data.filters import filtfilt_lowpass
from fricjax.errors import FricjaxError, where

Method = Literal["butterworth", "savgol"]

_METHODS: tuple[str, ...] = ("butterworth", "savgol")
_TABLE = "preprocess"
# Same tolerance as the recording layout (conventions.md: relative jitter < 1e-6).
_MAX_STEP_JITTER = 1e-6
# np.gradient(edge_order=2) needs 3 samples.
_MIN_SAMPLES = 3
# Odd padding over this many cutoff periods: the zero-phase filter's transient has died
# out by then, so the ends see a continued signal rather than the start-up of the filter.
_PAD_CUTOFF_PERIODS = 3.0


@dataclass(frozen=True)
class PreprocessSettings:
    """How :func:`derivatives` turns displacement into velocity and acceleration.

    Fields (the ``[preprocess]`` table of a TOML config):

    * ``method``: ``"butterworth"`` (seed §4.1) or ``"savgol"``.
    * ``order``: Butterworth order; applied forward-backward, so the magnitude is
      ``|H(f)|²`` (module docstring; effective order ``2·order``) and the phase is zero.
    * ``cutoff_hz``: Butterworth cutoff f_c [Hz], below the Nyquist frequency.
    * ``savgol_window``: Savitzky–Golay window [samples], odd, > ``savgol_polyorder``.
    * ``savgol_polyorder``: Savitzky–Golay polynomial degree, ≥ 2 (``a`` is its 2nd derivative).
    * ``trim``: samples dropped at each end after filtering (edge effects, see below).
    * ``stencil``: central-difference order of the Butterworth path, 2 (np.gradient, the
      seed's plain differencing) or 4 (see :func:`difference`).
    * ``decimate``: the IDIM-LS recipe's last step: the equation-error *residual* (i.e.
      every regressor column and the force) is anti-alias filtered and kept every
      ``decimate`` samples (:mod:`fricjax.data.decimate`); 1 = off. Applied by the
      problem's residual, not to the signals here.
    * ``filter_input``: filter the measured drive input ``u`` and force ``F`` like ``m·a``
      (True, the default), so the equation error compares like with like: Butterworth,
      ``L(L(F))`` (``a = L D L D x`` passes the same zero-phase low-pass twice);
      Savitzky–Golay, the smoothing polynomial of the same window and degree (``deriv=0``).
      False keeps them raw (the published EMPS IDIM-LS recipe filters the torque only
      through the decimation, ``configs/emps.toml``).
    * ``source``: where the settings came from (config file name), for error messages only.

    Why the defaults (measured for 1 kHz sampling; the paper twin has 10 harmonics of 5 Hz,
    so its highest drive frequency is 50 Hz, and white noise of σ_x = 1e-5..1e-4 m on x):

    Butterworth, ``order=4, cutoff_hz=100``. Gain of the zero-phase filter at 50 Hz: 0.9968
    on v and 0.9937 on a (a passes the filter twice), i.e. a 0.6 % bias on the highest
    harmonic of a, below the 3.3 % that the two central differences themselves cost at 50 Hz
    (``sin(ωdt)/(ωdt)`` = 0.9836 each; total gain on a at 50 Hz: 0.961). White-noise gain:
    ``σ_a/σ_x`` = 4.9e4 s⁻² (``σ_v/σ_x`` = 139 s⁻¹), 12.5× less than plain double central
    differencing (6.1e5 s⁻²; the three-point second difference gives 2.4e6 s⁻²).
    Neighbours: 80 Hz → filter gain on a at 50 Hz 0.959 (4.1 % bias, more than the
    differencing bias) for ``σ_a/σ_x`` = 2.9e4 s⁻²; 120 Hz → 0.9987 for 7.5e4 s⁻² (1.5× the
    noise for 0.5 % less bias). On 10 harmonics of equal acceleration amplitude 5 m/s², the
    interior RMS error of a was 0.19 m/s² (noise-free), 0.55 m/s² (σ_x = 1e-5 m) and
    4.7 m/s² (σ_x = 1e-4 m) at 100 Hz; the noise-optimal cutoff was 80–90 Hz at
    σ_x = 1e-5 m and ≤ 70 Hz at σ_x ≥ 3e-5 m, at the price of a 4–12 % bias on the 50 Hz
    harmonic, which shifts identified parameters rather than averaging out: lower
    ``cutoff_hz`` in the config for noisy recordings. A Coulomb step in a (velocity kink at a
    reversal) is spread over 6 ms (10–90 %) with ±6.6 % ringing at 100 Hz.

    Savitzky–Golay, ``savgol_polyorder=7, savgol_window=27`` (27 ms). Gains at 50 Hz: 0.9955
    on v and 0.965 on a (3.5 % bias, matching the Butterworth default's total 3.9 %);
    ``σ_a/σ_x`` = 5.7e4 s⁻² (10.7× below plain differencing), ``σ_v/σ_x`` = 166 s⁻¹. Degree 3
    (the textbook choice) cannot reach this: keeping the 50 Hz bias on a ≤ 4 % forces a
    5-sample window (``σ_a/σ_x`` = 5.4e5 s⁻², no smoothing), and an 11-sample window already
    loses 19 % of the 50 Hz harmonic. Savitzky–Golay stop-band side lobes pass vibrations
    above 150 Hz into a with up to 6e4 m/s² per metre of displacement, against 5e2 for the
    Butterworth default; that is why Butterworth (the seed paper's choice) is the default.

    Ends: Butterworth uses odd (point-reflection) padding over ``max(3·(2·n_sections+1),
    3·fs/f_c)`` samples (30 at the defaults). It keeps value and slope continuous at the
    ends; on the 272-sample test signal of tests/data/test_preprocess.py the RMS error of a
    over the first and last 10 samples was 7.4 % of the RMS of a with odd padding, 17 % with
    constant and 30 % with even padding (13 %, 47 %, 70 % on the 10 equal harmonics above).
    The padding length hardly matters at 100 Hz; at 30–60 Hz cutoffs 3 cutoff periods cut
    the end error of a 1.6–4× compared with scipy's default of 15 samples. Even so, white
    noise on the first and last ~5 samples of a is amplified up to ~24× more than in the
    interior (Savitzky–Golay: ~26× on the first sample), so set ``trim`` (e.g. 10) for noisy
    recordings. ``trim=0`` by default to keep all 272 samples of the paper twin.
    """

    method: Method = "butterworth"
    order: int = 4
    cutoff_hz: float = 100.0
    savgol_window: int = 27
    savgol_polyorder: int = 7
    trim: int = 0
    stencil: int = 2
    decimate: int = 1
    filter_input: bool = True
    source: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        if self.method not in _METHODS:
            raise FricjaxError(
                f"{self._key('method')}: must be one of {', '.join(map(repr, _METHODS))}, "
                f"got {self.method!r}"
            )
        for name, low in (("order", 1), ("savgol_polyorder", 2), ("trim", 0), ("decimate", 1)):
            value = getattr(self, name)
            if not _is_int(value) or value < low:
                raise FricjaxError(f"{self._key(name)}: must be an integer >= {low}, got {value!r}")
            object.__setattr__(self, name, int(value))
        if not isinstance(self.filter_input, bool | np.bool_):
            raise FricjaxError(
                f"{self._key('filter_input')}: must be true or false, got {self.filter_input!r}"
            )
        object.__setattr__(self, "filter_input", bool(self.filter_input))
        if not _is_int(self.stencil) or self.stencil not in (2, 4):
            raise FricjaxError(f"{self._key('stencil')}: must be 2 or 4, got {self.stencil!r}")
        window = self.savgol_window
        if not _is_int(window) or window % 2 != 1:
            raise FricjaxError(
                f"{self._key('savgol_window')}: must be an odd integer number of samples, "
                f"got {window!r}"
            )
        if window <= self.savgol_polyorder:
            raise FricjaxError(
                f"{self._key('savgol_window')}: must exceed savgol_polyorder "
                f"({self.savgol_polyorder}), got {window}"
            )
        object.__setattr__(self, "savgol_window", int(window))
        cutoff = self.cutoff_hz
        if not _is_real(cutoff) or not math.isfinite(cutoff) or cutoff <= 0:
            raise FricjaxError(
                f"{self._key('cutoff_hz')}: must be a positive finite frequency in Hz, "
                f"got {cutoff!r}"
            )
        object.__setattr__(self, "cutoff_hz", float(cutoff))

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], *, source: str = "config") -> PreprocessSettings:
        """Settings from the ``[preprocess]`` table of a TOML config.

        Missing keys take the defaults. An unknown key or a bad value raises
        :class:`FricjaxError` naming ``source`` and ``[preprocess].key``.
        """
        if not isinstance(d, Mapping):
            raise FricjaxError(f"{where(source, f'[{_TABLE}]')}: must be a table")
        known = {f.name for f in fields(cls)} - {"source"}
        for key in d:
            if key not in known:
                raise FricjaxError(
                    f"{where(source, f'[{_TABLE}].{key}')}: unknown key "
                    f"(known: {', '.join(sorted(known))})"
                )
        return cls(**dict(d), source=source)

    def check(self, sample_rate_hz: float, n: int, *, recording: str | None = None) -> None:
        """Raise :class:`FricjaxError` if these settings cannot process ``n`` samples at
        ``sample_rate_hz`` [Hz] (cutoff above Nyquist, window longer than the record, ...).

        With ``recording`` (the file the samples came from) a record too short for the
        settings is blamed on the recording, naming the fewest samples they need, and a
        cutoff below one period over the record (``cutoff_hz < fs/(n − 1)``, a filter whose
        response outlasts the data) is refused.
        """
        if recording is not None:
            self._check_record(sample_rate_hz, n, recording)
        if self.method == "butterworth":
            nyquist = sample_rate_hz / 2.0
            if self.cutoff_hz >= nyquist:
                raise FricjaxError(
                    f"{self._key('cutoff_hz')}: must be below the Nyquist frequency "
                    f"{nyquist:g} Hz, got {self.cutoff_hz:g}"
                )
        elif self.savgol_window > n:
            raise FricjaxError(
                f"{self._key('savgol_window')}: {self.savgol_window} samples is longer than "
                f"the record ({n} samples)"
            )
        if n - 2 * self.trim < _MIN_SAMPLES:
            raise FricjaxError(
                f"{self._key('trim')}: trimming {self.trim} samples at each end leaves "
                f"{n - 2 * self.trim} of the {n} samples, need at least {_MIN_SAMPLES}"
            )

    def min_samples(self) -> int:
        """Fewest samples these settings can process: ``2·trim + 3`` (np.gradient needs 3
        after trimming), and the Savitzky–Golay window."""
        need = 2 * self.trim + _MIN_SAMPLES
        return max(need, self.savgol_window) if self.method == "savgol" else need

    def _check_record(self, sample_rate_hz: float, n: int, recording: str) -> None:
        need = self.min_samples()
        if n < need:
            why = (
                f"trim = {self.trim} at each end, then {_MIN_SAMPLES} samples to differentiate"
                if need == 2 * self.trim + _MIN_SAMPLES
                else f"savgol_window = {self.savgol_window}"
            )
            raise FricjaxError(
                f"{where(recording, '/t')}: {n} samples is too short for the preprocessing "
                f"({where(self.source or None, f'[{_TABLE}]')}: {why}), which needs at least "
                f"{need} samples"
            )
        duration = (n - 1) / sample_rate_hz
        if self.method == "butterworth" and self.cutoff_hz * duration < 1.0:
            raise FricjaxError(
                f"{self._key('cutoff_hz')}: {self.cutoff_hz:g} Hz is less than one period "
                f"over the {duration:.6g} s of {recording}; the low-pass needs at least "
                f"{1.0 / duration:.3g} Hz"
            )

    def _key(self, name: str) -> str:
        return where(self.source or None, f"[{_TABLE}].{name}")


class Derivatives(NamedTuple):
    """Preprocessed recording, each field shape [m] with ``m = n - 2·trim``.

    ``t`` [s], ``x`` [m] (the measured displacement, not smoothed), ``v`` [m/s],
    ``a`` [m/s²], ``u`` (drive input, unit of the recording, or None) and ``F`` [N] (or None),
    the last two trimmed, and filtered like ``m·a`` unless ``filter_input`` is off.
    """

    t: Float[np.ndarray, " m"]
    x: Float[np.ndarray, " m"]
    v: Float[np.ndarray, " m"]
    a: Float[np.ndarray, " m"]
    u: Float[np.ndarray, " m"] | None
    F: Float[np.ndarray, " m"] | None


def derivatives(
    t: Float[np.ndarray, " n"],
    x: Float[np.ndarray, " n"],
    settings: PreprocessSettings,
    *,
    u: Float[np.ndarray, " n"] | None = None,
    F: Float[np.ndarray, " n"] | None = None,
    source: str | None = None,
) -> Derivatives:
    """Velocity and acceleration of a uniformly sampled displacement record (seed §4.1).

    Args:
        t: sample times [s], shape [n], strictly increasing with uniform step.
        x: displacement [m], shape [n].
        settings: filter choice and parameters (:class:`PreprocessSettings`).
        u: optional drive input, shape [n]; trimmed like the others and filtered like
            ``m·a`` (:func:`filter_like_acceleration`) when ``settings.filter_input``.
        F: optional measured force [N], shape [n]; treated as ``u``.
        source: recording name for error messages (e.g. the file path).

    Returns:
        :class:`Derivatives` with arrays of shape [n - 2·trim], float64.

    Raises:
        FricjaxError: non-finite or mismatched arrays, a non-uniform time step, or settings
            that do not fit the record (cutoff ≥ Nyquist, window > n, trim too large).
    """
    t_arr = _vector(t, "/t", source)
    n = t_arr.shape[0]
    x_arr = _vector(x, "/x", source, n)
    u_arr = None if u is None else _vector(u, "/u", source, n)
    F_arr = None if F is None else _vector(F, "/F", source, n)
    if n < _MIN_SAMPLES:
        raise FricjaxError(
            f"{where(source, '/t')}: {n} samples, need at least {_MIN_SAMPLES} to differentiate"
        )
    dt = _uniform_step(t_arr, source)
    settings.check(1.0 / dt, n, recording=source)
    if settings.method == "butterworth":
        v, a = _butterworth(x_arr, dt, settings)
    else:
        v, a = _savgol(x_arr, dt, settings)
    if settings.filter_input:
        u_arr = None if u_arr is None else filter_like_acceleration(u_arr, dt, settings)
        F_arr = None if F_arr is None else filter_like_acceleration(F_arr, dt, settings)
    keep = slice(settings.trim, n - settings.trim)
    return Derivatives(
        t=t_arr[keep],
        x=x_arr[keep],
        v=v[keep],
        a=a[keep],
        u=None if u_arr is None else u_arr[keep],
        F=None if F_arr is None else F_arr[keep],
    )


def derivative_columns(
    t: Float[np.ndarray, " n"], xs: Float[np.ndarray, "n k"], settings: PreprocessSettings
) -> tuple[Float[np.ndarray, "m k"], Float[np.ndarray, "m k"], Float[np.ndarray, "m k"]]:
    """:func:`derivatives` of every column of ``xs`` at once: the trimmed displacement,
    velocity and acceleration, [m = n − 2·trim, k] each (columns of unit impulses give the
    preprocessing's matrices, :mod:`fricjax.residual_noise`). ``t`` and ``settings`` are a
    record's that :func:`derivatives` accepted."""
    dt = _uniform_step(np.asarray(t, dtype=np.float64), None)
    xs = np.asarray(xs, dtype=np.float64)
    if settings.method == "butterworth":
        v, a = _butterworth(xs, dt, settings)
    else:
        v, a = _savgol(xs, dt, settings)
    keep = slice(settings.trim, xs.shape[0] - settings.trim)
    return xs[keep], v[keep], a[keep]


def filter_like_acceleration(
    y: Float[np.ndarray, " n"], dt: float, settings: PreprocessSettings
) -> Float[np.ndarray, " n"]:
    """A measured force (or drive input) ``y`` [any unit], shape [n], through the smoothing
    that :func:`derivatives` gives ``a``, so that ``m·a`` and ``y`` are compared alike.

    Butterworth: ``L(L(y))`` with ``L`` the zero-phase low-pass of ``a = L D L D x``, same
    order, cutoff and end padding (the differences ``D`` are derivatives, not smoothing; what
    remains of them is their gain ``sin(ωΔt)/(ωΔt)`` per difference, 0.9997 at 5 Hz and
    1 kHz). Savitzky–Golay: the least-squares polynomial of the same window and degree
    (``deriv=0``), the smoother whose second derivative is ``a``.
    """
    if settings.method == "butterworth":
        fs = 1.0 / dt
        padlen = _padlen(y.shape[0], fs, settings)
        once = filtfilt_lowpass(y, settings.order, settings.cutoff_hz, fs, padlen)
        return filtfilt_lowpass(once, settings.order, settings.cutoff_hz, fs, padlen)
    from scipy import signal

    return signal.savgol_filter(y, settings.savgol_window, settings.savgol_polyorder, mode="interp")


def measured_force(
    a: Float[np.ndarray, " m"], mass: float, *, source: str | None = None
) -> Float[np.ndarray, " m"]:
    """Measured force ``F = m·a`` [N] (left side of seed eq. 5), ``a`` [m/s²], ``mass`` [kg]."""
    if not _is_real(mass) or not math.isfinite(mass) or mass <= 0:
        raise FricjaxError(f"{where(source, 'mass')}: must be a positive mass in kg, got {mass!r}")
    return float(mass) * np.asarray(a, dtype=np.float64)


def noise_gains(settings: PreprocessSettings, sample_rate_hz: float) -> tuple[float, float]:
    """White-noise gains ``(σ_v/σ_x [1/s], σ_a/σ_x [1/s²])`` of :func:`derivatives` away from
    the record ends: the 2-norms of the impulse responses of the two linear operators."""
    dt = 1.0 / sample_rate_hz
    if settings.method == "butterworth":
        # The slowest Butterworth pole decays at 2π·f_c·sin(π/(2·order)) ≥ 2π·f_c/order per
        # second, so 20·order cutoff periods each side hold all but e^(-40π) of the response.
        half = math.ceil(20.0 * settings.order * sample_rate_hz / settings.cutoff_hz)
    else:
        half = settings.savgol_window
    replace(settings, trim=0).check(sample_rate_hz, 2 * half + 1)
    impulse = np.zeros(2 * half + 1)
    impulse[half] = 1.0
    if settings.method == "butterworth":
        v, a = _butterworth(impulse, dt, settings)
    else:
        v, a = _savgol(impulse, dt, settings)
    return float(np.linalg.norm(v)), float(np.linalg.norm(a))


def _butterworth(
    x: Float[np.ndarray, " n"], dt: float, s: PreprocessSettings
) -> tuple[Float[np.ndarray, " n"], Float[np.ndarray, " n"]]:
    fs = 1.0 / dt
    padlen = _padlen(x.shape[0], fs, s)
    # = scipy.signal.sosfiltfilt(butter(...), padtype="odd") to ~1e-14 (fricjax.data.filters)
    v = filtfilt_lowpass(difference(x, dt, s.stencil), s.order, s.cutoff_hz, fs, padlen)
    a = filtfilt_lowpass(difference(v, dt, s.stencil), s.order, s.cutoff_hz, fs, padlen)
    return v, a


def difference(
    y: Float[np.ndarray, " n *k"], dt: float, stencil: int = 2
) -> Float[np.ndarray, " n *k"]:
    """Central-difference derivative of order ``stencil`` (2 or 4) [unit of y per s], along
    the first axis.

    Frequency response ``i·sin(ωh)/h`` (stencil 2) or ``i·(8 sin ωh − sin 2ωh)/(6h)``
    (stencil 4): relative gain errors at 50 Hz and 1 kHz of −1.6 % and −3.2e-4 per
    differentiation. The second-order stencil's loss is a systematic bias of ``m·a``
    against the model force at the upper harmonics, which diagnosis would otherwise read as
    a mass error; the end samples fall back to np.gradient's second-order one-sided rule.
    """
    d = np.gradient(y, dt, edge_order=2, axis=0)
    if stencil == 4 and y.shape[0] >= 5:
        d[2:-2] = (y[:-4] - 8.0 * y[1:-3] + 8.0 * y[3:-1] - y[4:]) / (12.0 * dt)
    return d


def _padlen(n: int, fs: float, s: PreprocessSettings) -> int:
    n_sections = (s.order + 1) // 2  # scipy's default padlen counts second-order sections
    padlen = max(3 * (2 * n_sections + 1), math.ceil(_PAD_CUTOFF_PERIODS * fs / s.cutoff_hz))
    return min(padlen, n - 1)


def _savgol(
    x: Float[np.ndarray, " n"], dt: float, s: PreprocessSettings
) -> tuple[Float[np.ndarray, " n"], Float[np.ndarray, " n"]]:
    # mode="interp" fits the polynomial to the first/last window instead of inventing
    # samples beyond the record.
    from scipy import signal  # only here: importing scipy.signal costs ~0.6 s of CPU

    w, p = s.savgol_window, s.savgol_polyorder
    v = signal.savgol_filter(x, w, p, deriv=1, delta=dt, mode="interp", axis=0)
    a = signal.savgol_filter(x, w, p, deriv=2, delta=dt, mode="interp", axis=0)
    return v, a


def _vector(
    value: Any, name: str, source: str | None, n: int | None = None
) -> Float[np.ndarray, " n"]:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise FricjaxError(f"{where(source, name)}: must be an array of numbers") from None
    if arr.ndim != 1:
        raise FricjaxError(f"{where(source, name)}: must be 1-D, got shape {arr.shape}")
    if n is not None and arr.shape[0] != n:
        raise FricjaxError(f"{where(source, name)}: has {arr.shape[0]} samples, /t has {n}")
    bad = np.flatnonzero(~np.isfinite(arr))
    if bad.size:
        raise FricjaxError(f"{where(source, name)}: contains NaN or inf at index {bad[0]}")
    return arr


def _uniform_step(t: Float[np.ndarray, " n"], source: str | None) -> float:
    steps = np.diff(t)
    first_bad = np.flatnonzero(steps <= 0)
    if first_bad.size:
        i = int(first_bad[0])
        raise FricjaxError(f"{where(source, '/t')}: not strictly increasing at index {i + 1}")
    dt = float((t[-1] - t[0]) / (t.shape[0] - 1))
    jitter = np.abs(steps - dt) / dt
    worst = int(np.argmax(jitter))
    if jitter[worst] > _MAX_STEP_JITTER:
        raise FricjaxError(
            f"{where(source, '/t')}: non-uniform time step (step {worst} differs from the "
            f"mean {dt:g} s by a relative {jitter[worst]:.2g} > {_MAX_STEP_JITTER:g})"
        )
    return dt


def _is_int(value: object) -> bool:
    return isinstance(value, int | np.integer) and not isinstance(value, bool)


def _is_real(value: object) -> bool:
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(value, bool)
