"""The catalogue's force terms (:mod:`fricjax.model.effects`): each law against numpy, the
Dahl bristle state's exponential law, and a config naming them."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fricjax.config import Config, parse_config
from fricjax.errors import FricjaxError
from fricjax.model.effects import (
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
    is_stateful,
)
from fricjax.model.friction import CoulombViscous, StribeckFriction
from fricjax.model.system import Model
from fricjax.model.term import Signals


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
