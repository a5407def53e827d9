"""Equation-error cost (seed eq. 11) over a preprocessed recording."""

from __future__ import annotations

import dataclasses
from dataclasses import replace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fricjax.data.twin import PAPER_MODEL, PAPER_TRUTH
from fricjax.model.friction import StribeckFriction
from fricjax.model.simulate import simulate
from fricjax.model.system import Model, cost
from fricjax.model.term import Signals
from fricjax.params import ParamSpec
from fricjax.problem import Cost, EquationError, GridCost, Problem, build_problem


def _exact_problem(spec: ParamSpec) -> Problem:
    """Noise-free twin with exact v and a from the simulator (no differentiation bias)."""
    t = np.arange(272) / 1000.0
    p = {k: jnp.asarray(v) for k, v in PAPER_TRUTH.items()}
    traj = simulate(PAPER_MODEL, p, jnp.asarray(t), 0.0, 0.0, substeps=16)
    return Problem(
        PAPER_MODEL,
        spec,
        t,
        np.asarray(traj.x),
        np.asarray(traj.v),
        np.asarray(traj.a),
        np.zeros_like(t),
    )


def test_cost_is_zero_at_truth_and_positive_elsewhere(twin_problem: Problem) -> None:
    full = _exact_problem(twin_problem.spec)
    # Samples where the body is stuck (v == 0 exactly) are left out: there static friction
    # balances the drive, which an equation-error model with sgn(0) = 0 cannot express.
    moving = full.v != 0
    assert 0 < np.sum(~moving) < 0.2 * full.n
    pb = Problem(
        full.model,
        full.spec,
        full.t[moving],
        full.x[moving],
        full.v[moving],
        full.a[moving],
        full.u[moving],
    )
    truth = pb.theta(PAPER_TRUTH)
    force_scale = float(np.sum((PAPER_TRUTH["mass"] * pb.a) ** 2))
    assert pb.cost(truth) < 1e-18 * force_scale
    rng = np.random.default_rng(0)
    for _ in range(5):
        other = truth * (1 + 0.01 * rng.standard_normal(truth.size))
        assert pb.cost(other) > 1e-6 * force_scale


def test_vmap_over_parameters_equals_loop(twin_problem: Problem) -> None:
    rng = np.random.default_rng(1)
    spec = twin_problem.spec
    thetas = rng.uniform(spec.lower, spec.upper, (16, spec.n_free))
    batched = np.asarray(jax.vmap(twin_problem.cost_fn)(jnp.asarray(thetas)))
    looped = np.array([twin_problem.cost(th) for th in thetas])
    np.testing.assert_allclose(batched, looped, rtol=1e-12)


def test_vmap_over_recordings(twin_problem: Problem) -> None:
    """The residual is a pure function of the signals too: stack two records, vmap."""
    pb = twin_problem
    named = pb.spec.unflatten(jnp.asarray(pb.theta(PAPER_TRUTH)))
    sig = pb.signals
    sigs = Signals(*(jnp.stack([s, s[::-1]]) for s in sig))
    acc = jnp.stack([jnp.asarray(pb.a), jnp.asarray(pb.a[::-1])])
    costs = jax.vmap(lambda s, a: cost(pb.model.residual(named, s, a)))(sigs, acc)
    one = cost(pb.model.residual(named, Signals(*(s[::-1] for s in sig)), acc[1]))
    ref = float(pb.cost_fn(jnp.asarray(pb.theta(PAPER_TRUTH))))
    np.testing.assert_allclose(float(costs[0]), ref, rtol=1e-13)
    np.testing.assert_allclose(float(costs[1]), float(one), rtol=1e-13)


def test_cost_is_differentiable(twin_problem: Problem) -> None:
    theta = jnp.asarray(twin_problem.theta(PAPER_TRUTH))
    g = jax.grad(twin_problem.cost_fn)(theta)
    assert np.all(np.isfinite(np.asarray(g)))
    # directional derivative matches a central difference
    d = jnp.asarray(np.random.default_rng(2).standard_normal(theta.size)) * 1e-5
    fd = (twin_problem.cost(theta + d) - twin_problem.cost(theta - d)) / 2
    assert abs(float(g @ d) - fd) < 1e-5 * abs(fd) + 1e-5  # + roundoff of a 1e6 N² cost


# -- the time grid (angle addition in the harmonic drive, GridCost) ------------------------


