"""Closed-loop simulation (cascaded P/PD around the plant): exact against a matrix-exponential
reference for a linear plant, saturation, recovery of an injected input, derivatives."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.linalg import expm

from fricjax.errors import FricjaxError
from fricjax.model.closed_loop import (
    EMPS_CONTROLLER,
    CascadePD,
    feedback_law,
    input_disturbance,
    simulate_closed_loop,
)
from fricjax.model.drive import MeasuredInput
from fricjax.model.friction import CoulombViscous
from fricjax.model.system import Model

N = 800
DT = 1e-3
MODEL = Model((MeasuredInput(), CoulombViscous()))
T = np.arange(N) * DT
# EMPS-like reference: 0.02 m sine at 1 Hz (|v| ≤ 0.126 m/s, reverses at t = 0.25, 0.75 s)
REF = 0.05 + 0.02 * np.sin(2 * np.pi * 1.0 * T)
V0 = 0.02 * 2 * np.pi  # its slope at t = 0
X0 = 0.05 - V0 / EMPS_CONTROLLER.kp  # the lag of the P velocity loop at speed V0
PULSES = 2.0 * ((T % 0.2) < 0.1)  # V, added to the controller output


def params(**changes: float) -> dict[str, jax.Array]:
    p = {"gain": 35.15065188, "offset": -3.1648, "Fc": 20.3935, "Fv": 203.5034, "mass": 95.1}
    p.update(changes)
    return {k: jnp.asarray(v) for k, v in p.items()}


def linear_reference(
    p: dict[str, jax.Array], x0: float, v0: float, w: np.ndarray, ctrl: CascadePD
) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretisation of M·ẍ = g·ν − offset − Fv·ẋ (Fc = 0), with the
    sampled controller in a plain numpy loop: x [N], ν [N]."""
    m, fv, g, off = (float(p[k]) for k in ("mass", "Fv", "gain", "offset"))
    a = np.array([[0.0, 1.0], [0.0, -fv / m]])
    b = np.array([0.0, 1.0 / m])
    aug = np.zeros((3, 3))
    aug[:2, :2], aug[:2, 2] = a, b
    e = expm(aug * DT)
    phi, gamma = e[:2, :2], e[:2, 2]
    s = np.array([x0, v0])
    hist = [x0 - 2 * v0 * DT, x0 - v0 * DT]
    xs, us = np.zeros(N), np.zeros(N)
    for k in range(N):
        x = s[0]
        nu = ctrl.kp * ctrl.kv * (REF[k] - x) - ctrl.kv * (x - hist[0]) / (2 * DT) + w[k]
        nu = float(np.clip(nu, -ctrl.u_max, ctrl.u_max))
        xs[k], us[k] = x, nu
        hist = [hist[1], x]
        s = phi @ s + gamma * (g * nu - off)
    return xs, us


def test_linear_plant_matches_exact_discretisation() -> None:
    p = params(Fc=0.0)
    x0, v0 = X0, V0  # behind the reference by its steady lag, at its slope
    traj = simulate_closed_loop(MODEL, p, T, REF, x0, v0, EMPS_CONTROLLER, jnp.asarray(PULSES))
    xs, us = linear_reference(p, x0, v0, PULSES, EMPS_CONTROLLER)
    assert np.max(np.abs(np.asarray(traj.x) - xs)) < 1e-11  # m, RK4 error of a slow plant
    assert np.max(np.abs(np.asarray(traj.u) - us)) < 1e-7  # V (kv/(2dt) amplifies x 1.2e5×)
    assert np.max(np.abs(traj.x - REF)) < 2e-3  # and it tracks


def test_output_saturates_at_u_max() -> None:
    step = np.full(N, 0.02)  # 0.02 m step from rest: kp·kv·0.02 = 780 V asked
    ctrl = CascadePD(kp=160.18, kv=243.45, u_max=7.5)
    traj = simulate_closed_loop(MODEL, params(), T, step, 0.0, 0.0, ctrl)
    u = np.asarray(traj.u)
    assert u[0] == 7.5 and np.max(np.abs(u)) == 7.5
    assert abs(float(traj.x[-1]) - 0.02) < 1e-3  # it still gets there


def test_injected_input_is_recovered_from_the_record() -> None:
    p = params()
    traj = simulate_closed_loop(MODEL, p, T, REF, X0, V0, EMPS_CONTROLLER, jnp.asarray(PULSES))
    x, u = np.asarray(traj.x), np.asarray(traj.u)
    assert np.max(np.abs(u)) < EMPS_CONTROLLER.u_max  # unsaturated, so w = u − feedback
    w = input_disturbance(EMPS_CONTROLLER, T, x, REF, u)
    # From k = 2 on the history is the simulated one on both sides; before it the record
    # is extended by its first difference and the simulation by v0.
    np.testing.assert_allclose(w[2:], PULSES[2:], rtol=0, atol=1e-8)
    x2 = np.concatenate([[x[0], x[0]], x[:-2]])
    np.testing.assert_allclose(
        u[2:],
        np.asarray(feedback_law(EMPS_CONTROLLER, REF, x, x2, DT))[2:] + PULSES[2:],
        atol=1e-8,
    )


def test_force_error_gradient_matches_finite_differences() -> None:
    target = simulate_closed_loop(MODEL, params(), T, REF, X0, V0, EMPS_CONTROLLER).u

    def loss(fv: jax.Array, fc: jax.Array) -> jax.Array:
        traj = simulate_closed_loop(MODEL, params(Fv=fv, Fc=fc), T, REF, X0, V0, EMPS_CONTROLLER)
        return jnp.sum((35.15 * (traj.u - target)) ** 2)

    fv, fc = jnp.asarray(190.0), jnp.asarray(19.0)
    # forward mode, as Levenberg–Marquardt (fit_simulation_error) differentiates it
    g_fv, g_fc = jax.jacfwd(loss, argnums=(0, 1))(fv, fc)
    h = 1e-4
    fd_fv = (loss(fv + h, fc) - loss(fv - h, fc)) / (2 * h)
    fd_fc = (loss(fv, fc + h) - loss(fv, fc - h)) / (2 * h)
    assert float(g_fv) == pytest.approx(float(fd_fv), rel=1e-5)
    assert float(g_fc) == pytest.approx(float(fd_fc), rel=1e-5)
    assert float(g_fv) < 0 and float(g_fc) < 0  # both below the generating values


def test_vmap_over_parameter_sets_equals_separate_runs() -> None:
    masses = jnp.asarray([80.0, 110.0])

    def run(m: jax.Array) -> jax.Array:
        return simulate_closed_loop(MODEL, params(mass=m), T, REF, X0, V0, EMPS_CONTROLLER).u

    both = jax.vmap(run)(masses)
    for i in range(2):
        np.testing.assert_allclose(both[i], run(masses[i]), rtol=0, atol=1e-9)
    assert float(jnp.max(jnp.abs(both[0] - both[1]))) > 0.1  # the mass matters to the force


def test_shape_mismatch_refused_in_one_line() -> None:
    with pytest.raises(FricjaxError) as err:
        simulate_closed_loop(MODEL, params(), T, REF[:-1], 0.0, 0.0, EMPS_CONTROLLER)
    assert "\n" not in str(err.value)
    assert "simulate_closed_loop: r: shape (799,) differs from t's (800,)" in str(err.value)
