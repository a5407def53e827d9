"""Derivative accuracy, noise reduction, zero phase and user errors of fricjax.data.preprocess.

Test signal: a ramp of 0.4 m/s plus sinusoids at 5, 12, 27 and 50 Hz (the paper twin's
drive band is 5–50 Hz) with acceleration amplitudes 6, 4, 3, 2 m/s², sampled at 1 kHz for
0.272 s (the seed paper's record) and for 2 s. Errors are measured against the analytic
derivatives over the interior (10 samples dropped at each end) unless stated.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from jaxtyping import Float
from scipy import signal

from fricjax.data.preprocess import (
    Derivatives,
    PreprocessSettings,
    derivative_columns,
    derivatives,
    measured_force,
    noise_gains,
)
from fricjax.errors import FricjaxError

FS = 1000.0
DT = 1.0 / FS
FREQS = np.array([5.0, 12.0, 27.0, 50.0])
ACC_AMPS = np.array([6.0, 4.0, 3.0, 2.0])
PHASES = np.array([0.3, 1.1, 2.0, 0.7])
RAMP = 0.4
EDGE = 10
BUTTER = PreprocessSettings()
SAVGOL = PreprocessSettings(method="savgol")

Vec = Float[np.ndarray, " n"]


def known_signal(duration: float) -> tuple[Vec, Vec, Vec, Vec]:
    """t [s], x [m], v [m/s], a [m/s²] of the test signal, shape [round(duration·FS)]."""
    t = np.arange(round(duration * FS)) / FS
    omega = 2.0 * np.pi * FREQS
    phase = np.outer(t, omega) + PHASES
    x_amp = ACC_AMPS / omega**2
    x = RAMP * t + np.sin(phase) @ x_amp
    v = RAMP + np.cos(phase) @ (x_amp * omega)
    a = -np.sin(phase) @ ACC_AMPS
    return t, x, v, a


def interior_rel_rms(estimate: Vec, truth: Vec, reference: Vec) -> float:
    """RMS of (estimate − truth) over the interior, relative to the RMS of reference."""
    inner = slice(EDGE, -EDGE)
    err = estimate[inner] - truth[inner]
    return float(np.sqrt(np.mean(err**2) / np.mean(reference[inner] ** 2)))


def subsample_lag(estimate: Vec, truth: Vec) -> tuple[int, float]:
    """(integer lag of the cross-correlation peak, parabola-refined lag) in samples;
    positive when the estimate lags the truth."""
    c = np.correlate(estimate - estimate.mean(), truth - truth.mean(), mode="full")
    k = int(np.argmax(c))
    y0, y1, y2 = c[k - 1], c[k], c[k + 1]
    lag = k - (truth.shape[0] - 1)
    return lag, lag + 0.5 * float(y0 - y2) / float(y0 - 2.0 * y1 + y2)


# --- (1) noise-free accuracy -------------------------------------------------------------
# Measured relative RMS errors, v against the RMS of its oscillating part (v − ramp):
#   butterworth: v 8.7e-4 (0.272 s) / 8.1e-4 (2 s);  a 1.01e-2 / 1.03e-2
#   savgol:      v 1.8e-4 / 1.5e-4;                   a 8.6e-3 / 8.8e-3
# The Butterworth a error is mostly the two central differences' 3.3 % loss at 50 Hz.
@pytest.mark.parametrize(
    ("settings", "v_bound", "a_bound"),
    [(BUTTER, 1.2e-3, 1.3e-2), (SAVGOL, 3e-4, 1.1e-2)],
    ids=["butterworth", "savgol"],
)
@pytest.mark.parametrize("duration", [0.272, 2.0])
def test_noise_free_derivatives_match_analytic(
    settings: PreprocessSettings, v_bound: float, a_bound: float, duration: float
) -> None:
    t, x, v, a = known_signal(duration)
    d = derivatives(t, x, settings)
    assert interior_rel_rms(d.v, v, v - RAMP) < v_bound
    assert interior_rel_rms(d.a, a, a) < a_bound


def test_highest_harmonic_gain_matches_design() -> None:
    """At 50 Hz the Butterworth default keeps 0.9836² (central differences) × 0.9937
    (zero-phase filter, twice) = 0.961 of a's amplitude: the bias stated in the docstring."""
    t = np.arange(4000) * DT
    omega = 2.0 * np.pi * 50.0
    d = derivatives(t, np.sin(omega * t) / omega**2, BUTTER)
    inner = slice(1000, -1000)
    gain = np.sqrt(2.0 * np.mean(d.a[inner] ** 2))
    sinc = np.sin(omega * DT) / (omega * DT)
    # Digital Butterworth (bilinear transform): analog formula on prewarped frequencies.
    warped = np.tan(np.pi * 50.0 / FS) / np.tan(np.pi * BUTTER.cutoff_hz / FS)
    filt = 1.0 / (1.0 + warped ** (2 * BUTTER.order))
    assert filt == pytest.approx(0.99683, abs=1e-5)
    assert gain == pytest.approx(sinc**2 * filt**2, rel=1e-4)
    assert gain == pytest.approx(0.961, abs=1e-3)


