"""Catalogue of candidate physics terms: nesting at the null, force laws, grids, extension."""

from __future__ import annotations

import json
import math
import re
from dataclasses import replace
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import signal

from fricjax.config import Config, parse_config
from fricjax.data.preprocess import PreprocessSettings
from fricjax.data.twin import PAPER_TRUTH
from fricjax.diagnose.catalogue import (
    CATALOGUE,
    MASS_FRACTION,
    MAX_GRID,
    AsymmetricFriction,
    ExtraHarmonic,
    FrictionDrift,
    GaussianStribeck,
    Impact,
    PositionBump,
    PositionPeriodic,
    PreslidingHysteresis,
    QuadraticDrag,
    StribeckShape,
    bristle_state,
    candidate,
    cutoff_hz,
    force_scale,
    grid_size,
    is_stateful,
    near_drive_harmonic,
    ranges,
)
from fricjax.errors import FricjaxError
from fricjax.model.drive import HarmonicDrive
from fricjax.model.friction import CoulombViscous, StribeckFriction
from fricjax.model.system import Model
from fricjax.model.term import Signals
from fricjax.params import ParamSpec
from fricjax.problem import Problem

FORMATS = Path(__file__).resolve().parents[2] / "docs" / "formats.md"  # the conventions
EFFECTS = [c.effect for c in CATALOGUE]


def _signals(rng: np.random.Generator, n: int = 200) -> Signals:
    v = rng.normal(0.0, 0.5, n)
    v[::17] = 0.0  # sgn(0) = 0 must hold in every law
    return Signals(
        jnp.asarray(np.sort(rng.uniform(0.0, 2.0, n))),
        jnp.asarray(rng.uniform(-0.05, 0.05, n)),
        jnp.asarray(v),
        jnp.asarray(rng.normal(0.0, 1.0, n)),
    )


def _np(s: Signals) -> tuple[np.ndarray, ...]:
    return tuple(np.asarray(a) for a in s)


# -- coverage -----------------------------------------------------------------------------
def test_every_conventions_effect_is_catalogued_in_fixed_order() -> None:
    text = FORMATS.read_text()
    table = text[text.index("## Effect names") :]
    names = re.findall(r"^\| `([a-z_]+)` \|", table, flags=re.MULTILINE)
    assert "unexplained" in names and len(names) == 12
    assert EFFECTS == [n for n in names if n != "unexplained"]
    assert len(set(CATALOGUE)) == len(CATALOGUE)  # hashable and distinct
    for name in EFFECTS:
        assert candidate(name).effect == name
    with pytest.raises(FricjaxError, match=r"catalogue: effect: unknown effect 'unexplained'"):
        candidate("unexplained")


