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

from fricjax.data.preprocess import PreprocessSettings
from fricjax.data.twin import PAPER_TRUTH
from fricjax.diagnose.catalogue import (
    CATALOGUE,
    MAX_GRID,
    candidate,
    cutoff_hz,
    force_scale,
    grid_size,
    near_drive_harmonic,
    ranges,
)
from fricjax.errors import FricjaxError
from fricjax.model.drive import HarmonicDrive
from fricjax.model.effects import (
    MASS_FRACTION,
    FrictionDrift,
    PositionBump,
)
from fricjax.model.friction import CoulombViscous
from fricjax.model.system import Model
from fricjax.params import ParamSpec
from fricjax.problem import Problem

FORMATS = Path(__file__).resolve().parents[2] / "docs" / "formats.md"  # the conventions
EFFECTS = [c.effect for c in CATALOGUE]


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
    # the judge simulates every entry but the bristle state's
    assert [c.effect for c in CATALOGUE if not c.simulable] == ["presliding_hysteresis"]


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