def test_odd_padding_beats_even_and_constant_at_the_ends() -> None:
    """The padding choice: on the 272-sample record the RMS error of a over the first and
    last 10 samples (relative to the RMS of a) is 0.074 with odd padding, 0.30 even, 0.17
    constant (same filter, same padlen)."""
    t, x, _, a = known_signal(0.272)
    ends = np.r_[0:EDGE, t.shape[0] - EDGE : t.shape[0]]

    def end_error(est: Vec) -> float:
        return float(np.sqrt(np.mean((est[ends] - a[ends]) ** 2) / np.mean(a**2)))

    ours = end_error(derivatives(t, x, BUTTER).a)
    sos = signal.butter(BUTTER.order, BUTTER.cutoff_hz, fs=FS, output="sos")
    others = {}
    for padtype in ("even", "constant"):
        v = signal.sosfiltfilt(sos, np.gradient(x, DT, edge_order=2), padtype=padtype, padlen=30)
        est = signal.sosfiltfilt(sos, np.gradient(v, DT, edge_order=2), padtype=padtype, padlen=30)
        others[padtype] = end_error(est)
    assert ours < 0.09
    assert ours < 0.5 * min(others.values())


# --- (2) noise reduction -------------------------------------------------------------------
SIGMA_X = 1e-5


def noise_on_a(settings: PreprocessSettings, duration: float, seeds: int) -> tuple[float, float]:
    """Pooled interior std of the noise part of a: (this method, plain double central
    differencing), for white noise of std SIGMA_X on x."""
    t, x, _, _ = known_signal(duration)
    clean = derivatives(t, x, settings).a
    plain_clean = np.gradient(np.gradient(x, DT), DT)
    ours, plain = [], []
    for seed in range(seeds):
        noisy = x + SIGMA_X * np.random.default_rng(seed).standard_normal(x.shape)
        ours.append((derivatives(t, noisy, settings).a - clean)[EDGE:-EDGE])
        plain.append((np.gradient(np.gradient(noisy, DT), DT) - plain_clean)[EDGE:-EDGE])
    return float(np.std(np.concatenate(ours))), float(np.std(np.concatenate(plain)))


# Predicted (noise_gains): σ_a/σ_x = 4.89e4 s⁻² (butterworth), 5.74e4 (savgol), against
# 6.12e5 for plain differencing: reductions 12.5× and 10.7×. Pooled over the seeds below the
# measured reductions were 12.6 / 11.9 (butterworth, 2 s / 0.272 s) and 10.8 / 10.4 (savgol),
# and the pooled σ_a/σ_x were within 4.3 % of the prediction.
@pytest.mark.parametrize(
    ("settings", "min_reduction"), [(BUTTER, 11.0), (SAVGOL, 9.5)], ids=["butterworth", "savgol"]
)
@pytest.mark.parametrize(("duration", "seeds"), [(2.0, 4), (0.272, 16)])
def test_noise_on_a_is_reduced(
    settings: PreprocessSettings, min_reduction: float, duration: float, seeds: int
) -> None:
    ours, plain = noise_on_a(settings, duration, seeds)
    assert plain / ours > min_reduction
    _, gain_a = noise_gains(settings, FS)
    assert ours / SIGMA_X == pytest.approx(gain_a, rel=0.06)
    assert plain / SIGMA_X == pytest.approx(np.sqrt(3.0 / 8.0) * FS**2, rel=0.06)