class _StatefulStribeck(StribeckFriction):
    """The seed friction declared stateful: the problem must keep the samples in order."""

    stateful = True


def _plain_cost(pb: Problem) -> Cost:
    """The cost of git HEAD before the grid: sin/cos per sample, samples in order."""
    res = pb.residual_fn
    return Cost(
        EquationError(
            pb.model, res.spec, res.t, res.x, res.v, res.u, res.a, kernel=res.kernel, q=res.q
        )
    )


def _box(pb: Problem, c: int, seed: int) -> jnp.ndarray:
    lo, hi = pb.spec.lower, pb.spec.upper
    return jnp.asarray(lo + np.random.default_rng(seed).random((c, lo.size)) * (hi - lo))


@pytest.fixture(scope="module")
def box256(twin_problem: Problem) -> jnp.ndarray:
    return _box(twin_problem, 256, 11)


def test_twin_cost_on_the_grid_equals_the_plain_cost(twin_problem: Problem, box256) -> None:
    pb = twin_problem
    assert pb.grid is not None and pb.residual_fn.grid is not None
    fn = pb.cost_fn
    assert isinstance(fn, GridCost)
    j, r = pb.grid.outer.shape[0], pb.grid.inner.shape[0]
    assert (j, r) == (15, 16) and fn.t.shape == (j, r)
    assert int(np.sum(np.asarray(fn.keep))) == pb.n
    plain = _plain_cost(pb)
    old = np.asarray(jax.jit(jax.vmap(plain))(box256))
    new = np.asarray(jax.jit(jax.vmap(fn))(box256))
    assert np.max(np.abs(new / old - 1.0)) <= 1e-12  # measured 1.6e-15
    # the residual in sample order (grid path of the drive, for the refiner)
    r_new = np.asarray(jax.jit(jax.vmap(pb.residual_fn))(box256))
    r_old = np.asarray(jax.jit(jax.vmap(plain.residual))(box256))
    assert np.max(np.abs(r_new - r_old)) <= 1e-12 * np.max(np.abs(r_old))
    # gradients (the refiner and the search's derivative checks use them)
    theta = jnp.asarray(pb.theta(PAPER_TRUTH))
    g_new, g_old = jax.grad(fn)(theta), jax.grad(plain)(theta)
    np.testing.assert_allclose(np.asarray(g_new), np.asarray(g_old), rtol=1e-9, atol=1e-9)


def test_trimmed_and_decimated_problems_keep_the_grid(twin_problem: Problem) -> None:
    pb0 = twin_problem
    # trimmed further (a uniform slice stays uniform; 224 samples: a partly filled grid)
    cut = slice(5, -3)
    trimmed = replace(pb0, **{k: getattr(pb0, k)[cut] for k in ("t", "x", "v", "a", "u")})
    # a 1 s record with its residual decimated by 2 (the filter needs > 411 samples)
    t = 0.013 + np.arange(1000) / 1000.0
    rng = np.random.default_rng(14)
    v = 0.3 * np.sin(31.4 * t) + 0.01 * rng.standard_normal(t.size)
    decimated = Problem(
        pb0.model,
        pb0.spec,
        t,
        np.cumsum(v) / 1000.0,
        v,
        np.gradient(v, t),
        np.zeros_like(t),
        preprocess=dataclasses.replace(pb0.preprocess, decimate=2),
    )
    x = _box(pb0, 64, 12)
    for pb, kind in ((trimmed, GridCost), (decimated, Cost)):
        assert pb.grid is not None and pb.residual_fn.grid is not None
        assert isinstance(pb.cost_fn, kind)
        new = np.asarray(jax.jit(jax.vmap(pb.cost_fn))(x))
        old = np.asarray(jax.jit(jax.vmap(_plain_cost(pb)))(x))
        assert np.max(np.abs(new / old - 1.0)) <= 1e-12
    assert decimated.residual_fn(x[0]).shape == (decimated.n_residual,) == (500,)


def test_a_stateful_term_keeps_the_samples_in_order(twin_problem: Problem) -> None:
    pb = replace(twin_problem, model=Model((twin_problem.model.terms[0], _StatefulStribeck())))
    assert pb.grid is not None
    assert isinstance(pb.cost_fn, Cost) and pb.cost_fn.residual.grid is not None
    x = _box(pb, 16, 15)
    new = np.asarray(jax.jit(jax.vmap(pb.cost_fn))(x))
    old = np.asarray(jax.jit(jax.vmap(_plain_cost(pb)))(x))
    assert np.max(np.abs(new / old - 1.0)) <= 1e-12


