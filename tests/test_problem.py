"""Equation-error cost (seed eq. 11) over a preprocessed recording."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from fricjax.data.twin import PAPER_MODEL, PAPER_TRUTH
from fricjax.model.simulate import simulate
from fricjax.model.system import cost
from fricjax.model.term import Signals
from fricjax.params import ParamSpec
from fricjax.problem import Problem


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