def test_noise_gains_of_defaults() -> None:
    """The numbers the PreprocessSettings docstring quotes."""
    gv, ga = noise_gains(BUTTER, FS)
    assert gv == pytest.approx(139.4, rel=1e-3)
    assert ga == pytest.approx(4.885e4, rel=1e-3)
    gv, ga = noise_gains(SAVGOL, FS)
    assert gv == pytest.approx(166.0, rel=1e-3)
    assert ga == pytest.approx(5.744e4, rel=1e-3)
    # Savitzky–Golay: the norms of its fixed convolution weights.
    w = signal.savgol_coeffs(SAVGOL.savgol_window, SAVGOL.savgol_polyorder, deriv=2, delta=DT)
    assert ga == pytest.approx(np.linalg.norm(w), rel=1e-12)


# --- (3) zero phase ------------------------------------------------------------------------
@pytest.mark.parametrize("settings", [BUTTER, SAVGOL], ids=["butterworth", "savgol"])
def test_zero_phase_no_lag(settings: PreprocessSettings) -> None:
    """Cross-correlation with the true v and a peaks at lag 0 (refined: |lag| < 0.1 sample;
    measured < 0.05). A causal one-pass filter of the same design lags v by 4.9 samples,
    so the check can see a lag."""
    t, x, v, a = known_signal(0.272)
    d = derivatives(t, x, settings)
    for est, truth in ((d.v, v), (d.a, a)):
        lag, refined = subsample_lag(est, truth)
        assert lag == 0
        assert abs(refined) < 0.1
    sos = signal.butter(BUTTER.order, BUTTER.cutoff_hz, fs=FS, output="sos")
    causal_lag, causal_refined = subsample_lag(signal.sosfilt(sos, np.gradient(x, DT)), v)
    assert causal_lag >= 4
    assert causal_refined > 4.0


# --- trim, pass-through, measured force ----------------------------------------------------
def test_trim_drops_filtered_ends_and_passes_u_f() -> None:
    t, x, _, _ = known_signal(0.272)
    u = np.cos(t)
    F = np.sin(t)
    full = derivatives(t, x, BUTTER, u=u, F=F)
    trimmed = derivatives(t, x, dataclasses.replace(BUTTER, trim=7), u=u, F=F)
    assert isinstance(trimmed, Derivatives)
    assert trimmed.t.shape == (272 - 14,)
    for name in ("t", "x", "v", "a", "u", "F"):
        # Trimming happens after filtering: the kept samples are bit-identical.
        np.testing.assert_array_equal(getattr(trimmed, name), getattr(full, name)[7:-7])
    raw = derivatives(t, x, dataclasses.replace(BUTTER, filter_input=False), u=u, F=F)
    np.testing.assert_array_equal(raw.u, u)
    np.testing.assert_array_equal(raw.F, F)
    assert derivatives(t, x, BUTTER).u is None


@pytest.mark.parametrize("settings", [BUTTER, SAVGOL], ids=["butterworth", "savgol"])
def test_columns_are_the_derivatives_of_each_column(settings: PreprocessSettings) -> None:
    """The batched preprocessing (the residual noise's impulse responses and draws) is the
    one-record preprocessing of every column, to rounding."""
    t, x, _, _ = known_signal(0.272)
    rng = np.random.default_rng(2)
    xs = np.column_stack([x, rng.standard_normal(t.size), np.eye(t.size)[:, 100]])
    got = derivative_columns(t, xs, settings)
    for k in range(xs.shape[1]):
        one = derivatives(t, xs[:, k], settings)
        for name, col in zip(("x", "v", "a"), got, strict=True):
            ref = getattr(one, name)
            # (savgol's end windows are least-squares fits: 1e-10 of the scale apart)
            np.testing.assert_allclose(col[:, k], ref, rtol=0, atol=1e-9 * np.max(np.abs(ref)))


