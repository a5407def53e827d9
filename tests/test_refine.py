"""Facts about the Levenberg–Marquardt polish, the Gauss–Newton uncertainty and the census."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
from jaxtyping import Array, Float

import fricjax  # noqa: F401  (float64 on)
from fricjax.errors import FricjaxError
from fricjax.refine import (
    RefineSettings,
    cluster_minima,
    compile_refine,
    refine,
    refine_many,
    uncertainty,
    uncertainty_at,
    value_and_jacobian,
)

# Exponential decay + sinusoid, y(t) = A e^{−k t} + B sin(ω t + φ), noise-free.
T = jnp.linspace(0.0, 5.0, 200)
TRUE = jnp.array([2.0, 0.7, 0.5, 3.0, 0.3])
LO = jnp.array([0.0, 0.0, 0.0, 2.0, -1.0])
HI = jnp.array([5.0, 3.0, 2.0, 4.0, 1.0])


def _model(p: Float[Array, " 5"]) -> Float[Array, " n"]:
    return p[0] * jnp.exp(-p[1] * T) + p[2] * jnp.sin(p[3] * T + p[4])


Y = _model(TRUE)


def decay_sine_residual(p: Float[Array, " 5"]) -> Float[Array, " n"]:
    return _model(p) - Y


# Decay A e^{−k t} fitted to data with k = 0.7 while the box demands k ≥ 1: the
# constrained optimum has k on its lower bound.
T2 = jnp.linspace(0.0, 3.0, 50)
Y2 = 2.0 * jnp.exp(-0.7 * T2)
LO2 = jnp.array([0.0, 1.0])
HI2 = jnp.array([5.0, 3.0])


def bounded_residual(p: Float[Array, " 2"]) -> Float[Array, " n"]:
    return p[0] * jnp.exp(-p[1] * T2) - Y2


@pytest.fixture(scope="module")
def starts() -> np.ndarray:
    """Starts near the truth, far from it, and on the corners of the box (bad starts)."""
    rng = np.random.default_rng(0)
    u = rng.uniform(size=(4, 5))
    random = np.asarray(LO) + u * np.asarray(HI - LO)
    near = np.asarray(TRUE) * np.array([0.75, 1.4, 1.6, 0.97, 0.0]) + np.array(
        [0.0, 0.0, 0.0, 0.0, 0.1]
    )
    return np.vstack([near, random, np.asarray(LO), np.asarray(HI)])


@pytest.fixture(scope="module")
def many(starts: np.ndarray):
    return refine_many(decay_sine_residual, starts, LO, HI, RefineSettings())


def test_lm_recovers_known_parameters_to_1e8() -> None:
    x0 = jnp.array([1.5, 1.0, 0.8, 2.9, 0.0])
    r = refine(decay_sine_residual, x0, LO, HI)
    assert bool(r.success)
    np.testing.assert_allclose(np.asarray(r.x), np.asarray(TRUE), rtol=1e-8)
    assert float(r.cost_after) < 1e-20 < float(r.cost_before)
    assert 0 < int(r.n_steps) < RefineSettings().max_steps


def test_bounded_optimum_ends_on_the_bound_inside_the_box() -> None:
    for x0 in ([1.0, 2.0], [5.0, 3.0], [1.0, 1.0]):  # interior, upper corner, on the bound
        r = refine(bounded_residual, jnp.array(x0), LO2, HI2)
        x = np.asarray(r.x)
        assert np.all(x >= np.asarray(LO2)) and np.all(x <= np.asarray(HI2))
        assert bool(r.success)
        assert x[1] - 1.0 < 1e-9
        # With k = 1 fixed the best A solves the 1-D linear least squares exactly.
        e = np.exp(-np.asarray(T2))
        a_star = float(e @ np.asarray(Y2) / (e @ e))
        assert abs(x[0] - a_star) < 1e-6 * a_star


def test_sigmoid_transform_stays_inside_and_approaches_the_bound() -> None:
    r = refine(
        bounded_residual, jnp.array([1.0, 2.0]), LO2, HI2, RefineSettings(transform="sigmoid")
    )
    x = np.asarray(r.x)
    assert 1.0 < x[1] < 1.0 + 1e-3
    assert float(r.cost_after) < float(r.cost_before)


def test_cost_never_increases_even_from_bad_starts(many, starts: np.ndarray) -> None:
    before = np.asarray(many.cost_before)
    after = np.asarray(many.cost_after)
    assert np.all(after <= before)
    x = np.asarray(many.x)
    assert np.all((x >= np.asarray(LO)) & (x <= np.asarray(HI)))
    # cost_before is the cost of the given start, not of its transformed copy.
    direct = np.array([float(jnp.sum(decay_sine_residual(jnp.asarray(s)) ** 2)) for s in starts])
    np.testing.assert_allclose(before, direct, rtol=1e-14)
    # A single LM step cannot converge, and still may not make things worse.
    r1 = refine(decay_sine_residual, jnp.asarray(starts[-1]), LO, HI, RefineSettings(max_steps=1))
    assert not bool(r1.success)
    assert float(r1.cost_after) <= float(r1.cost_before)


def test_nan_region_never_returns_a_nan_point() -> None:
    def res(x: Float[Array, " 1"]) -> Float[Array, " 1"]:
        # Undefined (NaN) beyond x = 0.5, while the unconstrained optimum is at 2.
        return jnp.where(x[0] > 0.5, jnp.nan, 1.0) * (x - 2.0)

    r = refine(res, jnp.array([0.3]), jnp.array([0.0]), jnp.array([1.0]))
    assert np.all(np.isfinite(np.asarray(r.x))) and np.isfinite(float(r.cost_after))
    assert float(r.cost_after) <= float(r.cost_before) == pytest.approx(1.7**2, rel=1e-14)


def test_refine_many_equals_refine_one_by_one(many, starts: np.ndarray) -> None:
    assert np.asarray(many.x).shape == starts.shape
    for k, s in enumerate(starts):
        r = refine(decay_sine_residual, jnp.asarray(s), LO, HI)
        np.testing.assert_allclose(np.asarray(many.x[k]), np.asarray(r.x), rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(float(many.cost_after[k]), float(r.cost_after), atol=1e-10)
        assert bool(many.success[k]) == bool(r.success)


def test_repeated_calls_reuse_the_compilation() -> None:
    traces = []

    def res(p: Float[Array, " 2"]) -> Float[Array, " n"]:
        traces.append(1)  # runs only while jax traces the function
        return bounded_residual(p)

    refine(res, jnp.array([1.0, 2.0]), LO2, HI2)
    n_first = len(traces)
    r = refine(res, jnp.array([2.0, 1.5]), LO2, HI2)
    assert n_first > 0 and len(traces) == n_first
    assert float(r.cost_after) < float(r.cost_before)


def test_refine_is_bit_reproducible() -> None:
    x0 = jnp.array([1.5, 1.0, 0.8, 2.9, 0.0])
    a = refine(decay_sine_residual, x0, LO, HI)
    b = refine(decay_sine_residual, x0, LO, HI)
    assert np.array_equal(np.asarray(a.x), np.asarray(b.x))


def test_refine_rejects_start_outside_box_and_bad_bounds() -> None:
    with pytest.raises(FricjaxError, match=r"x0: value 6\.0 at index 0 is not inside"):
        refine(decay_sine_residual, jnp.array([6.0, 1.0, 0.5, 3.0, 0.0]), LO, HI)
    with pytest.raises(FricjaxError, match="lower/upper: need finite lower < upper, index 1"):
        refine(bounded_residual, jnp.array([1.0, 1.0]), LO2, jnp.array([5.0, 1.0]))
    with pytest.raises(FricjaxError, match="x0s: shape"):
        refine_many(bounded_residual, jnp.ones((3, 3)), LO2, HI2)
    with pytest.raises(FricjaxError, match="refine: settings: transform: must be one of"):
        refine(bounded_residual, jnp.array([1.0, 1.5]), LO2, HI2, RefineSettings(transform="tan"))
    with pytest.raises(FricjaxError, match="residual_fn: must return a 1-D residual vector"):
        refine(lambda p: jnp.outer(p, p), jnp.array([1.0, 1.5]), LO2, HI2)


def test_settings_from_dict_validates_keys_and_values() -> None:
    s = RefineSettings.from_dict({"rtol": 1e-8, "max_steps": 50, "transform": "sigmoid"}, "a.toml")
    assert s == RefineSettings(rtol=1e-8, max_steps=50, transform="sigmoid")
    with pytest.raises(FricjaxError, match=r"^a\.toml: rtl: unknown key; expected one of rtol"):
        RefineSettings.from_dict({"rtl": 1e-8}, "a.toml")
    with pytest.raises(FricjaxError, match=r"a\.toml: transform: must be one of sine"):
        RefineSettings.from_dict({"transform": "tanh"}, "a.toml")
    with pytest.raises(FricjaxError, match=r"a\.toml: max_steps: must be an integer ≥ 1"):
        RefineSettings.from_dict({"max_steps": 0}, "a.toml")
    with pytest.raises(FricjaxError, match=r"a\.toml: atol: must be a finite number > 0"):
        RefineSettings.from_dict({"atol": -1.0}, "a.toml")
    with pytest.raises(FricjaxError, match=r"a\.toml: eps_bound: must be < 0\.5"):
        RefineSettings.from_dict({"eps_bound": 0.7}, "a.toml")


# --------------------------------------------------------------------------------------
# Uncertainty
# --------------------------------------------------------------------------------------


def _linear_problem(a: np.ndarray, seed: int = 1):
    rng = np.random.default_rng(seed)
    theta = np.arange(1.0, a.shape[1] + 1.0)
    y = a @ theta + 0.1 * rng.standard_normal(a.shape[0])
    aj, yj = jnp.asarray(a), jnp.asarray(y)

    def res(p: Float[Array, " d"]) -> Float[Array, " n"]:
        return aj @ p - yj

    x_hat = np.linalg.lstsq(a, y, rcond=None)[0]
    return res, x_hat, y


def _design(n: int = 80, seed: int = 2) -> np.ndarray:
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0, n)
    # Columns of very different scales, to exercise the column scaling.
    return np.column_stack([np.ones(n), 1e3 * t, 1e-2 * t**2, rng.standard_normal(n)])


def test_linear_model_std_matches_ols_formula() -> None:
    a = _design()
    res, x_hat, y = _linear_problem(a)
    n, d = a.shape
    box = np.full(d, 1e3)
    u = uncertainty(res, x_hat, -box, box)
    rss = float(np.sum((a @ x_hat - y) ** 2))
    sigma2 = rss / (n - d)
    std_ols = np.sqrt(sigma2 * np.diag(np.linalg.inv(a.T @ a)))
    assert u.sigma2 == pytest.approx(sigma2, rel=1e-12)
    np.testing.assert_allclose(u.std, std_ols, rtol=1e-6)
    np.testing.assert_allclose(u.rel_std, std_ols / np.abs(x_hat), rtol=1e-6)
    cov = sigma2 * np.linalg.inv(a.T @ a)
    np.testing.assert_allclose(u.corr, cov / np.outer(std_ols, std_ols), atol=1e-8)
    scaled = a / np.linalg.norm(a, axis=0)
    assert u.cond == pytest.approx(np.linalg.cond(scaled.T @ scaled), rel=1e-6)
    assert not u.on_bound.any()
    # Only the t² column (scale 1e-2) leaves its coefficient poorly known.
    rel = std_ols / np.abs(x_hat)
    assert rel[2] > 1.0 and np.all(np.delete(rel, 2) < 1.0)
    assert u.flags == [[], [], [f"weakly determined (rel. σ = {rel[2]:.3g} > 1)"], []]


def test_duplicated_column_is_flagged_and_finite_where_determined() -> None:
    base = _design()[:, :2]
    a = np.column_stack([base, base[:, 1]])  # p1 and p2 enter only as p1 + p2
    res, x_hat, y = _linear_problem(a)
    n = a.shape[0]
    box = np.full(3, 1e4)
    u = uncertainty(res, x_hat, -box, box, names=["F0", "Fc", "Fv"])
    assert np.isinf(u.std[1]) and np.isinf(u.std[2]) and np.isinf(u.cond)
    assert u.corr[1, 2] == pytest.approx(-1.0, abs=1e-9)
    assert u.corr[0, 1] == 0.0
    assert "correlated with Fv (ρ = -1.000)" in u.flags[1]
    assert "correlated with Fc (ρ = -1.000)" in u.flags[2]
    assert any(f.startswith("not determined") for f in u.flags[1])
    # p0 stays estimable: its std is the OLS value of the model without the duplicate, with
    # the residual variance counted over n − 3 degrees of freedom.
    sigma2 = float(np.sum((a @ x_hat - y) ** 2)) / (n - 3)
    std0 = np.sqrt(sigma2 * np.linalg.inv(base.T @ base)[0, 0])
    assert u.std[0] == pytest.approx(std0, rel=1e-6)
    assert u.flags[0] == []


def test_nearly_collinear_parameters_are_weakly_determined() -> None:
    base = _design()[:, :2]
    rng = np.random.default_rng(5)
    a = np.column_stack([base, base[:, 1] * (1.0 + 1e-6 * rng.standard_normal(base.shape[0]))])
    res, x_hat, _ = _linear_problem(a)
    box = np.full(3, 1e6)
    u = uncertainty(res, x_hat, -box, box)
    assert np.all(np.isfinite(u.std)) and 1e10 < u.cond < np.inf
    assert abs(u.corr[1, 2]) > 0.99
    assert any(f.startswith("weakly determined (rel. σ = ") for f in u.flags[1])
    assert any(f.startswith("correlated with p2 (ρ = -") for f in u.flags[1])


def test_parameter_on_bound_is_flagged() -> None:
    r = refine(bounded_residual, jnp.array([1.0, 2.0]), LO2, HI2)
    u = uncertainty(bounded_residual, r.x, LO2, HI2, names=["A", "k"])
    assert list(u.on_bound) == [False, True]
    assert "on bound (lower)" in u.flags[1]
    assert not any(f.startswith("on bound") for f in u.flags[0])


def test_uncertainty_refuses_too_few_residuals() -> None:
    with pytest.raises(FricjaxError, match="residual_fn: 2 residuals for 2 parameters"):
        uncertainty(lambda p: p - 1.0, np.zeros(2), -np.ones(2), np.ones(2))
    with pytest.raises(FricjaxError, match="names: 1 names for 2 parameters"):
        uncertainty(bounded_residual, np.array([1.0, 1.5]), LO2, HI2, names=["A"])


def test_fast_compile_polish_reaches_the_same_optimum() -> None:
    # XLA's backend optimisation off and its fusion emitters off: the same LM iterations
    # to round-off, so the same optimum to 1e-8 and no worse than the start
    x0 = jnp.array([1.5, 1.0, 0.8, 2.9, 0.0])
    fast = refine(decay_sine_residual, x0, LO, HI, fast_compile=True)
    assert bool(fast.success) and float(fast.cost_after) < 1e-20 < float(fast.cost_before)
    np.testing.assert_allclose(np.asarray(fast.x), np.asarray(TRUE), rtol=1e-8)
    again = refine(decay_sine_residual, x0, LO, HI, fast_compile=True)
    np.testing.assert_array_equal(np.asarray(again.x), np.asarray(fast.x))


def test_polish_compiled_ahead_in_a_thread_is_the_same_polish() -> None:
    # compile_refine's program (compiled in a worker thread, as a cold identify does while
    # the search runs) gives the call-time compiled polish bit for bit, from another start
    from concurrent.futures import ThreadPoolExecutor

    x0 = jnp.array([1.5, 1.0, 0.8, 2.9, 0.0])
    with ThreadPoolExecutor(max_workers=1) as pool:
        program = pool.submit(
            compile_refine, decay_sine_residual, np.asarray(LO), LO, HI, fast_compile=True
        ).result()
    ahead = refine(decay_sine_residual, x0, LO, HI, program=program)
    now = refine(decay_sine_residual, x0, LO, HI, fast_compile=True)
    np.testing.assert_array_equal(np.asarray(ahead.x), np.asarray(now.x))
    assert float(ahead.cost_after) == float(now.cost_after) < 1e-20


def test_uncertainty_at_one_program_jacobian_equals_uncertainty() -> None:
    r = refine(bounded_residual, jnp.array([1.0, 2.0]), LO2, HI2)
    ref = uncertainty(bounded_residual, r.x, LO2, HI2, names=["A", "k"])
    res, jac = value_and_jacobian(bounded_residual, np.asarray(r.x))
    assert res.shape == (50,) and jac.shape == (50, 2)
    u = uncertainty_at(res, jac, r.x, LO2, HI2, names=["A", "k"])
    np.testing.assert_allclose(u.std, ref.std, rtol=1e-12)
    np.testing.assert_allclose(u.corr, ref.corr, rtol=1e-12, atol=1e-15)
    assert u.sigma2 == pytest.approx(ref.sigma2, rel=1e-13) and u.flags == ref.flags
    assert u.cond == pytest.approx(ref.cond, rel=1e-10)
    with pytest.raises(FricjaxError, match="uncertainty: jac: shape \\(50, 3\\), expected"):
        uncertainty_at(res, np.zeros((50, 3)), r.x, LO2, HI2)


# --------------------------------------------------------------------------------------
# Census of minima
# --------------------------------------------------------------------------------------


def test_cluster_minima_counts_two_minima() -> None:
    lo, hi = np.array([0.0, -10.0, 0.0]), np.array([1.0, 10.0, 100.0])
    m1, m2 = np.array([0.2, -3.0, 40.0]), np.array([0.7, 5.0, 41.0])
    rng = np.random.default_rng(3)
    jitter = 1e-3 * (hi - lo) * rng.standard_normal((4, 3))
    xs = np.vstack([m2, m1, m1, m2]) + jitter
    costs = np.array([1.01, 1.0 + 1e-9, 1.0, 1.02])
    xs = np.vstack([xs, m1])  # a diverged chain: left out
    costs = np.append(costs, np.nan)
    out = cluster_minima(xs, costs, lo, hi)
    assert [m.count for m in out] == [2, 2]
    assert [list(m.members) for m in out] == [[2, 1], [0, 3]]
    assert out[0].cost == 1.0 and out[1].cost == 1.01
    np.testing.assert_array_equal(out[0].x, xs[2])
    # With a tolerance larger than the separation (0.5 of the range) the two merge.
    assert [m.count for m in cluster_minima(xs, costs, lo, hi, tol=0.6)] == [4]
