"""The whitener: exact for the linearised residual noise, calibrated by Monte Carlo."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import fricjax  # noqa: F401  (float64 on)
from fricjax.data.preprocess import PreprocessSettings, derivatives, noise_gains
from fricjax.data.twin import PAPER_MODEL, PAPER_TRUTH
from fricjax.diagnose.evidence import near_rest_band
from fricjax.diagnose.whiten import (
    dc_scale,
    linear_damping,
    make_whitener,
    noise_operators,
    noise_response,
    stop_band_hz,
)
from fricjax.errors import FricjaxError
from fricjax.model.simulate import simulate
from fricjax.params import ParamSpec
from fricjax.problem import Problem

DT = 1e-3
MASS = 45.0
SIGMA_X = 2.4e-5  # the paper twin's displacement noise [m]
PAPER = PreprocessSettings(trim=10)  # configs/paper.toml


def bare_problem(n: int, settings: PreprocessSettings) -> Problem:
    """A problem whose arrays do not matter to the whitener (only t, mass, settings do)."""
    t = np.arange(n) * DT
    zero = np.zeros(n)
    spec = ParamSpec(
        tuple(p.fixed_at(MASS) if p.name == "mass" else p for p in PAPER_MODEL.parameters())
    )
    return Problem(PAPER_MODEL, spec, t, zero, zero, zero, zero, preprocess=settings)


def impulse_columns(
    settings: PreprocessSettings, n_full: int, column: Callable[[Any], np.ndarray]
) -> np.ndarray:
    """[n, n_full]: ``column(derivatives(e_j))`` for every unit impulse e_j of x."""
    t = np.arange(n_full) * DT
    return np.stack(
        [np.asarray(column(derivatives(t, e, settings))) for e in np.eye(n_full)], axis=1
    )


def operator(settings: PreprocessSettings, n_full: int, c: float) -> np.ndarray:
    """K = m·L_a + c·L_v [n, n_full], column by column from derivatives() on impulses."""
    return impulse_columns(settings, n_full, lambda d: MASS * d.a + c * d.v)


def test_noise_response_is_the_composed_filter() -> None:
    # a = L·D·(L·D·x) and v = L·D·x: in the interior H_a = H_v² exactly, H_v → i·2πf at
    # low frequency, and Parseval gives noise_gains' white-noise gains back.
    n = 4096
    h_v, h_a = noise_response(PreprocessSettings(), DT, n)
    f = np.fft.rfftfreq(n, DT)
    assert np.max(np.abs(h_a - h_v**2)) < 1e-9 * np.max(np.abs(h_a))
    low = (f > 0) & (f < 5.0)
    assert np.allclose(h_v[low] / (2j * np.pi * f[low]), 1.0, atol=2e-3)
    g_v, g_a = noise_gains(PreprocessSettings(), 1.0 / DT)
    weights = np.where((np.arange(f.size) == 0) | (np.arange(f.size) == n // 2), 1.0, 2.0)
    assert math.isclose(np.sqrt(np.sum(weights * np.abs(h_v) ** 2) / n), g_v, rel_tol=1e-9)
    assert math.isclose(np.sqrt(np.sum(weights * np.abs(h_a) ** 2) / n), g_a, rel_tol=1e-9)


def test_stop_band_cuts_the_savgol_side_lobes() -> None:
    # Butterworth default: a keeps < 10 % of its amplitude from 108 Hz on.
    assert 105.0 < stop_band_hz(PreprocessSettings(), DT) < 111.0
    sg = PreprocessSettings(method="savgol")
    f_stop = stop_band_hz(sg, DT)
    wh = make_whitener(bare_problem(800, sg), damping=1000.0)
    assert np.all(wh.freqs < f_stop)
    # The side lobe at 150 Hz passes 36 % of the peak response: above the noise floor, yet
    # dropped because it lies beyond the first stop-band crossing.
    _, h_a = noise_response(sg, DT, 800)
    k150 = round(150 * 800 * DT)
    assert abs(h_a[k150]) > 0.3 * np.abs(h_a).max()
    assert k150 not in wh.keep


@pytest.mark.parametrize(
    ("settings", "n", "c"),
    [
        (PAPER, 252, 0.0),
        (PAPER, 252, 3750.0),
        (PreprocessSettings(), 272, 3750.0),
    ],
)
def test_whitened_noise_covariance_is_exactly_identity(
    settings: PreprocessSettings, n: int, c: float
) -> None:
    wh = make_whitener(bare_problem(n, settings), damping=c)
    WK = wh(operator(settings, n + 2 * settings.trim, c))
    assert np.max(np.abs(WK @ WK.T - np.eye(wh.M))) < 1e-9
    # Without the edge correction the in-band Fourier coefficients alone are far off.
    Z0 = wh.base(operator(settings, n + 2 * settings.trim, c))
    assert np.max(np.diag(Z0 @ Z0.T)) > 10.0


def test_the_noise_model_has_the_residuals_own_sign_of_damping() -> None:
    # r = m·a − (drive − F_f): velocity noise enters r through +∂F_f/∂v. Build K column by
    # column from the MODEL's residual (viscous friction only, Fv = 3750 N·s/m, so r is
    # linear in (v, a)) on the derivatives of unit impulses: W must whiten it exactly. With
    # the damping's sign flipped (as the whitener had it until session 4) the covariance is
    # off by up to 0.043 (measured; the edge rows), while the interior is unchanged: the
    # circulant part only turns each bin's (Re, Im) pair, H becoming its conjugate.
    settings, n = PAPER, 252
    n_full = n + 2 * settings.trim
    base = bare_problem(n, settings)
    named = {**PAPER_TRUTH, "Fc": 0.0, "Fs": 0.0, "F0": 0.0, "Fv": 3750.0}
    named.update({k: 0.0 for k in named if k.startswith("Fp")})
    theta = jnp.asarray(base.theta(named))
    residual = jax.jit(
        lambda v, a: base.model.residual(base.spec.unflatten(theta), base.signals._replace(v=v), a)
    )
    K = impulse_columns(settings, n_full, lambda d: residual(jnp.asarray(d.v), jnp.asarray(d.a)))
    c = linear_damping(base, np.asarray(theta))
    assert abs(c - 3750.0) < 1e-9
    WK = make_whitener(base, damping=c)(K)
    assert np.max(np.abs(WK @ WK.T - np.eye(WK.shape[0]))) < 1e-9
    flipped = make_whitener(base, damping=-c)(K)
    assert np.max(np.abs(flipped @ flipped.T - np.eye(flipped.shape[0]))) > 0.02


@pytest.mark.parametrize(
    ("settings", "n", "start", "stop"),
    [
        (PAPER, 252, 176, 252),  # the held-out last 30 % of the paper twin (shorter than K)
        (PAPER, 252, 0, 176),  # its training part: record start, cut end
        (PreprocessSettings(), 600, 180, 600),  # 0.6 s, Butterworth without trim
        (PreprocessSettings(), 600, 150, 450),  # two cut ends
    ],
)
def test_a_part_of_a_record_is_whitened_by_the_rows_of_its_operator(
    settings: PreprocessSettings, n: int, start: int, stop: int
) -> None:
    # A held-out split keeps the preprocessing of the whole record: its noise is the rows
    # start … stop − 1 of the whole record's K, and at a cut end those rows reach x-samples
    # beyond the cut. The whitener of the part (Problem.window) whitens exactly them; the
    # whitener of a record that really ends there does not.
    c = 3750.0
    K = operator(settings, n + 2 * settings.trim, c)[start:stop]
    part = replace(bare_problem(stop - start, settings), window=(start, n))
    WK = make_whitener(part, damping=c)(K)
    assert np.max(np.abs(WK @ WK.T - np.eye(WK.shape[0]))) < 1e-9
    ended = make_whitener(bare_problem(stop - start, settings), damping=c)(K)
    assert np.max(np.abs(ended @ ended.T - np.eye(ended.shape[0]))) > 0.05


@pytest.mark.parametrize(
    ("settings", "n"), [(PAPER, 252), (PreprocessSettings(method="savgol", trim=10), 300)]
)
def test_noise_operators_are_the_preprocessing_on_impulses(
    settings: PreprocessSettings, n: int
) -> None:
    # L_v, L_a as sparse matrices: banded stationary kernel plus the measured end rows.
    L_v, L_a = noise_operators(settings, DT, n)
    n_full = n + 2 * settings.trim
    assert np.max(np.abs(L_v.toarray() - impulse_columns(settings, n_full, lambda d: d.v))) < 1e-9
    dense_a = impulse_columns(settings, n_full, lambda d: d.a)
    assert np.max(np.abs(L_a.toarray() - dense_a)) < 1e-9 * np.abs(dense_a).max()


def test_low_rank_correction_on_a_longer_record() -> None:
    # Savitzky–Golay, 1 s: the end rows are few (|R| = 96 < M/2), so the correction is a
    # low-rank update computed without the dense covariance, and it is still exact.
    settings = PreprocessSettings(method="savgol", trim=10)
    n = 980
    wh = make_whitener(bare_problem(n, settings), damping=1000.0)
    assert 0 < wh.s.size < wh.M / 2
    K = operator(settings, n + 20, 1000.0)
    WK = wh(K)
    assert np.max(np.abs(WK @ WK.T - np.eye(wh.M))) < 1e-9
    Z0 = wh.base(K)
    assert np.max(np.diag(Z0 @ Z0.T)) > 10.0


def test_monte_carlo_calibration_with_trim() -> None:
    # Noise-only residuals m·a_e + c·v_e of white x-noise through derivatives() (trim = 10,
    # configs/paper.toml): whitened entries are i.i.d. N(0, σ_x²).
    n_full, c, draws = 272, 3750.0, 600
    wh = make_whitener(bare_problem(n_full - 20, PAPER), damping=c)
    rng = np.random.default_rng(7)
    t = np.arange(n_full) * DT
    R = np.empty((n_full - 20, draws))
    for j in range(draws):
        d = derivatives(t, rng.normal(0.0, SIGMA_X, n_full), PAPER)
        R[:, j] = MASS * d.a + c * d.v
    Z = wh(R) / SIGMA_X
    ratio = float(np.mean(Z**2))
    assert abs(ratio - 1.0) < 4 * math.sqrt(2.0 / Z.size)  # measured 0.997 (M = 54)
    per_entry = np.mean(Z**2, axis=1)
    assert np.all(np.abs(per_entry - 1.0) < 5 * math.sqrt(2.0 / draws))
    corr = np.corrcoef(Z)
    off = np.abs(corr[~np.eye(wh.M, dtype=bool)])
    assert off.max() < 5.0 / math.sqrt(draws)
    # The uncorrected coefficients correlate up to 0.9 between neighbours.
    base = np.corrcoef(wh.base(R))
    assert np.abs(base[~np.eye(wh.M, dtype=bool)]).max() > 0.5


def test_apply_jax_matches_numpy_inside_jit() -> None:
    wh = make_whitener(bare_problem(252, PAPER), damping=3000.0, exclude=np.arange(252) % 50 == 0)
    y = np.random.default_rng(1).normal(size=(252, 3))
    out = jax.jit(lambda op, arr: op(arr))(wh.module, jnp.asarray(y))
    assert np.max(np.abs(np.asarray(out) - wh(y))) < 1e-12 * np.abs(wh(y)).max()
    assert np.allclose(np.asarray(wh.apply_jax(y[:, 0])), wh(y[:, 0]), rtol=0, atol=1e-18)


def test_whiteners_of_different_ranks_share_one_compiled_program() -> None:
    """The module pads N to the rank cap and U to M: records whose excluded samples differ
    (here 3 and 13 of them) give modules of one shape, and the same map as numpy."""
    pb = bare_problem(252, PAPER)
    rng = np.random.default_rng(2)
    y = rng.normal(size=252)
    ops, whs = [], []
    for every in (100, 20):
        wh = make_whitener(pb, damping=3000.0, exclude=np.arange(252) % every == 0, max_rank=40)
        whs.append(wh)
        ops.append(wh.module)
    assert whs[0].N.shape[1] != whs[1].N.shape[1]
    shapes = [[leaf.shape for leaf in jax.tree_util.tree_leaves(op)] for op in ops]
    assert shapes[0] == shapes[1]
    traces = []

    @jax.jit
    def apply(op: object, arr: jax.Array) -> jax.Array:
        traces.append(1)
        return op(arr)  # type: ignore[operator]

    for wh, op in zip(whs, ops, strict=True):
        out = np.asarray(apply(op, jnp.asarray(y)))
        assert np.max(np.abs(out - wh(y))) < 1e-12 * np.abs(wh(y)).max()
    assert len(traces) == 1


@pytest.fixture(scope="module")
def coulomb_records() -> tuple[Problem, list[Problem], np.ndarray]:
    """1 s paper twin (Coulomb + Stribeck): exact trajectory, then white x-noise through
    derivatives(); a is set so that the residual at the truth is exactly the noise's."""
    n = 1000
    t = np.arange(n) * DT
    p = {k: jnp.asarray(v) for k, v in PAPER_TRUTH.items()}
    traj = simulate(PAPER_MODEL, p, jnp.asarray(t), 0.0, 0.0, substeps=16)
    x, v, a = (np.asarray(arr) for arr in traj)
    spec = bare_problem(4, PAPER).spec.with_values(PAPER_TRUTH)
    keep = slice(10, n - 10)
    zero = np.zeros(n - 20)

    def build(vv: np.ndarray, aa: np.ndarray, xx: np.ndarray) -> Problem:
        return Problem(PAPER_MODEL, spec, t[keep], xx, vv, aa, zero, preprocess=PAPER)

    exact = build(v[keep], a[keep], x[keep])
    theta = exact.theta(PAPER_TRUTH)
    a_exact = a[keep] - exact.residual(theta) / MASS  # stuck samples: a from the model
    clean = derivatives(t, x, PAPER)
    records = []
    for seed in range(5):
        e = np.random.default_rng(100 + seed).normal(0.0, SIGMA_X, n)
        d = derivatives(t, x + e, PAPER)
        records.append(build(v[keep] + d.v - clean.v, a_exact + d.a - clean.a, x[keep] + e[keep]))
    return exact, records, theta