@pytest.mark.parametrize(
    ("settings", "rel"), [(BUTTER, 2e-3), (SAVGOL, 1e-5)], ids=["butterworth", "savgol"]
)
def test_measured_force_of_constant_acceleration(settings: PreprocessSettings, rel: float) -> None:
    """x = x0 + v0·t + ½·a0·t² ⇒ F = m·a0 at every sample, ends included. Butterworth's
    largest deviation (edge transient of the padded filter) measured 0.1 %; Savitzky–Golay
    is exact for polynomials up to its degree (round-off only)."""
    t = np.arange(272) * DT
    a0, mass = 3.5, 42.0
    d = derivatives(t, 0.01 + 0.2 * t + 0.5 * a0 * t**2, settings)
    F = measured_force(d.a, mass)
    np.testing.assert_allclose(F, mass * a0, rtol=rel)
    assert F.dtype == np.float64


def test_measured_force_is_mass_times_acceleration() -> None:
    a = np.array([-2.0, 0.0, 1.5])
    np.testing.assert_array_equal(measured_force(a, 4.0), np.array([-8.0, 0.0, 6.0]))


@pytest.mark.parametrize("mass", [0.0, -1.0, float("nan"), float("inf"), True, "12"])
def test_measured_force_rejects_bad_mass(mass: object) -> None:
    with pytest.raises(FricjaxError, match=r"rec\.h5: mass: must be a positive mass"):
        measured_force(np.ones(3), mass, source="rec.h5")  # type: ignore[arg-type]


# --- (4) user errors -----------------------------------------------------------------------
def test_from_dict_reads_table_and_defaults() -> None:
    s = PreprocessSettings.from_dict({"cutoff_hz": 80, "trim": 5}, source="paper.toml")
    assert s == dataclasses.replace(PreprocessSettings(), cutoff_hz=80.0, trim=5)
    assert isinstance(s.cutoff_hz, float)
    assert PreprocessSettings.from_dict({}) == PreprocessSettings()


def test_cutoff_above_nyquist_names_file_and_key() -> None:
    s = PreprocessSettings.from_dict({"cutoff_hz": 600.0}, source="paper.toml")
    t, x, _, _ = known_signal(0.272)
    with pytest.raises(FricjaxError) as err:
        derivatives(t, x, s)
    assert str(err.value) == (
        "paper.toml: [preprocess].cutoff_hz: must be below the Nyquist frequency 500 Hz, got 600"
    )


def test_savgol_window_longer_than_record() -> None:
    s = PreprocessSettings.from_dict(
        {"method": "savgol", "savgol_window": 301}, source="paper.toml"
    )
    t, x, _, _ = known_signal(0.272)
    with pytest.raises(FricjaxError, match=r"paper\.toml: \[preprocess\]\.savgol_window: 301"):
        derivatives(t, x, s)


def test_trim_too_large_for_record() -> None:
    s = PreprocessSettings.from_dict({"trim": 135}, source="paper.toml")
    t, x, _, _ = known_signal(0.272)
    with pytest.raises(FricjaxError, match=r"paper\.toml: \[preprocess\]\.trim: .* leaves 2"):
        derivatives(t, x, s)


