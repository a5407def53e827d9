"""The scale of the diagnosis' tests comes from the recording: σ̂_x, its degrees of freedom,
and the near-rest band it sizes."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import stats

from fricjax.data.noise import NoiseEstimate
from fricjax.data.preprocess import PreprocessSettings, derivatives, noise_gains
from fricjax.data.twin import PAPER_MODEL
from fricjax.diagnose.evidence import (
    EXACT_DOF,
    Evidence,
    effective_dof,
    near_rest_band,
    record_noise,
)
from fricjax.params import ParamSpec
from fricjax.problem import Problem

SETTINGS = PreprocessSettings(trim=10)


def _problem(x: np.ndarray, dt: float = 1e-3) -> Problem:
    """A problem built from a raw displacement record as build_problem does."""
    t = np.arange(x.shape[0]) * dt
    d = derivatives(t, x, SETTINGS)
    spec = ParamSpec(
        tuple(p.fixed_at(45.0) if p.name == "mass" else p for p in PAPER_MODEL.parameters())
    )
    zero = np.zeros_like(d.t)
    return Problem(PAPER_MODEL, spec, d.t, d.x, d.v, d.a, zero, preprocess=SETTINGS)


def _motion(n: int) -> np.ndarray:
    t = np.arange(n) * 1e-3
    return 0.05 * np.sin(2 * np.pi * 1.5 * t) + 0.01 * np.sin(2 * np.pi * 4.0 * t)


def test_sigma_from_the_record_is_within_its_error_of_the_truth_whatever_the_model() -> None:
    # 1 s of a smooth motion with 24 µm of white noise: σ̂_x must be the noise's within a
    # few of its standard errors; no model enters (the same x gives the same σ̂).
    sigma = 24e-6
    rng = np.random.default_rng(5)
    pb = _problem(_motion(1000) + rng.normal(0.0, sigma, 1000))
    ev = record_noise(pb)
    assert ev.noise.model == "white"
    assert abs(ev.sigma_x - sigma) < 3 * ev.noise.se
    # ν = ½(σ/se)²: a scale measured to ~5 % carries a few hundred degrees of freedom
    assert ev.nu == int(0.5 * (ev.sigma_x / ev.noise.se) ** 2)
    assert 20 < ev.nu < 2000


def test_effective_dof_matches_the_spread_of_the_estimate() -> None:
    # Over many noise draws the spread of σ̂² must be that of χ²_ν/ν with the ν reported
    # (the F references of the tests rely on it), within a factor that 200 draws resolve.
    sigma = 10e-6
    rng = np.random.default_rng(9)
    x0 = _motion(1000)
    draws = [record_noise(_problem(x0 + rng.normal(0.0, sigma, 1000))) for _ in range(200)]
    s2 = np.array([d.sigma_x**2 for d in draws]) / sigma**2
    nu = float(np.median([d.nu for d in draws]))
    ratio = float(np.var(s2) / (2.0 / nu))
    # a sample variance over 200 draws is within ±20 % (2σ); ν from 8 blocks is noisy too
    assert 0.6 < ratio < 1.6
    assert abs(float(np.mean(s2)) - 1.0) < 4 * math.sqrt(2.0 / nu / len(draws)) + 0.05


def test_a_quantised_scale_is_exact_and_a_scale_without_error_is_most_cautious() -> None:
    q = 1e-6
    quantised = NoiseEstimate(q / math.sqrt(12), math.nan, "quantised", 0, q, {})
    assert effective_dof(quantised) == EXACT_DOF
    no_error = NoiseEstimate(1e-5, math.nan, "white", 2, math.nan, {})
    assert effective_dof(no_error) == 1
    # with ν = 1 the F reference of a one-column score is far wider than χ²_1
    assert stats.f.ppf(0.99, 1, 1) > 100 * stats.chi2.ppf(0.99, 1)
    assert "ν = ∞" in Evidence(quantised).describe()


def test_the_near_rest_band_is_in_m_per_s_and_its_share_is_the_real_share() -> None:
    sigma = 2e-6
    rng = np.random.default_rng(2)
    pb = _problem(_motion(4000) + rng.normal(0.0, sigma, 4000))
    band = near_rest_band(pb, sigma)
    gain_v, _ = noise_gains(SETTINGS, 1000.0)
    assert band.speed == pytest.approx(4.0 * sigma * gain_v)
    v = np.asarray(pb.v)
    assert band.share == pytest.approx(float(np.mean(np.abs(v) < band.speed)))
    assert np.array_equal(band.mask, np.abs(v) < band.speed)
    # a band sized by a σ four times too large (a residual's, with model error in it)
    # holds a larger share: the band must come from the record's own σ
    assert near_rest_band(pb, 4 * sigma).share > band.share
