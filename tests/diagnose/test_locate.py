"""Mismatch maps and residual tests: calibrated on null records, and they find what is there.

Null records: a 1 s paper-twin trajectory with viscous friction only (Fc = Fs = 0, so the
residual is linear in the noise), simulated once; white x-noise (σ_x = 24 µm) goes through
derivatives() (trim = 10) and a is set so that the residual at the truth is exactly the
preprocessed noise's. Base model: the paper's drive + Stribeck term with Fc, Fs, vs fixed
(23 free parameters), evaluated at the truth.
"""

from __future__ import annotations

from dataclasses import replace
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

import fricjax  # noqa: F401  (float64 on)
from fricjax.data.preprocess import PreprocessSettings, derivatives
from fricjax.data.twin import PAPER_MODEL, PAPER_TRUTH
from fricjax.diagnose.locate import (
    VARIABLES,
    default_whitener,
    jacobian,
    locate,
    locate_plan,
    locate_whitened,
    map_scores,
    max_score_null,
    orthonormal_basis,
    project_out,
    score_pvalue,
    score_statistic,
)
from fricjax.diagnose.whiten import Whitener, make_whitener
from fricjax.errors import FricjaxError
from fricjax.model.simulate import simulate
from fricjax.params import ParamSpec
from fricjax.problem import Problem

N_FULL = 1000
DT = 1e-3
MASS = 45.0
SIGMA_X = 2.4e-5
SETTINGS = PreprocessSettings(trim=10)
TRUTH = {**PAPER_TRUTH, "Fc": 0.0, "Fs": 0.0}
FIXED = {"Fc": 0.0, "Fs": 0.0, "vs": PAPER_TRUTH["vs"], "mass": MASS}


class Twin(NamedTuple):
    t: np.ndarray  # full record [N_FULL]
    x: np.ndarray
    v_exact: np.ndarray  # trimmed [n]
    a_exact: np.ndarray
    spec: ParamSpec
    theta: np.ndarray
    wh: Whitener

    def record(self, seed: int, force: np.ndarray | None = None) -> Problem:
        """Null record (plus an extra force [N] on the trimmed samples, if given)."""
        e = np.random.default_rng(seed).normal(0.0, SIGMA_X, N_FULL)
        d, clean = derivatives(self.t, self.x + e, SETTINGS), derivatives(self.t, self.x, SETTINGS)
        a = self.a_exact + d.a - clean.a + (0.0 if force is None else force / MASS)
        keep = slice(10, N_FULL - 10)
        return Problem(
            PAPER_MODEL,
            self.spec,
            self.t[keep],
            d.x,
            self.v_exact + d.v - clean.v,
            a,
            np.zeros(N_FULL - 20),
            preprocess=SETTINGS,
        )


@pytest.fixture(scope="module")
def twin() -> Twin:
    t = np.arange(N_FULL) * DT
    p = {k: jnp.asarray(v) for k, v in TRUTH.items()}
    x, v, a = (
        np.asarray(arr) for arr in simulate(PAPER_MODEL, p, jnp.asarray(t), 0.0, 0.0, substeps=16)
    )
    params = tuple(
        q.fixed_at(FIXED[q.name]) if q.name in FIXED else replace(q, init=TRUTH[q.name])
        for q in PAPER_MODEL.parameters()
    )
    spec = ParamSpec(params)
    keep = slice(10, N_FULL - 10)
    exact = Problem(
        PAPER_MODEL,
        spec,
        t[keep],
        x[keep],
        v[keep],
        a[keep],
        np.zeros(N_FULL - 20),
        preprocess=SETTINGS,
    )
    theta = spec.init
    a_exact = a[keep] - exact.residual(theta) / MASS  # the model's own acceleration
    wh = make_whitener(exact, damping=TRUTH["Fv"])  # viscous friction: c = Fv exactly
    return Twin(t, x, v[keep], a_exact, spec, theta, wh)


@pytest.fixture(scope="module")
def plan(twin: Twin):
    return locate_plan(twin.record(0), twin.theta, whitener=twin.wh, n_mc=2000, seed=0)


def test_projection_and_score_algebra(twin: Twin) -> None:
    rng = np.random.default_rng(3)
    J = rng.normal(size=(twin.wh.M, 5))
    J[:, 4] = J[:, 0] + J[:, 1]  # dependent column: rank 4
    assert orthonormal_basis(J).shape[1] == 4
    assert np.max(np.abs(J.T @ project_out(J, rng.normal(size=twin.wh.M)))) < 1e-10
    # A regressor inside the span of J scores 0; one outside scores its explained share.
    r = rng.normal(size=twin.wh.M)
    assert score_statistic(r, J[:, :2] @ [1.0, 2.0], J, 1.0) == pytest.approx(0.0, abs=1e-20)
    g = rng.normal(size=twin.wh.M)
    gp = project_out(J, g)
    assert score_statistic(r, g, J, 2.0) == pytest.approx((gp @ r) ** 2 / (gp @ gp) / 2.0)