@pytest.mark.parametrize(
    ("table", "key"),
    [
        ({"cutof_hz": 100.0}, "cutof_hz: unknown key"),
        ({"method": "kalman"}, "method: must be one of"),
        ({"order": 0}, "order: must be an integer >= 1"),
        ({"order": 4.0}, "order: must be an integer"),
        ({"order": True}, "order: must be an integer"),
        ({"cutoff_hz": -5.0}, "cutoff_hz: must be a positive finite"),
        ({"cutoff_hz": float("inf")}, "cutoff_hz: must be a positive finite"),
        ({"cutoff_hz": "100"}, "cutoff_hz: must be a positive finite"),
        ({"savgol_window": 26}, "savgol_window: must be an odd integer"),
        ({"savgol_window": 7, "savgol_polyorder": 7}, "savgol_window: must exceed"),
        ({"savgol_polyorder": 1, "savgol_window": 5}, "savgol_polyorder: must be an integer >= 2"),
        ({"trim": -1}, "trim: must be an integer >= 0"),
    ],
)
def test_bad_settings_name_file_and_key(table: dict[str, object], key: str) -> None:
    with pytest.raises(FricjaxError) as err:
        PreprocessSettings.from_dict(table, source="paper.toml")
    assert str(err.value).startswith(f"paper.toml: [preprocess].{key}")
    assert "\n" not in str(err.value)


def test_bad_settings_built_in_code_name_memory() -> None:
    with pytest.raises(FricjaxError, match=r"^<memory>: \[preprocess\]\.order"):
        PreprocessSettings(order=-2)


def test_bad_arrays_name_the_field() -> None:
    t, x, _, _ = known_signal(0.272)
    cases = []
    x_nan = x.copy()
    x_nan[17] = np.nan
    cases.append(((t, x_nan), {}, r"rec\.h5: /x: contains NaN or inf at index 17"))
    cases.append(((t, x[:-1]), {}, r"rec\.h5: /x: has 271 samples, /t has 272"))
    cases.append(((t, x), {"F": x[:10]}, r"rec\.h5: /F: has 10 samples"))
    cases.append(((t, x.reshape(2, -1)), {}, r"rec\.h5: /x: must be 1-D"))
    t_back = t.copy()
    t_back[50] = t_back[49]
    cases.append(((t_back, x), {}, r"rec\.h5: /t: not strictly increasing at index 50"))
    t_jit = t.copy()
    t_jit[100] += 1e-5 * DT
    cases.append(((t_jit, x), {}, r"rec\.h5: /t: non-uniform time step"))
    cases.append(((t[:2], x[:2]), {}, r"rec\.h5: /t: 2 samples"))
    for args, kwargs, pattern in cases:
        with pytest.raises(FricjaxError, match=pattern):
            derivatives(*args, BUTTER, source="rec.h5", **kwargs)


def test_measured_force_filtered_like_m_a_matches_it_on_a_noiseless_axis() -> None:
    """A noiseless axis m·ẍ = F with content up to 80 Hz (above the 100 Hz filter's flat
    band): filtered like m·a, the measured F equals the preprocessed m·a to 0.2 % RMS
    (what is left is the 4th-order difference's gain), raw it is 6 % off."""
    t = np.arange(1000) / FS
    freqs = np.array([5.0, 12.0, 27.0, 50.0, 80.0])
    amps = np.array([6.0, 4.0, 3.0, 2.0, 2.0])
    omega = 2.0 * np.pi * freqs
    phase = np.outer(t, omega) + np.array([0.3, 1.1, 2.0, 0.7, 0.2])
    x = RAMP * t + np.sin(phase) @ (amps / omega**2)
    mass = 3.0
    F = mass * (-np.sin(phase) @ amps)
    settings = PreprocessSettings(stencil=4)
    inner = slice(30, -30)

    def rel(d: Derivatives) -> float:
        err = d.F[inner] - mass * d.a[inner]
        return float(np.sqrt(np.mean(err**2) / np.mean(F[inner] ** 2)))

    assert rel(derivatives(t, x, settings, F=F)) < 2e-3
    assert rel(derivatives(t, x, dataclasses.replace(settings, filter_input=False), F=F)) > 0.05
    # Savitzky–Golay: its smoother is only close to the operator that made a
    smooth = PreprocessSettings(method="savgol")
    assert rel(derivatives(t, x, smooth, F=F)) < 0.5 * rel(
        derivatives(t, x, dataclasses.replace(smooth, filter_input=False), F=F)
    )