def test_velocity_reversals_break_the_linear_model_and_exclusion_restores_it(
    coulomb_records: tuple[Problem, list[Problem], np.ndarray],
) -> None:
    _, records, theta = coulomb_records
    c = linear_damping(records[0], theta)
    assert 2400.0 < c < 3750.0  # Fv minus the Stribeck drop's slope
    wh = make_whitener(records[0], damping=c)
    low = np.concatenate([wh.freqs < 10.0, (wh.freqs < 10.0)[wh.im_keep]])
    plain, excluded, dofs = [], [], []
    for pb in records:
        r = pb.residual(theta)
        z = wh(r) / SIGMA_X
        plain.append(np.mean(z[low] ** 2))
        mask = near_rest_band(pb, SIGMA_X).mask
        w_ex = make_whitener(pb, damping=c, exclude=mask)
        excluded.append(np.sum((w_ex(r) / SIGMA_X) ** 2))
        dofs.append(w_ex.dof)
    # Sign flips of the Coulomb term at reversals: hundreds of σ_x² per low bin.
    assert np.mean(plain) > 50.0
    # Samples with |v| < 4σ_v treated as missing: E‖W r‖² = σ_x²·dof again (measured 1.02).
    assert abs(np.sum(excluded) / np.sum(dofs) - 1.0) < 0.1
    assert min(dofs) < wh.M  # each excluded sample costs a degree of freedom