def test_non_uniform_times_fall_back_to_the_plain_cost(twin_problem: Problem) -> None:
    pb0 = twin_problem
    keep = np.ones(pb0.n, bool)
    keep[[40, 41, 150]] = False  # samples dropped: t is no longer a grid
    pb = replace(pb0, **{k: getattr(pb0, k)[keep] for k in ("t", "x", "v", "a", "u")})
    assert pb.grid is None and pb.residual_fn.grid is None
    assert isinstance(pb.cost_fn, Cost)
    x = _box(pb0, 8, 13)
    np.testing.assert_array_equal(
        np.asarray(jax.vmap(pb.cost_fn)(x)), np.asarray(jax.vmap(_plain_cost(pb))(x))
    )


def test_measured_force_reaches_the_drive_filtered_like_m_a() -> None:
    """``[model.measured_input] signal = "F"``: the model's drive reads /F [N], through the
    same filter as m·a; a recording without /F is refused naming it."""
    from fricjax.config import parse_config
    from fricjax.data.preprocess import PreprocessSettings, filter_like_acceleration
    from fricjax.data.recording import Recording
    from fricjax.errors import FricjaxError

    t = np.arange(500) / 1000.0
    F = 10.0 * np.sin(2 * np.pi * 3.0 * t) + np.sin(2 * np.pi * 150.0 * t)  # 150 Hz: cut
    rec = Recording(t=t, x=0.01 * np.sin(2 * np.pi * 3.0 * t), F=F, u=0 * t, mass=2.0)
    raw = {
        "model": {
            "terms": ["measured_input", "coulomb_viscous"],
            "measured_input": {"signal": "F"},
        },
        "params": {
            "gain": {"unit": "N/N", "value": 1.0},
            "offset": {"unit": "N", "lower": -1.0, "upper": 1.0},
            "Fc": {"unit": "N", "lower": 0.0, "upper": 5.0},
            "Fv": {"unit": "N*s/m", "lower": 0.0, "upper": 5.0},
        },
    }
    problem = build_problem(rec, parse_config(raw))
    expected = filter_like_acceleration(F, 1e-3, PreprocessSettings())
    np.testing.assert_allclose(problem.u, expected, rtol=0, atol=1e-12)
    assert np.max(np.abs(problem.u - F)) > 0.5  # the 150 Hz line is gone, as from m·a
    with pytest.raises(FricjaxError, match=r"/F: missing .*recorded force /F"):
        build_problem(Recording(t=t, x=rec.x, u=F, mass=2.0), parse_config(raw))
    raw["model"]["measured_input"] = {"signal": "G"}
    with pytest.raises(FricjaxError, match="signal must be one of u, F"):
        parse_config(raw)


def test_joined_recordings_keep_their_clocks_and_refuse_another_rate(twin_problem: Problem) -> None:
    """``joined``: the samples end to end, each recording on its own clock, the joins where
    each later one starts; recordings of another sample step or another model are refused
    in one line."""
    from fricjax.errors import FricjaxError
    from fricjax.problem import joined

    pb = twin_problem
    half = replace(pb, t=pb.t[:100], x=pb.x[:100], v=pb.v[:100], a=pb.a[:100], u=pb.u[:100])
    both = joined([pb, half])
    dt = float(pb.t[1] - pb.t[0])
    assert both.n == pb.n + 100 and both.joins == (pb.n,)
    np.testing.assert_array_equal(both.t, np.concatenate([pb.t, pb.t[:100]]))
    assert both.dt == pytest.approx(dt, rel=1e-12)
    np.testing.assert_array_equal(both.x, np.concatenate([pb.x, pb.x[:100]]))
    np.testing.assert_array_equal(both.drive_input, np.concatenate([pb.u, pb.u[:100]]))
    slow = replace(half, t=pb.t[0] + 2 * (half.t - pb.t[0]))
    for other, needle in ((slow, "sample step"), (replace(half, spec=ParamSpec(())), "model")):
        with pytest.raises(FricjaxError, match=needle) as err:
            joined([pb, other])
        assert "\n" not in str(err.value)
