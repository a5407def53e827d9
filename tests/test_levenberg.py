"""Levenberg–Marquardt on an explicit Jacobian (fricjax.levenberg)."""

import jax
import jax.numpy as jnp
import numpy as np

import fricjax  # noqa: F401  (float64)
from fricjax.levenberg import levenberg_marquardt
from fricjax.refine import RefineSettings, refine

SETTINGS = RefineSettings(rtol=1e-10, atol=1e-10, max_steps=500)


def _with_jacobian(fn):
    return lambda th: (fn(th), jax.jacfwd(fn)(th))


def _rosenbrock(th):
    return jnp.stack([10.0 * (th[1] - th[0] ** 2), 1.0 - th[0]])


def test_linear_least_squares_lands_on_the_normal_equations_solution():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(40, 3))
    b = rng.normal(size=40)
    exact = np.linalg.lstsq(A, b, rcond=None)[0]
    fn = lambda th: jnp.asarray(A) @ th - jnp.asarray(b)  # noqa: E731
    lo, hi = exact - 5.0, exact + 5.0
    fit = levenberg_marquardt(
        fn, _with_jacobian(fn), jnp.asarray(lo + 1.0), lo, hi, jnp.ones(3, bool), SETTINGS
    )
    out = fit.refined
    assert bool(out.success)
    np.testing.assert_allclose(out.x, exact, atol=1e-8)
    np.testing.assert_allclose(out.cost_after, np.sum((A @ exact - b) ** 2), rtol=1e-12)
    # r and J handed back are those at the end point
    np.testing.assert_allclose(fit.r, A @ np.asarray(out.x) - b, atol=1e-12)
    np.testing.assert_allclose(fit.jac, A, atol=1e-12)


def test_held_components_stay_and_the_rest_solve_the_reduced_problem():
    rng = np.random.default_rng(1)
    A = rng.normal(size=(30, 3))
    b = rng.normal(size=30)
    fn = lambda th: jnp.asarray(A) @ th - jnp.asarray(b)  # noqa: E731
    x0 = np.array([0.3, 0.7, -0.2])
    free = np.array([True, False, True])
    lo, hi = x0 - 10.0, x0 + 10.0
    out = levenberg_marquardt(
        fn, _with_jacobian(fn), jnp.asarray(x0), lo, hi, free, SETTINGS
    ).refined
    assert float(out.x[1]) == x0[1]
    reduced = np.linalg.lstsq(A[:, free], b - A[:, 1] * x0[1], rcond=None)[0]
    np.testing.assert_allclose(np.asarray(out.x)[free], reduced, atol=1e-8)


def test_rosenbrock_valley_reaches_the_minimum_as_optimistix_does():
    lo, hi = np.array([-2.0, -2.0]), np.array([2.0, 3.0])
    x0 = np.array([-1.2, 1.0])
    out = levenberg_marquardt(
        _rosenbrock, _with_jacobian(_rosenbrock), jnp.asarray(x0), lo, hi,
        jnp.ones(2, bool), SETTINGS,
    ).refined  # fmt: skip
    ref = refine(_rosenbrock, x0, lo, hi, SETTINGS)
    assert bool(out.success)
    np.testing.assert_allclose(out.x, [1.0, 1.0], atol=1e-7)
    np.testing.assert_allclose(out.x, ref.x, atol=1e-7)
    assert float(out.cost_after) < 1e-14


def test_an_optimum_outside_the_box_ends_on_its_bound():
    fn = lambda th: th - 5.0  # noqa: E731  (minimum at 5, box [0, 2])
    out = levenberg_marquardt(
        fn, _with_jacobian(fn), jnp.asarray([1.0]), jnp.asarray([0.0]), jnp.asarray([2.0]),
        jnp.ones(1, bool), SETTINGS,
    ).refined  # fmt: skip
    np.testing.assert_allclose(out.x, [2.0], atol=1e-8)
    np.testing.assert_allclose(out.cost_after, 9.0, rtol=1e-8)


def test_vmapped_starts_equal_separate_fits():
    lo, hi = jnp.asarray([-2.0, -2.0]), jnp.asarray([2.0, 3.0])
    starts = jnp.asarray([[-1.2, 1.0], [0.5, -1.0], [1.5, 2.5]])

    def fit(x0):
        return levenberg_marquardt(
            _rosenbrock, _with_jacobian(_rosenbrock), x0, lo, hi, jnp.ones(2, bool), SETTINGS
        ).refined

    batched = jax.jit(jax.vmap(fit))(starts)
    for i in range(3):
        one = jax.jit(fit)(starts[i])
        np.testing.assert_allclose(batched.x[i], one.x, atol=1e-12)
        assert int(batched.n_steps[i]) == int(one.n_steps)