def test_a_stick_phase_costs_a_few_degrees_of_freedom_not_one_per_sample(
    coulomb_records: tuple[Problem, list[Problem], np.ndarray],
) -> None:
    # Spikes on neighbouring masked samples share a few low-frequency whitened directions:
    # projecting out only those where a sign flip (2·Fs) would keep more than SPIKE_TOL·σ_x
    # restores E‖W r‖² = σ_x²·dof as exact exclusion does, at fewer degrees of freedom
    # (measured: 0.975 at dof 172-177, where exact exclusion keeps 148-154).
    _, records, theta = coulomb_records
    c = linear_damping(records[0], theta)
    spike = 2.0 * PAPER_TRUTH["Fs"] / SIGMA_X
    rss, dofs, exact_dofs = [], [], []
    for pb in records:
        mask = near_rest_band(pb, SIGMA_X).mask
        r = pb.residual(theta)
        w_tr = make_whitener(pb, damping=c, exclude=mask, spike=spike)
        rss.append(np.sum((w_tr(r) / SIGMA_X) ** 2))
        dofs.append(w_tr.dof)
        exact_dofs.append(make_whitener(pb, damping=c, exclude=mask).dof)
    assert abs(np.sum(rss) / np.sum(dofs) - 1.0) < 0.15
    assert np.mean(dofs) > np.mean(exact_dofs) + 5
    # and a cap keeps the largest directions only
    capped = make_whitener(records[0], damping=c, exclude=mask, spike=spike, max_rank=3)
    assert capped.dof == capped.M - 3


