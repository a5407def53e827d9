"""Facts about the forward simulator, checked against an event-driven scipy reference.

The reference (:func:`reference`) integrates the smooth ODE of the current direction of
motion with ``solve_ivp`` (DOP853, rtol 1e-13, atol 1e-15) and stops it with a terminal
event at ``v = 0``; at an event, or while stuck, it decides stick or slip itself: the body
slips when ``|F_p| > static`` (in the drive's direction) and otherwise stays put until the
first time ``|F_p|`` exceeds the static limit (found on a 20 µs grid, then by ``brentq``).
Its friction branches are the analytic continuations of seed eq. (1) for δ = 1, written
here independently of ``fricjax``.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.optimize import brentq

from fricjax.config import Config
from fricjax.errors import FricjaxError
from fricjax.model.drive import HarmonicDrive, MeasuredInput
from fricjax.model.friction import CoulombViscous, StribeckFriction
from fricjax.model.simulate import Trajectory, _simulate, simulate
from fricjax.model.system import Model

# --------------------------------------------------------------------------------------
# Reference integrator
# --------------------------------------------------------------------------------------

Drive = Callable[[np.ndarray], np.ndarray]
Branch = Callable[[float, int], float]


def reference(
    drive: Drive,
    branch: Branch,
    static: float,
    mass: float,
    t: np.ndarray,
    x0: float,
    v0: float,
    breaks: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, list[tuple[float, str, int]]]:
    """Piecewise-smooth solution of ``m·ẍ = F_p(t) − F_f(ẋ)`` with stiction, at times ``t``.

    drive(τ) [N] (independent of x, v); branch(v, d) [N]: the friction of direction d = ±1
    as a smooth function of v; static [N]: the static limit (both directions); breaks: times
    where the drive has kinks (each piece is integrated separately). Returns x, v at ``t``
    and the events ``(time, "stop" | "break", direction)``.
    """
    xs = np.full(t.shape, np.nan)
    vs = np.full(t.shape, np.nan)
    xs[0], vs[0] = x0, v0
    breaks = np.array([t[0], t[-1]]) if breaks is None else breaks
    tau, x, v = float(t[0]), float(x0), float(v0)
    mode = int(np.sign(v))
    events: list[tuple[float, str, int]] = []

    def fill(a: float, b: float, fx: Callable, fv: Callable) -> None:
        k = (t >= a - 1e-12) & (t <= b + 1e-12)
        xs[k], vs[k] = fx(t[k]), fv(t[k])

    def at_rest(xc: float) -> tuple[Callable, Callable]:
        return (lambda q: np.full_like(q, xc)), np.zeros_like

    for b1 in breaks[1:]:
        while tau < b1 - 1e-15:
            if mode == 0:
                force = float(drive(np.asarray(tau)))
                if abs(force) > static:
                    mode = int(np.sign(force))
                    events.append((tau, "break", mode))
                    continue
                grid = np.linspace(tau, b1, max(3, int((b1 - tau) / 2e-5) + 2))
                above = np.nonzero(np.abs(drive(grid)) > static)[0]
                if above.size == 0:
                    fill(tau, b1, *at_rest(x))
                    tau = b1
                    continue
                i = above[0]
                tb = brentq(
                    lambda q: abs(float(drive(np.asarray(q)))) - static,
                    grid[i - 1],
                    grid[i],
                    xtol=1e-15,
                    rtol=1e-15,
                )
                while abs(float(drive(np.asarray(tb)))) <= static:  # start on the slip side
                    tb = float(np.nextafter(tb, np.inf))
                fill(tau, tb, *at_rest(x))
                tau, mode = tb, int(np.sign(float(drive(np.asarray(tb)))))
                events.append((tau, "break", mode))
            else:
                d = mode

                def rhs(q: float, y: np.ndarray, d: int = d) -> list[float]:
                    return [y[1], (float(drive(np.asarray(q))) - branch(y[1], d)) / mass]

                def stop(q: float, y: np.ndarray) -> float:
                    return y[1]

                stop.terminal = True  # type: ignore[attr-defined]
                stop.direction = -d  # type: ignore[attr-defined]
                sol = solve_ivp(
                    rhs,
                    (tau, b1),
                    [x, v],
                    method="DOP853",
                    rtol=1e-13,
                    atol=1e-15,
                    events=stop,
                    dense_output=True,
                )
                if sol.t_events[0].size:
                    te = float(sol.t_events[0][0])
                    fill(tau, te, lambda q, s=sol: s.sol(q)[0], lambda q, s=sol: s.sol(q)[1])
                    tau, x, v = te, float(sol.y_events[0][0][0]), 0.0
                    events.append((te, "stop", d))
                    force = float(drive(np.asarray(tau)))
                    mode = int(np.sign(force)) if abs(force) > static else 0
                    if mode:
                        events.append((tau, "break", mode))
                else:
                    fill(tau, b1, lambda q, s=sol: s.sol(q)[0], lambda q, s=sol: s.sol(q)[1])
                    tau, x, v = float(b1), float(sol.y[0, -1]), float(sol.y[1, -1])
    return xs, vs, events


def stribeck_branch(Fc: float, Fs: float, vs: float, Fv: float) -> Branch:
    """Seed eq. (1), δ = 1, for direction d, continued analytically across v = 0."""
    return lambda v, d: d * (Fc + (Fs - Fc) * np.exp(-d * v / vs)) + Fv * v


def harmonic(F0: float, omega: float, amps: list[float], phis: list[float]) -> Drive:
    """Seed eq. (4)."""
    i = np.arange(1, len(amps) + 1)

    def drive(q: np.ndarray) -> np.ndarray:
        q = np.asarray(q, dtype=float)
        arg = np.multiply.outer(q, i * omega) + np.asarray(phis)
        return F0 + np.sin(arg) @ np.asarray(amps)

    return drive


def jparams(values: dict[str, float]) -> dict[str, jax.Array]:
    return {k: jnp.asarray(v, dtype=jnp.float64) for k, v in values.items()}


# --------------------------------------------------------------------------------------
# 1. The seed's model with the CSAA parameters
# --------------------------------------------------------------------------------------

AMPS = [667.5, 998.1, 1118.9, 879.9, 559.9, 49.99, 279.9, 139.9, 413.0, 9.99]
PHIS = [0.71, 0.96, 1.24, 1.49, 1.57, 0.499, 0.001, 0.001, 0.001, 1.00]
CSAA = {
    "F0": 432.7, "Fc": 30.0, "Fv": 3749.9, "Fs": 189.99, "vs": 0.121, "omega": 2 * np.pi * 5,
    **{f"Fp_{i}": a for i, a in enumerate(AMPS, 1)},
    **{f"phi_{i}": f for i, f in enumerate(PHIS, 1)},
}  # fmt: skip
MASS = 45.0
T_PAPER = np.arange(2001) * 1e-3  # 1 kHz, 2 s; its first 273 samples are the 0.272 s record
N_SHORT = 273


def paper_p(config: Config, theta: jax.Array) -> dict[str, jax.Array]:
    return {**config.spec.unflatten(theta), "mass": jnp.asarray(MASS)}


@pytest.fixture(scope="module")
def paper_theta(paper_config: Config) -> jax.Array:
    return jnp.asarray(paper_config.spec.flatten(CSAA))


@pytest.fixture(scope="module")
def paper_ref() -> tuple[np.ndarray, np.ndarray, list]:
    drive = harmonic(CSAA["F0"], CSAA["omega"], AMPS, PHIS)
    branch = stribeck_branch(CSAA["Fc"], CSAA["Fs"], CSAA["vs"], CSAA["Fv"])
    return reference(drive, branch, CSAA["Fs"], MASS, T_PAPER, 0.0, 0.0)


@pytest.fixture(scope="module")
def paper_errors(
    paper_config: Config, paper_theta: jax.Array, paper_ref: tuple
) -> dict[int, tuple[float, float, float, float]]:
    """substeps -> (max|Δx| 0.272 s, max|Δv| 0.272 s, max|Δx| 2 s, max|Δv| 2 s)."""
    xr, vr, _ = paper_ref
    out = {}
    for substeps in (4, 8, 16):
        tr = simulate(
            paper_config.model,
            paper_p(paper_config, paper_theta),
            jnp.asarray(T_PAPER),
            0.0,
            0.0,
            substeps=substeps,
        )
        dx, dv = np.abs(np.asarray(tr.x) - xr), np.abs(np.asarray(tr.v) - vr)
        out[substeps] = (dx[:N_SHORT].max(), dv[:N_SHORT].max(), dx.max(), dv.max())
    return out


def test_paper_reference_has_reversals_and_sticking(paper_ref: tuple) -> None:
    # The CSAA record is a hard case: the body reverses and sticks, every 0.2 s period.
    _, _, events = paper_ref
    kinds = [k for _, k, _ in events]
    assert kinds.count("stop") >= 30 and kinds.count("break") >= 30


def test_paper_model_matches_reference(paper_errors: dict) -> None:
    # Measured at 8 sub-steps (1 kHz): |Δx| 2.7e-12 m, |Δv| 1.25e-10 m/s over 0.272 s;
    # |Δx| 3.8e-12 m, |Δv| 1.25e-10 m/s over 2 s (x ≈ 0.2 m, |v| ≤ 0.6 m/s).
    dx_short, dv_short, dx_long, dv_long = paper_errors[8]
    assert dx_short < 2e-11 and dv_short < 1e-9
    assert dx_long < 2e-11 and dv_long < 1e-9


def test_paper_model_converges_at_fourth_order(paper_errors: dict) -> None:
    # RK4 with located events: 4 -> 16 sub-steps should divide the error by 4⁴ = 256
    # (measured: Δv 2.0e-9 -> 7.8e-12, Δx 2.2e-10 -> 2.7e-13 over 2 s).
    for col in range(4):
        assert paper_errors[16][col] < paper_errors[4][col] / 50


def test_vmap_over_parameter_vectors_equals_a_loop(
    paper_config: Config, paper_theta: jax.Array
) -> None:
    spec = paper_config.spec
    rng = np.random.default_rng(7)
    thetas = jnp.asarray(spec.lower + (spec.upper - spec.lower) * rng.random((3, spec.n_free)))
    thetas = jnp.concatenate([paper_theta[None], thetas])
    t = jnp.asarray(T_PAPER)

    def run(theta: jax.Array) -> Trajectory:
        return simulate(paper_config.model, paper_p(paper_config, theta), t, 0.0, 0.0)

    batch = jax.vmap(run)(thetas)
    for k in range(thetas.shape[0]):
        one = run(thetas[k])
        for got, want in zip(batch, one, strict=True):
            np.testing.assert_allclose(np.asarray(got[k]), np.asarray(want), rtol=1e-12, atol=1e-13)
        # The stuck samples are identical (exact zeros) in the batch and the loop.
        np.testing.assert_array_equal(np.asarray(batch.v[k]) == 0, np.asarray(one.v) == 0)


# --------------------------------------------------------------------------------------
# 2./3. Stick-slip under a slow sinusoid; sticking under a drive below the static limit
# --------------------------------------------------------------------------------------

T_SLOW = np.arange(4001) * 1e-3  # 4 s at 1 kHz: two periods of the drive
SLOW = {"F0": 0.0, "omega": np.pi, "Fp_1": 150.0, "phi_1": 0.0, "Fv": 20.0, "mass": 10.0}
STICK_SLIP_CASES = {
    "coulomb": (CoulombViscous(), {"Fc": 100.0}, 100.0),
    "stribeck": (StribeckFriction(), {"Fc": 80.0, "Fs": 120.0, "vs": 0.05, "delta": 1.0}, 120.0),
}


def runs_of_rest(v: np.ndarray) -> list[tuple[int, int]]:
    """Maximal index runs [start, end] with v == 0 exactly."""
    rest = np.concatenate([[False], v == 0, [False]]).astype(int)
    edges = np.diff(rest)
    return list(zip(np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0] - 1, strict=True))


def sign_changes(v: np.ndarray) -> int:
    s = np.sign(v[v != 0])
    return int(np.count_nonzero(s[1:] != s[:-1]))


@pytest.mark.parametrize("case", sorted(STICK_SLIP_CASES))
def test_stick_slip_matches_reference_without_chatter(case: str) -> None:
    term, fric, static = STICK_SLIP_CASES[case]
    model = Model((HarmonicDrive(harmonics=1), term))
    values = {**SLOW, **fric}
    tr = simulate(model, jparams(values), jnp.asarray(T_SLOW), 0.0, 0.0)
    x, v = np.asarray(tr.x), np.asarray(tr.v)

    drive = harmonic(0.0, np.pi, [150.0], [0.0])
    branch = stribeck_branch(
        fric["Fc"], fric.get("Fs", fric["Fc"]), fric.get("vs", 1.0), SLOW["Fv"]
    )
    xr, vr, events = reference(drive, branch, static, SLOW["mass"], T_SLOW, 0.0, 0.0)
    # Measured: Coulomb |Δx| 1.9e-13 m, |Δv| 3.8e-13 m/s; Stribeck |Δx| 4.3e-12 m,
    # |Δv| 1.8e-11 m/s (x, v of order 0.1). Stribeck's falling branch (slope −780 N·s/m near
    # v = 0) amplifies rounding at breakaway: the reference itself moves by 1.5e-11 m/s when
    # restarted at other times, so this is its floor, not the simulator's.
    assert np.max(np.abs(x - xr)) < 3e-11 and np.max(np.abs(v - vr)) < 1e-10

    # The reference's stuck intervals: initial rest, and every stop not followed at once by
    # a breakaway.
    stuck, reversals, heading = [], 0, 0
    rest_since: float | None = float(T_SLOW[0])
    for time, kind, d in events:
        if kind == "stop":
            rest_since = time
        else:
            if rest_since is not None and time > rest_since:
                stuck.append((rest_since, time))
            reversals += int(heading != 0 and d != heading)
            heading, rest_since = d, None
    if rest_since is not None:  # at rest when the record ends
        stuck.append((rest_since, np.inf))
    assert len(stuck) >= 3 and reversals >= 2  # the case really is stick-slip

    runs = runs_of_rest(v)
    assert len(runs) == len(stuck)  # every rest is one unbroken run: no chatter
    assert sign_changes(v) == reversals
    dt = T_SLOW[1] - T_SLOW[0]
    for (k0, k1), (t_stop, t_break) in zip(runs, stuck, strict=True):
        # Exactly at rest over the run, and the run spans the reference's stuck interval.
        assert np.all(x[k0 : k1 + 1] == x[k0])
        assert 0 <= T_SLOW[k0] - t_stop <= dt
        if np.isfinite(t_break):
            assert 0 < T_SLOW[k1 + 1] - t_break <= dt  # breakaway within one sample
        else:
            assert k1 == T_SLOW.size - 1
        assert np.all(tr.a[k0 : k1 + 1] == 0)


@pytest.mark.parametrize("F0", [100.0, -100.0])
def test_drive_below_static_limit_never_moves(F0: float) -> None:
    # |F0| + |Fp_1| = 115 N < Fs = 120 N: the body must not move at all.
    term, fric, _ = STICK_SLIP_CASES["stribeck"]
    model = Model((HarmonicDrive(harmonics=1), term))
    values = {**SLOW, **fric, "F0": F0, "Fp_1": 15.0}
    tr = simulate(model, jparams(values), jnp.asarray(T_SLOW), 0.3, 0.0)
    assert np.all(np.asarray(tr.x) == 0.3)
    assert np.all(np.asarray(tr.v) == 0.0)
    assert np.all(np.asarray(tr.a) == 0.0)


# --------------------------------------------------------------------------------------
# 4. A free body under a constant force
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("v0", [0.5, 0.0, -0.5])
def test_free_body_follows_the_parabola(v0: float) -> None:
    # No friction (static limit 0): x = x0 + v0·t + F·t²/(2m); with v0 < 0 the velocity
    # passes through zero at t = 1/3 s and the body must turn around without a hiccup.
    model = Model((HarmonicDrive(harmonics=1),))
    force, mass, x0 = 3.0, 2.0, 0.1
    values = {"F0": force, "omega": np.pi, "Fp_1": 0.0, "phi_1": 0.0, "mass": mass}
    t = np.arange(1001) * 1e-3
    tr = simulate(model, jparams(values), jnp.asarray(t), x0, v0)
    # Measured: ≤ 2e-15 m, ≤ 3e-15 m/s.
    np.testing.assert_allclose(tr.x, x0 + v0 * t + force * t**2 / (2 * mass), rtol=0, atol=1e-9)
    np.testing.assert_allclose(tr.v, v0 + force * t / mass, rtol=0, atol=1e-9)
    np.testing.assert_allclose(tr.a, force / mass, rtol=1e-12)


# --------------------------------------------------------------------------------------
# 5. Drive from a recorded input
# --------------------------------------------------------------------------------------


def test_measured_input_matches_reference_with_interpolated_input() -> None:
    # EMPS-like rig: F_p = g·u − offset, Stribeck friction, a noisy two-tone input.
    model = Model((MeasuredInput(), StribeckFriction()))
    values = {
        "gain": 35.15, "offset": 2.0, "Fc": 20.0, "Fs": 30.0, "vs": 0.02, "delta": 1.0,
        "Fv": 200.0, "mass": 5.0,
    }  # fmt: skip
    t = np.arange(601) * 1e-3
    rng = np.random.default_rng(3)
    u = (
        1.2 * np.sin(2 * np.pi * 3 * t)
        + 0.4 * np.sin(2 * np.pi * 11 * t + 1.0)
        + 0.05 * rng.standard_normal(t.size)
    )
    tr = simulate(model, jparams(values), jnp.asarray(t), 0.0, 0.0, jnp.asarray(u))

    def drive(q: np.ndarray) -> np.ndarray:
        return values["gain"] * np.interp(q, t, u) - values["offset"]

    branch = stribeck_branch(values["Fc"], values["Fs"], values["vs"], values["Fv"])
    xr, vr, events = reference(drive, branch, values["Fs"], values["mass"], t, 0.0, 0.0, t)
    assert sum(k == "stop" for _, k, _ in events) >= 3
    # Measured at 8 sub-steps: |Δx| 2.3e-12 m, |Δv| 4.2e-11 m/s (|x| ≤ 5 mm, |v| ≤ 0.13 m/s);
    # 2.6e-12 m/s at 16 sub-steps.
    assert np.max(np.abs(np.asarray(tr.x) - xr)) < 1e-11
    assert np.max(np.abs(np.asarray(tr.v) - vr)) < 3e-10
    assert len(runs_of_rest(np.asarray(tr.v))) == len(runs_of_rest(vr))


# --------------------------------------------------------------------------------------
# User mistakes
# --------------------------------------------------------------------------------------


def test_user_mistakes_name_the_field() -> None:
    model = Model((HarmonicDrive(harmonics=1), CoulombViscous()))
    p = jparams({**SLOW, "Fc": 100.0})
    t = jnp.asarray(T_SLOW[:10])
    no_mass = {k: v for k, v in p.items() if k != "mass"}
    with pytest.raises(FricjaxError, match=r"^simulate: p: missing parameter\(s\) mass"):
        simulate(model, no_mass, t, 0.0, 0.0)
    with pytest.raises(FricjaxError, match=r"^simulate: u: shape \(9,\) differs"):
        simulate(model, p, t, 0.0, 0.0, jnp.zeros(9))
    with pytest.raises(FricjaxError, match=r"^simulate: t: needs a 1-D array of at least 2"):
        simulate(model, p, t[:1], 0.0, 0.0)
    with pytest.raises(FricjaxError, match=r"^simulate: substeps: must be a positive integer"):
        simulate(model, p, t, 0.0, 0.0, substeps=0)


def test_gradient_through_stick_slip_matches_finite_differences() -> None:
    # The stop and breakaway instants move with the parameters; d(loss)/dθ must follow them
    # (measured agreement with central differences: 1e-10 .. 5e-8 relative).
    term, fric, _ = STICK_SLIP_CASES["stribeck"]
    model = Model((HarmonicDrive(harmonics=1), term))
    base = jparams({**SLOW, **fric})
    names = ("Fp_1", "Fc", "Fs", "vs", "mass")
    t = jnp.asarray(T_SLOW)

    def loss(theta: jax.Array) -> jax.Array:
        p = {**base, **{k: theta[i] for i, k in enumerate(names)}}
        return jnp.mean(simulate(model, p, t, 0.0, 0.0).x ** 2) * 1e2

    theta = jnp.stack([base[k] for k in names])
    grad = np.asarray(jax.jit(jax.grad(loss))(theta))
    assert np.all(np.isfinite(grad))
    for i, name in enumerate(names):
        step = 1e-6 * abs(float(theta[i]))
        fd = (float(loss(theta.at[i].add(step))) - float(loss(theta.at[i].add(-step)))) / (2 * step)
        assert abs(grad[i] - fd) <= 1e-6 * abs(fd), name


def test_skipping_idle_event_machinery_changes_nothing() -> None:
    # Idle parts of the event machinery (a slide that does not stop, a body not at rest, no
    # breakaway) are skipped by a lax.cond taken for a whole vmap batch. The skipped parts
    # must change nothing: trajectories and their forward derivatives equal those of the
    # path that evaluates everything, on a batch of stick-slip records whose stops and
    # breakaways differ.
    term, fric, _ = STICK_SLIP_CASES["stribeck"]
    model = Model((HarmonicDrive(harmonics=1), term))
    base = jparams({**SLOW, **fric})
    names = ("Fp_1", "Fc", "Fs", "vs", "mass")
    t = jnp.asarray(T_SLOW)
    theta0 = jnp.stack([base[k] for k in names])
    thetas = theta0 * jnp.asarray(
        [[1.0] * 5, [1.03, 0.97, 1.0, 1.1, 1.0], [0.95, 1.0, 1.04, 1.0, 0.9]]
    )
    # a relative tangent mixing every parameter, [batch, 5]
    dirs = thetas * jnp.asarray([0.3, -0.2, 0.5, 0.1, -0.4])

    def run(skip_idle: bool) -> tuple[Trajectory, Trajectory]:
        def batch(th: jax.Array) -> Trajectory:
            def one(theta: jax.Array) -> Trajectory:
                p = {**base, **{k: theta[i] for i, k in enumerate(names)}}
                return _simulate(model, p, t, 0.0, 0.0, None, 2, skip_idle)

            return jax.vmap(one)(th)

        def tangents(th: jax.Array, d: jax.Array) -> tuple[Trajectory, Trajectory]:
            return jax.jvp(batch, (th,), (d,))

        return jax.jit(tangents)(thetas, dirs)

    (fast, dfast), (full, dfull) = run(True), run(False)
    for k in range(thetas.shape[0]):
        v = np.asarray(full.v[k])
        assert len(runs_of_rest(v)) >= 3 and sign_changes(v) >= 2  # stops, rests, reversals
    for got, want in zip((*fast, *dfast), (*full, *dfull), strict=True):
        scale = np.max(np.abs(np.asarray(want)))
        assert scale > 0
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=0, atol=1e-12 * scale)
    # Rest is exact in both: the same samples are stuck.
    np.testing.assert_array_equal(np.asarray(fast.v) == 0, np.asarray(full.v) == 0)
    # Unbatched, the cond is a plain branch: the same trajectory again.
    alone = simulate(model, base, t, 0.0, 0.0, substeps=2)
    for got, want in zip(alone, full, strict=True):
        np.testing.assert_allclose(
            np.asarray(got),
            np.asarray(want[0]),
            rtol=0,
            atol=1e-12 * np.max(np.abs(np.asarray(want[0]))),
        )