# -- nesting: null amplitudes give back the base model ------------------------------------
@pytest.mark.parametrize("effect", EFFECTS)
def test_null_amplitudes_reproduce_the_base_residual(effect: str, twin_problem: Problem) -> None:
    cand = candidate(effect)
    base = twin_problem
    assert cand.applicable(base.model, base.spec)
    ext = cand.extend_problem(base)
    r_base = np.asarray(base.residual_fn(jnp.asarray(base.spec.init)))
    lin = {p.name: p.null for p in cand.linear_params(base)}
    assert all(p.null == 0.0 for p in cand.linear_params(base)) or effect == "mass_error"
    grid = cand.grid(base)
    g = grid_size(grid)
    for k in sorted({0, g // 2, g - 1}):
        named = {**base.spec.as_dict(), **lin, **{q: float(a[k]) for q, a in grid.items()}}
        theta = ext.spec.flatten({q: named[q] for q in ext.spec.free_names})
        r_ext = np.asarray(ext.residual_fn(jnp.asarray(theta)))
        assert np.max(np.abs(r_ext - r_base)) <= 1e-9


# -- force laws against numpy -------------------------------------------------------------
def test_force_laws_match_numpy_at_random_parameters() -> None:
    rng = np.random.default_rng(7)
    s = _signals(rng)
    t, x, v, _ = _np(s)
    sg = np.sign(v)
    for _ in range(5):
        A, B, c1, c2 = rng.normal(0.0, 100.0, 4)
        vst, lam, f = rng.uniform(0.01, 1.0), rng.uniform(0.002, 0.05), rng.uniform(0.5, 50.0)
        x0, w = rng.uniform(-0.05, 0.05), rng.uniform(0.001, 0.03)
        t0, tw = rng.uniform(0.0, 2.0), rng.uniform(0.001, 0.1)
        tm, dur = rng.uniform(0.0, 2.0), rng.uniform(0.5, 3.0)
        cases = [
            (GaussianStribeck(), {"stribeck_A": A, "stribeck_vst": vst},
             A * np.exp(-((np.abs(v) / vst) ** 2)) * sg),
            (AsymmetricFriction(), {"asym_dFc": c1, "asym_dFv": c2},
             c1 * np.abs(sg) + c2 * np.abs(v)),
            (QuadraticDrag(), {"drag_Cd": c1}, c1 * v * np.abs(v)),
            (PositionBump(), {"bump_A": A, "bump_x0": x0, "bump_w": w},
             A * np.exp(-(((x - x0) / w) ** 2) / 2) * sg),
            (PositionPeriodic(), {"per_A": A, "per_B": B, "per_lambda": lam},
             A * np.sin(2 * np.pi * x / lam) + B * np.cos(2 * np.pi * x / lam)),
            (Impact(), {"impact_A": A, "impact_t0": t0, "impact_w": tw},
             A * np.exp(-(((t - t0) / tw) ** 2) / 2)),
            (ExtraHarmonic(), {"harm_A": A, "harm_B": B, "harm_f": f},
             A * np.sin(2 * np.pi * f * t) + B * np.cos(2 * np.pi * f * t)),
            (FrictionDrift(t_mid=tm, duration=dur), {"drift_beta": A},
             A * (t - tm) / dur * sg),
        ]  # fmt: skip
        for term, p, expect in cases:
            got = np.asarray(term.force({k: jnp.asarray(val) for k, val in p.items()}, s))
            np.testing.assert_allclose(got, expect, rtol=1e-12, atol=1e-9, err_msg=term.name)
            assert sorted(p) == sorted(term.param_names)
            assert not is_stateful(term)


def test_stribeck_shape_moves_the_base_exponent() -> None:
    rng = np.random.default_rng(3)
    s = _signals(rng)
    v = np.asarray(s.v)
    base = {"Fc": 30.0, "Fs": 190.0, "vs": 0.12, "delta": 1.0, "Fv": 3750.0}
    dd = 0.7
    p = {k: jnp.asarray(val) for k, val in {**base, "shape_ddelta": dd}.items()}
    rho = np.abs(v) / 0.12
    expect = 160.0 * (np.exp(-(rho ** (1.0 + dd))) - np.exp(-rho)) * np.sign(v)
    got = np.asarray(StribeckShape().force(p, s))
    np.testing.assert_allclose(got, expect, rtol=1e-12, atol=1e-12)
    # base + term is the Stribeck law with exponent δ + dδ
    total = StribeckFriction().force(p, s) + StribeckShape().force(p, s)
    law = StribeckFriction().force({**p, "delta": jnp.asarray(1.0 + dd)}, s)
    np.testing.assert_allclose(np.asarray(total), np.asarray(law), rtol=1e-12, atol=1e-9)
    # the local score column ∂F/∂dδ at 0, finite (zero) at rest
    col = jax.jacfwd(lambda d: StribeckShape().force({**p, "shape_ddelta": d}, s))(jnp.asarray(0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        analytic = np.where(rho > 0, -160.0 * rho * np.log(rho) * np.exp(-rho), 0.0)
    np.testing.assert_allclose(np.asarray(col), analytic * np.sign(v), rtol=1e-10, atol=1e-12)
    # the judge simulates every entry but the bristle state's
    assert [c.effect for c in CATALOGUE if not c.simulable] == ["presliding_hysteresis"]


def test_asymmetric_friction_gives_direction_dependent_levels() -> None:
    v = np.array([-0.8, -0.3, -1e-3, 0.0, 1e-3, 0.3, 0.8])
    s = Signals(*(jnp.asarray(a) for a in (np.zeros_like(v), np.zeros_like(v), v, v * 0)))
    Fc, Fv, dFc, dFv = 30.0, 400.0, 7.0, -55.0
    p = {k: jnp.asarray(val) for k, val in
         {"Fc": Fc, "Fv": Fv, "asym_dFc": dFc, "asym_dFv": dFv}.items()}  # fmt: skip
    model = Model((CoulombViscous(), AsymmetricFriction()))
    got = np.asarray(model.friction(p, s))
    fwd = (Fc + dFc) + (Fv + dFv) * v  # Fc+, Fv+
    bwd = -(Fc - dFc) + (Fv - dFv) * v  # Fc-, Fv-
    expect = np.where(v > 0, fwd, np.where(v < 0, bwd, 0.0))
    np.testing.assert_allclose(got, expect, rtol=1e-13, atol=1e-12)
    static = model.static(p, Signals(*(jnp.asarray(0.0),) * 4), jnp.asarray([1.0, -1.0]))
    np.testing.assert_allclose(np.asarray(static), [Fc + dFc, -(Fc - dFc)], rtol=1e-14)


# -- presliding hysteresis ----------------------------------------------------------------
def test_bristle_state_follows_the_exact_exponential_law() -> None:
    eps = 1e-4
    step = 2e-5
    n_fwd, n_back = 40, 80
    x = np.concatenate([np.arange(n_fwd) * step, (n_fwd - 1) * step - np.arange(1, n_back) * step])
    v = np.gradient(x)
    v[n_fwd - 1] = -1.0  # the reversal sample already moves backwards
    z = np.asarray(bristle_state(jnp.asarray(x), jnp.asarray(v), jnp.asarray(eps)))
    assert np.all(z[: n_fwd - 1] == 1.0)  # settled from the start
    back = np.arange(n_fwd - 1, x.size)
    travel = np.abs(x[back] - x[n_fwd - 1])
    # z − s = (z_rev − s)·exp(−travel/ε) with z_rev = +1, s = −1
    # (z + 1 cancels near z = −1: absolute error ~ ulp(1))
    np.testing.assert_allclose(z[back] + 1.0, 2.0 * np.exp(-travel / eps), rtol=1e-12, atol=1e-15)
    settled = travel >= 5 * eps
    assert settled.any() and np.all(np.abs(z[back][settled] + 1.0) <= 2 * math.exp(-5) + 1e-15)
    assert np.all(np.abs(z) <= 1.0)


def test_presliding_force_vanishes_in_steady_sliding_and_lags_after_reversal() -> None:
    term = PreslidingHysteresis()
    assert is_stateful(term)
    t = np.arange(300) * 1e-3
    p = {"presl_A": jnp.asarray(25.0), "presl_eps": jnp.asarray(2e-4)}
    x = 0.01 + 0.3 * t  # steady sliding
    s = Signals(*(jnp.asarray(a) for a in (t, x, np.full_like(t, 0.3), np.zeros_like(t))))
    assert np.all(np.asarray(term.force(p, s)) == 0.0)
    x2 = 0.05 * np.sin(2 * np.pi * 2.0 * t)  # reverses at t = 0.125 s
    v2 = 0.05 * 2 * np.pi * 2.0 * np.cos(2 * np.pi * 2.0 * t)
    s2 = Signals(*(jnp.asarray(a) for a in (t, x2, v2, np.zeros_like(t))))
    f = np.asarray(term.force(p, s2))
    k = int(np.argmax(v2 < 0))
    assert np.all(f[:k] == 0.0) and f[k] > 0  # still resisting the old direction
    assert abs(f[k + 40]) < 1e-6 * 25.0  # settled ~40 ms (≫ 5ε of travel) later
    with pytest.raises(FricjaxError, match="presliding_hysteresis: stateful term"):
        term.force(p, Signals(*(jnp.asarray(0.0),) * 4))


# -- grids, bounds, extension -------------------------------------------------------------
def test_grids_have_documented_sizes_and_lie_inside_bounds(twin_problem: Problem) -> None:
    r = ranges(twin_problem)
    f_lo = min(1 / r.duration, r.f_cut / 2)
    lam_hi = min(r.x_range, r.travel / 3)
    lam_lo = min(max(r.v_max / r.f_cut, 20 * r.dt * r.v_mean), lam_hi / 2)
    w_lo = max(2 * r.dt, 1 / (2 * math.pi * r.f_cut))
    sizes = {
        "stribeck": 32,
        "presliding_hysteresis": 24,
        "position_bump": 51 * 3,
        "impact": 3 * min(MAX_GRID // 3, math.ceil(r.duration / w_lo) + 1),
        "extra_harmonic": int(np.clip(math.floor((r.f_cut - f_lo) * 4 * r.duration) + 1, 16, 400)),
        "position_periodic": int(
            np.clip(math.ceil((1 / lam_lo - 1 / lam_hi) * 4 * r.travel) + 1, 16, 400)
        ),
    }
    for cand in CATALOGUE:
        grid = cand.grid(twin_problem)
        assert grid_size(grid) == sizes.get(cand.effect, 1), cand.effect
        assert grid_size(grid) <= MAX_GRID
        nl = {p.name: p for p in cand.nonlinear_params(twin_problem)}
        assert set(grid) == set(nl)
        for name, values in grid.items():
            assert values.shape == (grid_size(grid),)
            assert np.all((values >= nl[name].lower) & (values <= nl[name].upper)), name
            assert nl[name].lower <= nl[name].init <= nl[name].upper
        for p in cand.linear_params(twin_problem):
            assert p.lower <= p.null <= p.upper and p.init == p.null and p.free
    f_grid = candidate("extra_harmonic").grid(twin_problem)["harm_f"]
    np.testing.assert_allclose(np.diff(f_grid), 1 / (4 * r.duration), rtol=0.02)
    assert f_grid[-1] == pytest.approx(100.0)
    lam = candidate("position_periodic").grid(twin_problem)["per_lambda"]
    # twin: travel/3 = 16.7 mm caps λ, so the cut-off bound (8.4 mm) yields to λ_hi/2
    np.testing.assert_allclose([lam.min(), lam.max()], [lam_lo, lam_hi], rtol=1e-12)
    assert lam_lo == pytest.approx(lam_hi / 2) and lam.max() <= r.x_range
    vst = candidate("stribeck").grid(twin_problem)["stribeck_vst"]
    np.testing.assert_allclose([vst[0], vst[-1]], [0.01 * r.v_max, 0.5 * r.v_max], rtol=1e-12)


def test_amplitude_bounds_scale_with_the_measured_force(twin_problem: Problem) -> None:
    f_ref = force_scale(twin_problem)
    rms_ma = float(np.sqrt(np.mean((45.0 * twin_problem.a) ** 2)))
    assert f_ref >= rms_ma > 0
    # bounds are host metadata, usable while a caller traces (e.g. inside jax.jit)
    assert float(jax.jit(lambda one: one * force_scale(twin_problem))(1.0)) == f_ref
    assert candidate("stribeck").linear_params(twin_problem)[0].upper == pytest.approx(2 * f_ref)
    v_max = ranges(twin_problem).v_max
    cd = candidate("quadratic_drag").linear_params(twin_problem)[0]
    assert cd.upper == pytest.approx(2 * f_ref / v_max**2)


def test_extend_appends_linear_then_nonlinear_after_the_base(twin_problem: Problem) -> None:
    base = twin_problem
    cand = candidate("position_bump")
    model, spec = cand.extend(base.model, base.spec, base, {"bump_x0": 0.02, "bump_w": 1.0})
    n = len(base.spec.params)
    assert spec.params[:n] == base.spec.params
    assert spec.names[n:] == ("bump_A", "bump_x0", "bump_w")
    assert spec["bump_A"].init == 0.0 and spec["bump_A"].null == 0.0
    assert spec["bump_x0"].init == 0.02 and spec["bump_x0"].free
    assert spec["bump_w"].init == spec["bump_w"].upper  # clipped into its bounds
    assert model.terms[: len(base.model.terms)] == base.model.terms
    assert isinstance(model.terms[-1], PositionBump)
    assert spec.free_names[: base.spec.n_free] == base.spec.free_names
    assert not cand.applicable(model, spec)  # already added
    with pytest.raises(FricjaxError, match="catalogue: position_bump: not applicable"):
        cand.extend(model, spec, base)
    with pytest.raises(FricjaxError, match="unknown nonlinear parameter 'bump_z'"):
        cand.extend(base.model, base.spec, base, {"bump_z": 1.0})
    drift_model, _ = candidate("friction_drift").extend(base.model, base.spec, base)
    r = ranges(base)
    assert drift_model.terms[-1] == FrictionDrift(t_mid=(r.t0 + r.t1) / 2, duration=r.duration)


def test_mass_error_scales_the_noise_free_model_force(twin_problem: Problem) -> None:
    base = twin_problem
    cand = candidate("mass_error")
    model, spec = cand.extend(base.model, base.spec, base)
    assert spec.free_names == (*base.spec.free_names, "mass_eps")
    eps = spec["mass_eps"]
    assert eps.init == 0.0 and eps.null == 0.0
    assert (eps.lower, eps.upper) == pytest.approx((-MASS_FRACTION, MASS_FRACTION))
    assert not cand.applicable(model, spec)  # already added
    # ∂r/∂ε = F*_base = m·a − r: the regressor is the model force, not the noisy a
    ext = replace(base, model=model, spec=spec)
    theta = jnp.asarray(spec.init)
    jac = jax.jacfwd(ext.residual_fn)(theta)
    f_model = base.a * 45.0 - np.asarray(base.residual_fn(theta[:-1]))
    np.testing.assert_allclose(np.asarray(jac[:, -1]), f_model, rtol=1e-10, atol=1e-9)


def test_applicability_follows_the_base_model(twin_problem: Problem) -> None:
    drive_only = Model((HarmonicDrive(harmonics=2),))
    spec = ParamSpec(drive_only.parameters())
    needs_friction = {"stribeck", "stribeck_shape", "asymmetric_friction",
                      "presliding_hysteresis", "friction_drift"}  # fmt: skip
    for cand in CATALOGUE:
        assert cand.applicable(drive_only, spec) == (cand.effect not in needs_friction)
    cv = Model((CoulombViscous(),))
    assert not candidate("stribeck_shape").applicable(cv, ParamSpec(cv.parameters()))
    free_delta = ParamSpec(
        tuple(replace(p, free=True) if p.name == "delta" else p for p in twin_problem.spec.params)
    )
    assert not candidate("stribeck_shape").applicable(twin_problem.model, free_delta)
    assert candidate("stribeck_shape").applicable(twin_problem.model, twin_problem.spec)


def test_location_and_explanation_report_the_parameters(twin_problem: Problem) -> None:
    values = {
        "stribeck": {"stribeck_A": 120.0, "stribeck_vst": 0.05},
        "stribeck_shape": {"shape_ddelta": 0.5},
        "asymmetric_friction": {"asym_dFc": -8.0, "asym_dFv": 0.0},
        "quadratic_drag": {"drag_Cd": 300.0},
        "presliding_hysteresis": {"presl_A": 30.0, "presl_eps": 1e-4},
        "position_bump": {"bump_A": 50.0, "bump_x0": 0.02, "bump_w": 0.001},
        "position_periodic": {"per_A": 3.0, "per_B": 4.0, "per_lambda": 0.01},
        "impact": {"impact_A": 900.0, "impact_t0": 0.1, "impact_w": 0.002},
        "extra_harmonic": {"harm_A": 6.0, "harm_B": 8.0, "harm_f": 37.0},
        "friction_drift": {"drift_beta": 12.0},
        "mass_error": {"mass_eps": 1 - 45.0 / 49.5},
    }
    assert set(values) == set(EFFECTS)
    expect = {
        "stribeck": ("velocity_mps", [0.0, 0.1]),
        "asymmetric_friction": ("direction", "negative"),
        "position_bump": ("position_m", [0.018, 0.022]),
        "impact": ("time_s", [0.096, 0.104]),
        "extra_harmonic": ("frequency_hz", 37.0),
        "position_periodic": ("period_m", 0.01),
    }
    for effect, params in values.items():
        cand = candidate(effect)
        loc = cand.location(params, twin_problem)
        json.dumps(loc)  # plain JSON types
        if effect in expect:
            key, val = expect[effect]
            assert loc[key] == (pytest.approx(val) if not isinstance(val, str) else val)
        text = cand.explain(params, twin_problem)
        assert 0 < text.count(". ") + 1 <= 2 and re.search(r"\d", text), text
    assert "10 N" in candidate("extra_harmonic").explain(values["extra_harmonic"], twin_problem)
    assert "+10.0 %" in candidate("mass_error").explain(values["mass_error"], twin_problem)
    assert "37 Hz" in candidate("extra_harmonic").explain(values["extra_harmonic"], twin_problem)


def test_a_frequency_is_inseparable_from_a_drive_harmonic_within_one_over_t() -> None:
    # PAPER_TRUTH: ω = 2π·5 rad/s, harmonics 5..50 Hz
    clash = near_drive_harmonic(37.0, PAPER_TRUTH, 0.272)
    assert clash is not None and clash["harmonic"] == 7
    assert clash["separation_hz"] == pytest.approx(2.0)
    # two cycles of drift over 1 s: separable; 0.3 Hz over 2 s: less than one cycle
    assert near_drive_harmonic(37.0, PAPER_TRUTH, 1.0) is None
    assert near_drive_harmonic(35.3, PAPER_TRUTH, 2.0)["harmonic"] == 7
    # above the 10th harmonic (50 Hz) only the 10th is a neighbour; none without a drive
    assert near_drive_harmonic(53.0, PAPER_TRUTH, 0.272)["harmonic"] == 10
    assert near_drive_harmonic(60.0, PAPER_TRUTH, 0.272) is None
    no_drive = {k: v for k, v in PAPER_TRUTH.items() if k != "omega"}
    assert near_drive_harmonic(35.0, no_drive, 0.272) is None


def test_cutoff_of_savgol_is_its_half_power_frequency(twin_problem: Problem) -> None:
    assert cutoff_hz(twin_problem) == 100.0
    sg = replace(twin_problem, preprocess=PreprocessSettings(method="savgol"))
    fc = cutoff_hz(sg)
    _, h = signal.freqz(signal.savgol_coeffs(27, 7), worN=[fc - 0.3, fc + 0.3], fs=1000.0)
    assert abs(h[0]) >= 1 / math.sqrt(2) > abs(h[1])
    assert cutoff_hz(replace(twin_problem, preprocess=None)) == pytest.approx(500.0)


# -- registry -----------------------------------------------------------------------------
def test_a_config_can_name_catalogue_terms() -> None:
    raw = {
        "model": {
            "terms": ["coulomb_viscous", "measured_input", "quadratic_drag", "friction_drift"],
            "friction_drift": {"t_mid": 1.0, "duration": 2.0},
        },
        "params": {
            "Fc": {"unit": "N", "lower": 0.0, "upper": 50.0, "init": 20.0},
            "Fv": {"unit": "N*s/m", "lower": 0.0, "upper": 500.0, "init": 100.0},
            "gain": {"unit": "N/V", "value": 35.15},
            "offset": {"unit": "N", "lower": -10.0, "upper": 10.0, "init": 0.0},
            "drag_Cd": {"unit": "N*s^2/m^2", "lower": -100.0, "upper": 100.0, "init": 4.0},
            "drift_beta": {"unit": "N", "lower": -10.0, "upper": 10.0, "init": 2.0},
        },
    }
    config: Config = parse_config(raw, source="drag.toml")
    assert [t.name for t in config.model.terms][2:] == ["quadratic_drag", "friction_drift"]
    assert config.model.terms[3] == FrictionDrift(t_mid=1.0, duration=2.0)
    assert config.spec["drag_Cd"].null == 0.0
    v = np.array([-0.5, 0.0, 0.5])
    t = np.array([0.0, 1.0, 2.0])
    s = Signals(*(jnp.asarray(a) for a in (t, np.zeros(3), v, np.zeros(3))))
    got = np.asarray(config.model.friction(config.spec.as_dict(), s))
    expect = (
        20.0 * np.sign(v) + 100.0 * v + 4.0 * v * np.abs(v) + 2.0 * (t - 1.0) / 2.0 * np.sign(v)
    )
    np.testing.assert_allclose(got, expect, rtol=1e-13)
    bad = {**raw, "params": {**raw["params"], "drag_Cd": {"unit": "N", "value": 1.0}}}
    with pytest.raises(FricjaxError, match=r"drag.toml: \[params\].drag_Cd: wrong unit"):
        parse_config(bad, source="drag.toml")