def test_a_start_no_step_improves_is_returned_unchanged():
    fn = lambda th: jnp.asarray([jnp.nan]) * th  # noqa: E731  (nowhere finite)
    x0 = jnp.asarray([0.5])
    out = levenberg_marquardt(
        fn, _with_jacobian(fn), x0, jnp.asarray([0.0]), jnp.asarray([1.0]),
        jnp.ones(1, bool), SETTINGS,
    ).refined  # fmt: skip
    assert float(out.x[0]) == 0.5
    assert not bool(out.success)


def test_the_decrement_stop_leaves_less_than_gain_tol_to_gain():
    # with a box transform the residual in z is not linear, so LM needs several steps; the
    # point it stops at must be within gain_tol of the minimum, which for a residual linear
    # in θ is the Gauss–Newton decrement itself
    rng = np.random.default_rng(2)
    A = rng.normal(size=(50, 4))
    b = rng.normal(size=50)
    exact = np.linalg.lstsq(A, b, rcond=None)[0]
    best = float(np.sum((A @ exact - b) ** 2))
    fn = lambda th: jnp.asarray(A) @ th - jnp.asarray(b)  # noqa: E731
    lo, hi = exact - 3.0, exact + 3.0
    loose = RefineSettings(rtol=1e-14, atol=1e-14, max_steps=500)
    for tol in (1e-2, 1e-6):
        out = levenberg_marquardt(
            fn, _with_jacobian(fn), jnp.asarray(lo + 0.5), lo, hi, jnp.ones(4, bool), loose, tol
        ).refined
        assert bool(out.success)
        assert 0.0 <= float(out.cost_after) - best < tol
    # the tighter tolerance takes more steps: the stop is the decrement's, not Cauchy's
    steps = [
        int(
            levenberg_marquardt(
                fn, _with_jacobian(fn), jnp.asarray(lo + 0.5), lo, hi, jnp.ones(4, bool), loose, t
            ).refined.n_steps
        )
        for t in (1e-2, 1e-6)
    ]
    assert steps[0] < steps[1]


def test_a_gain_beyond_the_bound_does_not_count():
    # minimum at 5 outside the box [0, 2], start in the middle: the gain up to the bound
    # (16 → 9) counts, the Gauss–Newton step's beyond it does not, or the fit would never
    # stop (sine transform: z creeps to π/2)
    fn = lambda th: th - 5.0  # noqa: E731
    loose = RefineSettings(rtol=1e-14, atol=1e-14, max_steps=500)
    out = levenberg_marquardt(
        fn, _with_jacobian(fn), jnp.asarray([1.0]), jnp.asarray([0.0]), jnp.asarray([2.0]),
        jnp.ones(1, bool), loose, 1e-2,
    ).refined  # fmt: skip
    assert bool(out.success)
    assert int(out.n_steps) < 500
    # it stops on the bound's side, with less than gain_tol left to the bound's cost 9
    assert 1.9 < float(out.x[0]) <= 2.0
    assert 0.0 <= float(out.cost_after) - 9.0 < 1e-2


def test_a_small_column_still_counts_in_the_stop():
    # one stiff parameter (column 1e6) and one whose column is 0.1, its minimum 0.09 below
    # the start: the decrement is regularised per column, so the stiff one does not drown
    # the other's gain (regularised by 1e-12 of the largest curvature, 1, its 0.01 counted
    # for 1 % of itself: the seed model's base stopped 2.9 σ_x² above its minimum so)
    def fn(th):
        return jnp.stack([1e6 * (th[0] - 1.0), 0.1 * (th[1] - 3.0)])

    lo, hi = jnp.asarray([-10.0, -10.0]), jnp.asarray([10.0, 10.0])
    loose = RefineSettings(rtol=1e-14, atol=1e-14, max_steps=500)
    out = levenberg_marquardt(
        fn, _with_jacobian(fn), jnp.asarray([1.0, 0.0]), lo, hi, jnp.ones(2, bool), loose, 1e-2
    ).refined
    assert bool(out.success)
    assert float(out.cost_after) < 1e-2
    assert abs(float(out.x[1]) - 3.0) < 0.35


def _counted(fn, calls):
    def counted(th):
        jax.debug.callback(lambda: calls.append(1))
        return fn(th)

    return counted


def test_plain_steps_reach_the_minimum_with_one_residual_per_step():
    lo, hi = np.array([-2.0, -2.0]), np.array([2.0, 3.0])
    x0 = jnp.asarray([-1.2, 1.0])
    calls = {True: [], False: []}
    fits = {
        bent: levenberg_marquardt(
            _counted(_rosenbrock, calls[bent]), _with_jacobian(_rosenbrock), x0, lo, hi,
            jnp.ones(2, bool), SETTINGS, accelerate=bent,
        ).refined
        for bent in (True, False)
    }  # fmt: skip
    for out in fits.values():
        assert bool(out.success)
        np.testing.assert_allclose(out.x, [1.0, 1.0], atol=1e-7)
    # a bent step probes the residual at z + δ·h before its trial; a plain one does not
    assert len(calls[False]) == int(fits[False].n_steps) + 1
    assert len(calls[True]) == 2 * (int(fits[True].n_steps) + 1)
