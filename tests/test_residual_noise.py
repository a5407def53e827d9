"""The residual's noise propagated from x (fricjax.residual_noise) and the sandwich σ it
gives (fricjax.refine.uncertainty_at): σ matches the spread of the estimates over noise
seeds where Gauss–Newton's white-residual σ is several times too large; the draws' path
agrees with the exact sum; a residual holding more than the noise widens σ."""

from __future__ import annotations

import dataclasses
import math
import tomllib
from pathlib import Path

import numpy as np
import pytest

import fricjax.residual_noise as residual_noise_module
from fricjax.config import load_config, parse_config
from fricjax.data.twin import AXIS_TRUTH, axis_twin
from fricjax.problem import Problem, build_problem
from fricjax.refine import (
    GAUSS_NEWTON,
    SANDWICH,
    SANDWICH_EXCESS,
    uncertainty_at,
    value_and_jacobian,
)
from fricjax.residual_noise import residual_noise

ROOT = Path(__file__).resolve().parents[1]
#: The measured-input axis, mass weighed, 200 Hz filter, 20 samples trimmed each end.
CONFIG = ROOT / "configs" / "axis_joint.toml"
#: x noise [m] of the seeds' twins (tests/test_joint.py's).
NOISE = 2e-6
SEEDS = 20
#: 99 % two-sided band of σ/s for the sample std s of 20 normal draws: s²·19/σ² ~ χ²₁₉,
#: whose 0.5 % and 99.5 % points are 6.844 and 38.582.
BAND = (math.sqrt(19 / 38.582), math.sqrt(19 / 6.844))


