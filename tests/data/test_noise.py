"""The noise scale of a recording from its own high band (fricjax.data.noise)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fricjax.data.noise import estimate_noise

RATE = 1000.0


def _ram_like(n: int, seed: int) -> np.ndarray:
    """A smooth 0.1 m stroke with ten harmonics of 5 Hz (the seed's drive, eq. 4), [m]."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / RATE
    x = 0.3 * t**2
    for i in range(1, 11):
        amp = 0.02 / i**3
        x = x + amp * np.sin(2 * np.pi * 5 * i * t + rng.uniform(0, 2 * np.pi))
    return x


@pytest.mark.parametrize("sigma", [1e-6, 5e-6, 24e-6, 100e-6])
@pytest.mark.parametrize("n", [272, 1000, 4000])
def test_white_displacement_noise_is_recovered_within_its_standard_error(sigma, n):
    rng = np.random.default_rng(7)
    est = estimate_noise(_ram_like(n, 1) + rng.normal(0.0, sigma, n))
    assert est.model == "white"
    # the stated error is honest (4 se) and the estimate is useful (within 15 %)
    assert abs(est.sigma - sigma) <= 4 * est.se
    assert abs(est.sigma / sigma - 1) < 0.15


def test_a_stick_slip_motion_does_not_inflate_the_scale():
    # velocity kinks at every stop: x holds still for 40 of every 100 samples
    n, sigma = 2000, 5e-6
    v = np.where((np.arange(n) % 100) < 60, 0.05, 0.0)
    x = np.cumsum(v) / RATE
    est = estimate_noise(x + np.random.default_rng(3).normal(0.0, sigma, n))
    assert abs(est.sigma / sigma - 1) < 0.15


def test_an_encoder_lattice_gives_the_rounding_error_of_its_step():
    q = 1e-5
    x = np.round(_ram_like(2000, 2) / q) * q
    est = estimate_noise(x)
    assert est.model == "quantised"
    assert math.isclose(est.step, q, rel_tol=1e-9)
    assert math.isclose(est.sigma, q / math.sqrt(12.0), rel_tol=1e-9)


def test_noise_coarser_than_the_storage_lattice_is_measured_not_rounded():
    sigma, q = 3e-6, 1e-6
    rng = np.random.default_rng(5)
    x = np.round((_ram_like(2000, 3) + rng.normal(0.0, sigma, 2000)) / q) * q
    est = estimate_noise(x)
    assert est.model == "white"
    # rounding adds q²/12 in quadrature
    assert abs(est.sigma / math.hypot(sigma, q / math.sqrt(12.0)) - 1) < 0.15


def test_a_noiseless_motion_gives_only_an_upper_bound_far_below_any_sensor():
    est = estimate_noise(_ram_like(1000, 4))
    assert est.model == "upper_bound"
    assert est.sigma < 1e-8


def test_a_force_channel_in_newtons():
    rng = np.random.default_rng(11)
    t = np.arange(3000) / RATE
    force = 200 * np.sin(2 * np.pi * 3 * t) + 40 * np.sign(np.sin(2 * np.pi * 1.5 * t))
    est = estimate_noise(force + rng.normal(0.0, 2.0, t.size))
    assert abs(est.sigma / 2.0 - 1) < 0.15


def test_too_short_a_signal_is_refused():
    with pytest.raises(ValueError, match="16 samples"):
        estimate_noise(np.zeros(10))


def test_reversals_count_the_motion_s_turns_not_the_noise_s_flips() -> None:
    from fricjax.data.noise import reversals

    rng = np.random.default_rng(8)
    t = np.arange(4000) / 1000.0
    sigma_v = 1e-3
    # three periods of a sine (6 turns), long stops at rest between the strokes where only
    # noise moves the filtered velocity
    v = 0.05 * np.sin(2 * np.pi * 0.75 * t) * (np.abs(np.sin(2 * np.pi * 0.75 * t)) > 0.3)
    noisy = v + rng.normal(0.0, sigma_v, t.size)
    naive = int(np.sum(np.diff(np.sign(noisy[np.abs(noisy) > 1e-9])) != 0))
    assert naive > 50  # every sign change counted: the noise's
    assert reversals(noisy, 4.0 * sigma_v) == 5  # the turns between 6 strokes
    assert reversals(rng.normal(0.0, sigma_v, t.size), 4.0 * sigma_v) <= 1