def test_the_mean_of_the_residual_noise_has_the_scale_the_fit_pins_it_by() -> None:
    # The whitener drops DC (H(0) = 0); the base fit holds the residual's mean instead,
    # weighted by std(mean r_noise) = σ_x·dc_scale. Monte Carlo of m·a_e + c·v_e.
    n_full, c, draws = 272, 3750.0, 800
    wh = make_whitener(bare_problem(n_full - 20, PAPER), damping=c)
    assert wh.keep[0] > 0  # DC is not among the whitened bins
    rng = np.random.default_rng(11)
    t = np.arange(n_full) * DT
    means = np.empty(draws)
    for j in range(draws):
        d = derivatives(t, rng.normal(0.0, SIGMA_X, n_full), PAPER)
        means[j] = np.mean(MASS * d.a + c * d.v)
    ratio = float(np.std(means) / (SIGMA_X * dc_scale(wh, PAPER)))
    assert abs(ratio - 1.0) < 4 / math.sqrt(2 * draws)


def test_user_errors_name_the_field() -> None:
    pb = bare_problem(252, PAPER)
    with pytest.raises(FricjaxError, match="preprocess"):
        make_whitener(Problem(pb.model, pb.spec, pb.t, pb.x, pb.v, pb.a, pb.u))
    with pytest.raises(FricjaxError, match=r"exclude: must be a bool mask of shape \(252,\)"):
        make_whitener(pb, exclude=np.zeros(10, dtype=bool))
    with pytest.raises(FricjaxError, match="rel_floor"):
        make_whitener(pb, rel_floor=1.5)
    with pytest.raises(FricjaxError, match="has 10 samples, the whitener 252"):
        make_whitener(pb)(np.zeros(10))