def test_max_score_null_is_chi2_and_reproducible(twin: Twin) -> None:
    g = np.random.default_rng(4).normal(size=(1, twin.wh.M, 1))
    null = max_score_null(g, 4000, 11)
    assert stats.kstest(null, stats.chi2(1).cdf).pvalue > 0.01
    assert np.array_equal(null, max_score_null(g, 4000, 11))
    assert not np.array_equal(null, max_score_null(g, 4000, 12))
    # Normalised by its own σ̂² (J given): S/dof ~ Beta(1/2, (dof − 1)/2).
    J = np.random.default_rng(5).normal(size=(twin.wh.M, 20))
    gp = project_out(J, g[0])[None]
    dof = twin.wh.M - 20
    null_j = max_score_null(gp, 4000, 13, J_w=J)
    assert stats.kstest(null_j / dof, stats.beta(0.5, (dof - 1) / 2).cdf).pvalue > 0.01
    # Normalised by an independent σ̂² with ν degrees of freedom: S ~ F(1, ν).
    null_e = max_score_null(gp, 4000, 14, external=30)
    assert stats.kstest(null_e, stats.f(1, 30).cdf).pvalue > 0.01
    p = score_pvalue(null_e, 1, dof, external=30)
    assert stats.kstest(p, stats.uniform.cdf).pvalue > 0.01


def test_score_pvalues_of_fixed_regressors_are_uniform(twin: Twin) -> None:
    # Three fixed force shapes: a slow ramp, a 30 Hz burst, a smooth random force [N].
    t = twin.t[10:-10]
    rng = np.random.default_rng(6)
    smooth = np.convolve(rng.normal(size=t.size + 40), np.hanning(41), mode="valid")
    shapes = np.stack([t - t.mean(), np.sin(2 * np.pi * 30 * t) * (t > 0.5), smooth], axis=1)
    G_w = twin.wh(shapes)
    # (i) 200 synthetic whitened null residuals z ~ N(0, I) around one base Jacobian.
    J_w = twin.wh(jacobian(twin.record(0), twin.theta))
    Q = orthonormal_basis(J_w)
    dof = twin.wh.M - Q.shape[1]
    Z = np.random.default_rng(8).standard_normal((twin.wh.M, 200))
    p_syn = []
    for z in Z.T:
        zp = project_out(Q, z)
        for k in range(3):
            s = score_statistic(z, G_w[:, k], Q, zp @ zp / dof)
            p_syn.append(float(score_pvalue(s, 1, dof)))
    assert stats.kstest(p_syn, "uniform").pvalue > 0.01
    # (ii) 20 true-noise records, each with its own (noisy-v) Jacobian.
    p_true = []
    for seed in range(20):
        rec = twin.record(100 + seed)
        Qs = orthonormal_basis(twin.wh(jacobian(rec, twin.theta)))
        r_w = twin.wh(rec.residual(twin.theta))
        rp = project_out(Qs, r_w)
        s2 = rp @ rp / (twin.wh.M - Qs.shape[1])
        for k in range(3):
            s = score_statistic(r_w, G_w[:, k], Qs, s2)
            p_true.append(float(score_pvalue(s, 1, twin.wh.M - Qs.shape[1])))
    assert stats.kstest(p_true, "uniform").pvalue > 0.01


def test_family_false_alarm_rate_is_alpha(twin: Twin, plan) -> None:
    # 4000 synthetic null residuals: each map raises an alarm (some bin significant) at the
    # rate α = 0.01 it is calibrated for (measured 0.007–0.012 per map).
    scores = map_scores(plan, np.random.default_rng(21).standard_normal((twin.wh.M, 4000)))
    rates = {
        name: float(np.mean(s.max(axis=0) > np.quantile(plan.null_max[name], 0.99)))
        for name, s in scores.items()
    }
    assert set(rates) == set(VARIABLES)
    assert all(0.002 < r < 0.022 for r in rates.values()), rates
    assert 0.006 < np.mean(list(rates.values())) < 0.015
    # 20 true-noise records: family p-values uniform, few alarms, residuals white.
    fam, alarms, lb = [], 0, []
    for seed in range(20):
        rec = twin.record(200 + seed)
        r = rec.residual(twin.theta)
        rep = locate_whitened(plan, twin.wh(r), residual=r, alpha=0.01)
        fam += list(rep.family_p.values())
        alarms += len({b.variable for b in rep.significant})
        lb.append(rep.ljung_box_p)
        assert 0.85 < rep.sigma / SIGMA_X < 1.15
    assert stats.kstest(fam, "uniform").pvalue > 0.01
    assert alarms <= 4  # of 120 map-record pairs; expected 1.2
    assert sum(p < 0.01 for p in lb) <= 1
    assert stats.kstest(lb, "uniform").pvalue > 0.01


