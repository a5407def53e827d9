"""Errors in variables (fricjax/diagnose/errors_in_variables.py): the regressors carry the
residual's own noise, so a score has a mean under H0; the predicted mean removes it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from fricjax.config import Config
from fricjax.data.twin import PAPER_TRUTH, paper_twin
from fricjax.diagnose.errors_in_variables import candidate_bias, score_bias
from fricjax.diagnose.locate import default_whitener, jacobian
from fricjax.problem import build_problem

SIGMA_X = 24e-6
DRAWS = 10


def _start_impact(config: Config, seed: int) -> tuple[float, float]:
    """(score, predicted mean) in σ of an impact column at t0 = 27 ms, w = 18 ms, at the true
    parameters of one noise draw on the 1 s paper twin; there v falls from 0.49 m/s through
    the Stribeck region (vs = 0.1 m/s) right after the record starts."""
    clean, _ = paper_twin(duration=1.0, seed=3, noise_std=0.0)
    noise = np.random.default_rng(seed).normal(0.0, SIGMA_X, clean.x.shape)
    problem = build_problem(replace(clean, x=clean.x + noise), config)
    theta = problem.theta(PAPER_TRUTH)
    wh = default_whitener(problem, theta)
    col = wh(-np.exp(-0.5 * ((problem.t - 0.027) / 0.018) ** 2))  # ∂r/∂A of the impact
    basis, sv, _ = np.linalg.svd(wh(jacobian(problem, theta)), full_matrices=False)
    basis = basis[:, sv > 1e-10 * sv[0]]
    perp = col - basis @ (basis.T @ col)
    norm = float(np.linalg.norm(perp))
    z = wh(problem.residual(theta))
    score = float(perp @ z) / norm / SIGMA_X
    bias = score_bias(problem, problem.model, problem.spec, theta, wh, SIGMA_X**2)
    assert bias is not None
    # the impact's column is a function of t alone: no own part
    mean = candidate_bias(bias, col[None, :, None])
    return score, float(mean[0, 0]) / norm / SIGMA_X


@pytest.fixture(scope="module")
def draws(paper_config: Config) -> np.ndarray:
    return np.array([_start_impact(paper_config, 100 + k) for k in range(DRAWS)])


def test_a_score_near_the_stribeck_region_has_a_mean_under_the_null(draws: np.ndarray) -> None:
    # At the TRUE parameters, with no effect: a white-noise score would have mean 0 and unit
    # variance. Measured: mean −2.61 σ over these 10 draws (−1.38 … −4.11); the score
    # statistic sees ~7 where χ²₁ means 1.
    assert np.mean(draws[:, 0]) < -1.3


def test_the_predicted_mean_removes_it(draws: np.ndarray) -> None:
    # Each draw's own prediction (Stein's lemma at the observed signals: one draw of the
    # noisy derivative; measured −2.05 … −2.53 σ): the centred score has mean zero within
    # the Monte Carlo error of 10 draws (measured −0.42, std 0.97, so SE ≈ 0.3).
    centred = draws[:, 0] - draws[:, 1]
    assert np.all(draws[:, 1] < -1.0)
    assert abs(float(np.mean(centred))) < 0.9
    assert abs(float(np.mean(centred))) < 0.5 * abs(float(np.mean(draws[:, 0])))


def test_no_correction_under_spectral_noise(paper_config: Config) -> None:
    # The derivation is for displacement noise; a spectral whitener's noise is force noise.
    rec, _ = paper_twin(duration=0.272, seed=1)
    problem = build_problem(rec, paper_config)
    theta = problem.theta(PAPER_TRUTH)
    wh = default_whitener(problem, theta, "spectral")
    assert score_bias(problem, problem.model, problem.spec, theta, wh, SIGMA_X**2) is None
