"""The numpy zero-phase Butterworth (fricjax.data.filters) against scipy.signal."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from fricjax.data.filters import butter_lowpass_zpk, filtfilt_lowpass, impulse_response


@pytest.mark.parametrize(
    ("order", "cutoff", "n", "padlen"),
    [
        (8, 100.0, 272, 60),
        (4, 100.0, 5000, 120),
        (3, 50.0, 500, 40),
        (2, 10.0, 3000, 900),
        (1, 30.0, 400, 9),
        (8, 100.0, 272, 0),
        (6, 200.0, 1000, 30),
    ],
)
def test_filtfilt_matches_scipy_sosfiltfilt(order: int, cutoff: float, n: int, padlen: int):
    rng = np.random.default_rng(order * 7 + n)
    x = np.cumsum(rng.normal(size=n)) * 1e-3 + np.sin(0.05 * np.arange(n))
    sos = signal.butter(order, cutoff, fs=1000.0, output="sos")
    if padlen:
        ref = signal.sosfiltfilt(sos, x, padtype="odd", padlen=padlen)
    else:
        ref = signal.sosfiltfilt(sos, x, padtype=None)
    got = filtfilt_lowpass(x, order, cutoff, 1000.0, padlen)
    assert np.max(np.abs(got - ref)) <= 1e-13 * np.max(np.abs(ref))


@pytest.mark.parametrize("order", [1, 2, 5, 8])
def test_design_matches_scipy_butter(order: int):
    z, p, k = butter_lowpass_zpk(order, 120.0, 1000.0)
    zz, pp, kk = signal.butter(order, 120.0, fs=1000.0, output="zpk")
    # every pole has its scipy twin (sorting conjugates is fragile at 1e-16)
    assert np.max(np.min(np.abs(p[:, None] - pp[None, :]), axis=1)) < 1e-14
    assert np.allclose(z, zz) and abs(k - kk) <= 1e-12 * abs(kk)


def test_impulse_response_has_unit_dc_gain_and_a_negligible_tail():
    h = impulse_response(8, 100.0, 1000.0)
    assert abs(h.sum() - 1.0) < 1e-14
    assert np.sum(np.abs(h[-20:])) < 1e-15 * np.sum(np.abs(h))


def test_bad_arguments_are_rejected():
    with pytest.raises(ValueError, match="cutoff"):
        butter_lowpass_zpk(4, 600.0, 1000.0)
    with pytest.raises(ValueError, match="padlen"):
        filtfilt_lowpass(np.zeros(10), 4, 100.0, 1000.0, 10)