def _significant(report, variable: str):
    return [b for b in report.significant if b.variable == variable]


def test_force_in_a_time_interval_is_located(twin: Twin) -> None:
    t = twin.t[10:-10]
    lo, hi = 0.433, 0.517
    force = np.where((t >= lo) & (t <= hi), 40.0, 0.0)
    rec = twin.record(31, force)
    rep = locate(rec, twin.theta, whitener=twin.wh, n_mc=1000, seed=1)
    hits = _significant(rep, "time")
    assert hits and all(b.hi >= lo - 0.05 and b.lo <= hi + 0.05 for b in hits)
    best = max((b for b in rep.bins if b.variable == "time"), key=lambda b: b.score)
    assert best.hi >= lo and best.lo <= hi
    assert rep.family_p["time"] < 0.01
    assert rep.ljung_box_p < 1e-6  # a localised force is not white
    # and the null record of the same seed raises nothing in time
    assert not _significant(
        locate(twin.record(31), twin.theta, whitener=twin.wh, n_mc=1000, seed=1), "time"
    )


def test_friction_bump_in_a_position_band_is_located(twin: Twin) -> None:
    rec0 = twin.record(41)
    x = rec0.x
    lo, hi = np.quantile(x, [0.55, 0.62])
    force = 60.0 * ((x >= lo) & (x <= hi)) * np.sign(rec0.v)
    rep = locate(twin.record(41, force), twin.theta, whitener=twin.wh, n_mc=1000, seed=2)
    hits = _significant(rep, "position")
    assert hits and all(b.hi >= lo and b.lo <= hi for b in hits)


def test_sinusoid_is_found_at_its_frequency(twin: Twin) -> None:
    t = twin.t[10:-10]
    f0 = 37.3  # not a drive harmonic (multiples of 5 Hz)
    # 40 N: the residual noise near 37 Hz is ≈ 5 N of sinusoid amplitude per bin (m·a noise).
    rep = locate(
        twin.record(51, 40.0 * np.sin(2 * np.pi * f0 * t + 0.4)),
        twin.theta,
        whitener=twin.wh,
        n_mc=1000,
        seed=3,
    )
    hits = _significant(rep, "frequency")
    df = 1.0 / (t.size * DT)
    best = min(hits, key=lambda b: b.p_value)
    assert abs(0.5 * (best.lo + best.hi) - f0) <= 1.01 * df
    assert all(abs(0.5 * (b.lo + b.hi) - f0) <= 1.01 * df for b in hits)
    assert 16.0 < best.mean_residual < 48.0  # amplitude at the nearest bin [N], with leakage


def test_locate_is_reproducible_and_reports_cross_tests(twin: Twin) -> None:
    rec = twin.record(61)
    a = locate(rec, twin.theta, whitener=twin.wh, n_mc=200, seed=5)
    b = locate(rec, twin.theta, whitener=twin.wh, n_mc=200, seed=5)
    c = locate(rec, twin.theta, whitener=twin.wh, n_mc=200, seed=6)
    assert a.bins == b.bins and a.family_p == b.family_p and a.sigma == b.sigma
    assert a.ljung_box_p == b.ljung_box_p
    assert np.array_equal(list(a.crosscorr.values()), list(b.crosscorr.values()), equal_nan=True)
    assert a.family_p != c.family_p
    # v lies in the base span (Fv is free); a's own noise outweighs its signal; sgn v flips
    # at the reversals the whitener keeps: neither can be tested.
    assert a.crosscorr["v"] == 1.0
    assert np.isnan(a.crosscorr["a"]) and np.isnan(a.crosscorr["sgn v"])
    assert 0.0 <= a.crosscorr["x"] <= 1.0
    # No static friction at this theta: the default whitener excludes nothing.
    assert default_whitener(rec, twin.theta).dof == twin.wh.M


def test_user_errors_name_the_field(twin: Twin) -> None:
    rec = twin.record(0)
    with pytest.raises(FricjaxError, match="alpha"):
        locate(rec, twin.theta, whitener=twin.wh, n_mc=50, alpha=1.5)
    short = replace(twin.wh, n=500)
    with pytest.raises(FricjaxError, match="built for 500 samples, the problem has 980"):
        locate(rec, twin.theta, whitener=short, n_mc=50)