def fit(problem: Problem, theta0: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares estimate of a residual linear in θ (one Gauss–Newton step is exact),
    with the residual and Jacobian there."""
    r, jac = value_and_jacobian(problem.residual_fn, theta0)
    step = np.linalg.lstsq(jac, -r, rcond=None)[0]
    return theta0 + step, r + jac @ step, jac


@pytest.fixture(scope="module")
def seeds():
    cfg = load_config(CONFIG)
    truth = {**AXIS_TRUTH, "offset": 6.0}
    theta0 = np.array([truth[k] for k in ("offset", "Fc", "Fv")])
    out = []
    for seed in range(SEEDS):
        rec, _ = axis_twin(seed=seed, noise_std=NOISE, truth=truth)
        problem = build_problem(rec, cfg)
        out.append((problem, *fit(problem, theta0)))
    return out


def test_sandwich_sigma_matches_the_spread_over_noise_seeds_where_gauss_newton_does_not(seeds):
    problem, x, r, jac = seeds[0]
    lo, hi = problem.spec.lower, problem.spec.upper
    noise = residual_noise(problem, x, jac)
    honest = uncertainty_at(r, jac, x, lo, hi, noise=noise)
    white = uncertainty_at(r, jac, x, lo, hi)
    assert honest.method == SANDWICH and white.method == GAUSS_NEWTON
    spread = np.std([s[1] for s in seeds], axis=0, ddof=1)
    ratio = honest.std / spread
    assert np.all((ratio > BAND[0]) & (ratio < BAND[1])), ratio
    # the white residual's σ: 3-7x the spread (offset, Fc, Fv) on these twins
    assert np.all(white.std / spread > 2.5), white.std / spread
    # a residual of noise alone: its sum of squares is what the noise predicts
    assert abs(honest.dispersion - 1.0) < 0.2


def test_draws_agree_with_the_exact_sum_within_their_sampling_error(seeds, monkeypatch):
    problem, x, _, jac = seeds[0]
    exact = residual_noise(problem, x, jac)
    monkeypatch.setattr(residual_noise_module, "EXACT_UP_TO", 0)
    drawn = residual_noise(problem, x, jac)
    assert "exact" in exact.label and f"{residual_noise_module.DRAWS} draws" in drawn.label
    rel = math.sqrt(2.0 / residual_noise_module.DRAWS)  # of each variance, 6.3 %
    np.testing.assert_allclose(np.diag(drawn.jsj), np.diag(exact.jsj), rtol=4 * rel)
    # tr Σ sums n ≈ 10³ nearly independent squares: far tighter than one variance
    assert drawn.trace == pytest.approx(exact.trace, rel=rel)
    assert drawn.trace_sq == pytest.approx(exact.trace_sq, rel=4 * rel)


def test_a_left_out_term_widens_sigma_with_the_dispersion():
    # the axis without its Coulomb term, on twins whose Coulomb level grows; less x noise
    # so that the misfit stands out of the (high-band) noise in the residual's sum
    raw = tomllib.loads(CONFIG.read_text())
    raw.pop("joint")
    raw["params"]["Fc"] = {"unit": "N", "value": 0.0}
    cfg = parse_config(raw)
    found = []
    for fc in (20.0, 40.0):
        rec, _ = axis_twin(seed=0, noise_std=5e-7, truth={**AXIS_TRUTH, "offset": 6.0, "Fc": fc})
        problem = build_problem(rec, cfg)
        x, r, jac = fit(problem, np.array([6.0, AXIS_TRUTH["Fv"]]))
        lo, hi = problem.spec.lower, problem.spec.upper
        honest = uncertainty_at(r, jac, x, lo, hi, noise=residual_noise(problem, x, jac))
        white = uncertainty_at(r, jac, x, lo, hi)
        assert honest.method == SANDWICH_EXCESS
        # the excess over the noise is counted white: at least (1 − 1/φ) of the
        # white-residual variance, at most all of it plus the noise's own
        floor = np.sqrt(1.0 - 1.0 / honest.dispersion) * white.std
        assert np.all(honest.std >= floor * (1 - 1e-9))
        found.append((honest.dispersion, honest.std))
    (phi_1, std_1), (phi_2, std_2) = found
    assert 1.2 < phi_1 < phi_2
    assert np.all(std_2 > 2 * std_1)


def test_without_the_preprocessing_settings_sigma_stays_gauss_newton(seeds):
    problem, x, r, jac = seeds[0]
    bare = dataclasses.replace(problem, preprocess=None)
    assert residual_noise(bare, x, jac) is None
    unc = uncertainty_at(r, jac, x, problem.spec.lower, problem.spec.upper, noise=None)
    assert unc.method == GAUSS_NEWTON and math.isnan(unc.dispersion)
    # σ² = E/(n − d)·(JᵀJ)⁻¹ for the offset, from the residual alone
    want = math.sqrt(r @ r / (r.size - 3) * np.linalg.inv(jac.T @ jac)[0, 0])
    assert unc.std[0] == pytest.approx(want, rel=1e-9)


def _paper_problem(decimate: int | None = None) -> Problem:
    from fricjax.data.twin import paper_twin

    raw = tomllib.loads((ROOT / "configs" / "paper.toml").read_text())
    if decimate:
        raw.setdefault("preprocess", {})["decimate"] = decimate
    rec, _ = paper_twin(duration=1.0, seed=3)
    return build_problem(rec, parse_config(raw))


@pytest.mark.parametrize("case", ["axis", "paper"])
def test_the_banded_pointwise_path_equals_the_sum_over_every_impulse(seeds, case, monkeypatch):
    if case == "axis":
        problem, x, _, jac = seeds[0]
    else:
        problem = _paper_problem()
        x = problem.spec.init
        jac = value_and_jacobian(problem.residual_fn, x)[1]
    n_raw = problem.n + 2 * problem.preprocess.trim
    dt = float(problem.t[-1] - problem.t[0]) / (problem.n - 1)
    assert residual_noise_module._reach(problem.preprocess, n_raw, dt) is not None
    banded = residual_noise(problem, x, jac)
    monkeypatch.setattr(residual_noise_module, "_reach", lambda *a: None)
    dense = residual_noise(problem, x, jac)
    # the reach leaves BAND_TOL = 1e-20 of each response's squared mass out: ~1e-10 of an
    # amplitude, far below σ's own sampling error; off-diagonal terms against their scale
    scale = np.sqrt(np.outer(np.diag(dense.jsj), np.diag(dense.jsj)))
    assert np.all(np.abs(banded.jsj - dense.jsj) <= 1e-8 * scale)
    assert banded.trace == pytest.approx(dense.trace, rel=1e-8)
    assert banded.trace_sq == pytest.approx(dense.trace_sq, rel=1e-8)


def test_a_decimated_residual_is_not_taken_for_pointwise():
    problem = _paper_problem(decimate=4)
    n_raw = problem.n + 2 * problem.preprocess.trim
    dt = float(problem.t[-1] - problem.t[0]) / (problem.n - 1)
    irs = residual_noise_module._impulse_responses(problem.preprocess, n_raw, dt)
    theta = np.asarray(problem.spec.init)[None]
    assert residual_noise_module._pointwise_gains([problem.residual_fn], theta, irs) == [None]


def test_several_problems_at_once_give_each_its_own_noise(seeds):
    from fricjax.residual_noise import residual_noises

    chosen = seeds[:3]
    batch = residual_noises([s[0] for s in chosen], [s[1] for s in chosen], [s[3] for s in chosen])
    for (problem, x, _, jac), together in zip(chosen, batch, strict=True):
        alone = residual_noise(problem, x, jac)
        np.testing.assert_allclose(together.jsj, alone.jsj, rtol=1e-12)
        assert together.trace == pytest.approx(alone.trace, rel=1e-12)
        assert together.trace_sq == pytest.approx(alone.trace_sq, rel=1e-12)
        assert together.label == alone.label
