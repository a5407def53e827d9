from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np

from fricjax.model.drive import HarmonicDrive, MeasuredInput, phasor
from fricjax.model.term import (
    GRID_TOLERANCE_ULPS,
    MAX_INNER,
    GridSignals,
    Signals,
    TimeGrid,
    time_grid,
)


def test_harmonic_series_matches_numpy_reference() -> None:
    rng = np.random.default_rng(3)
    n_h = 7
    amps = rng.uniform(10, 1000, n_h)
    phases = rng.uniform(-math.pi, math.pi, n_h)
    omega, f0 = 2 * math.pi * 4.3, 123.4
    t = np.arange(500) / 1000.0
    p = {"F0": f0, "omega": omega}
    p.update({f"Fp_{i + 1}": amps[i] for i in range(n_h)})
    p.update({f"phi_{i + 1}": phases[i] for i in range(n_h)})
    p = {k: jnp.asarray(v) for k, v in p.items()}
    ref = f0 + sum(amps[i] * np.sin((i + 1) * omega * t + phases[i]) for i in range(n_h))
    z = jnp.zeros_like(jnp.asarray(t))
    got = HarmonicDrive(harmonics=n_h).force(p, Signals(jnp.asarray(t), z, z, z))
    np.testing.assert_allclose(np.asarray(got), ref, rtol=0, atol=1e-9)
    # scalar time (simulator) gives the same value
    s0 = Signals(jnp.asarray(t[123]), 0.0, 0.0, 0.0)
    assert abs(float(HarmonicDrive(harmonics=n_h).force(p, s0)) - ref[123]) < 1e-9


def test_measured_input_is_gain_times_u_minus_offset() -> None:
    u = jnp.linspace(-4, 4, 9)
    z = jnp.zeros_like(u)
    p = {"gain": jnp.asarray(35.15), "offset": jnp.asarray(-3.1648)}
    got = MeasuredInput().force(p, Signals(z, z, z, u))
    np.testing.assert_allclose(np.asarray(got), 35.15 * np.asarray(u) + 3.1648, rtol=1e-14)


# -- time grid and angle addition (fricjax.model.term.TimeGrid, drive.phasor) ---------------

EPS = float(np.finfo(np.float64).eps)  # 2^-52
# the paper twin after trim: 232 samples at 1 kHz from t = 0.02 s
TWIN_T = 0.02 + np.arange(232) / 1000.0
# omega boxes: the drive's own parameter box and configs/paper.toml's
OMEGA_BOXES = ((1.0, 1e3), (2 * math.pi * 3, 2 * math.pi * 8))


def _sig(t: np.ndarray, grid: TimeGrid | None = None) -> Signals:
    z = jnp.zeros_like(jnp.asarray(t))
    return GridSignals(jnp.asarray(t), z, z, z, grid)


def _drive_params(rng: np.random.Generator, omega: float, n_h: int = 10) -> dict:
    p = {"F0": 432.7, "omega": omega}
    p.update({f"Fp_{i}": rng.uniform(5.0, 1700.0) for i in range(1, n_h + 1)})
    p.update({f"phi_{i}": rng.uniform(-math.pi, math.pi) for i in range(1, n_h + 1)})
    return {k: jnp.asarray(v) for k, v in p.items()}


def test_time_grid_rebuilds_uniform_times_to_a_few_roundings() -> None:
    cases = (TWIN_T, np.arange(272) / 1000.0, np.linspace(3.0, 7.0, 1001), TWIN_T[3:-5][::3])
    for t in cases:
        n = t.size
        g = time_grid(t)
        assert g is not None
        j, r = g.outer.shape[0], g.inner.shape[0]
        assert r == min(math.isqrt(n - 1) + 1, MAX_INNER)
        assert (j - 1) * r < n <= j * r
        rebuilt = (np.asarray(g.outer)[:, None] + np.asarray(g.inner)[None, :]).ravel()[:n]
        assert np.max(np.abs(rebuilt - t)) <= GRID_TOLERANCE_ULPS * EPS * np.max(np.abs(t))
        np.testing.assert_array_equal(np.asarray(g.outer), t[::r])  # the recorded times
        # the grid layout puts sample k at [k // R, k % R] and repeats the last one after n
        lay = g.arrange(t)
        assert lay.shape == (j, r)
        np.testing.assert_array_equal(lay.ravel()[:n], t)
        assert np.all(lay.ravel()[n:] == t[-1])


def test_time_grid_is_none_unless_t_is_uniform() -> None:
    rng = np.random.default_rng(0)
    assert time_grid(np.delete(TWIN_T, 100)) is None  # a dropped sample
    # jitter far inside the recordings' 1e-6 tolerance is still no exact grid
    assert time_grid(TWIN_T + 1e-12 * rng.standard_normal(TWIN_T.size)) is None
    assert time_grid(TWIN_T[:3]) is None
    assert time_grid(np.stack([TWIN_T, TWIN_T])) is None
    assert time_grid(np.where(np.arange(232) == 7, np.nan, TWIN_T)) is None


def test_phasor_on_the_grid_equals_sin_cos_within_the_documented_bound() -> None:
    rng = np.random.default_rng(1)
    grid = time_grid(TWIN_T)
    t_max = float(np.max(np.abs(TWIN_T)))
    u = EPS / 2
    for lo, hi in OMEGA_BOXES:
        for omega in rng.uniform(lo, hi, 64):
            c0, s0 = phasor(jnp.asarray(omega), _sig(TWIN_T))
            c1, s1 = phasor(jnp.asarray(omega), _sig(TWIN_T, grid))
            # plain ≤ u(|ωt| + 2), grid ≤ u(|ωt| + 8) + |ω|·4·EPS·max|t| (phasor docstring)
            bound = u * (2 * omega * t_max + 10) + omega * GRID_TOLERANCE_ULPS * EPS * t_max
            assert float(jnp.max(jnp.abs(c1 - c0))) <= bound
            assert float(jnp.max(jnp.abs(s1 - s0))) <= bound
            np.testing.assert_allclose(np.asarray(c1), np.cos(omega * TWIN_T), rtol=0, atol=bound)


def test_drive_force_and_basis_on_the_grid_equal_the_plain_path() -> None:
    rng = np.random.default_rng(2)
    drive = HarmonicDrive()
    for t in (TWIN_T, TWIN_T[7:-2][::2]):  # the twin, and trimmed + decimated by 2
        grid = time_grid(t)
        assert grid is not None
        force = jax.jit(drive.force)
        basis = jax.jit(lambda p, s: drive.basis(p, s).columns)
        for lo, hi in OMEGA_BOXES:
            for omega in rng.uniform(lo, hi, 16):
                p = _drive_params(rng, omega)
                scale = sum(float(p[f"Fp_{i}"]) for i in range(1, 11))
                f0, f1 = force(p, _sig(t)), force(p, _sig(t, grid))
                assert float(jnp.max(jnp.abs(f1 - f0))) <= 1e-12 * scale
                b0, b1 = basis(p, _sig(t)), basis(p, _sig(t, grid))
                assert b1.shape == b0.shape == (t.size, 21)
                assert float(jnp.max(jnp.abs(b1 - b0))) <= 1e-12


def test_drive_on_the_grid_layout_equals_the_flat_grid_path() -> None:
    rng = np.random.default_rng(3)
    grid = time_grid(TWIN_T)
    drive = HarmonicDrive()
    p = _drive_params(rng, 2 * math.pi * 5.3)
    flat = np.asarray(drive.force(p, _sig(TWIN_T, grid)))
    lay = drive.force(p, _sig(grid.arrange(TWIN_T), grid))
    assert lay.shape == (grid.outer.shape[0], grid.inner.shape[0])
    scale = sum(float(p[f"Fp_{i}"]) for i in range(1, 11))
    np.testing.assert_allclose(np.asarray(lay).ravel()[: TWIN_T.size], flat, atol=1e-13 * scale)


def test_a_grid_that_does_not_fit_falls_back_to_plain_sin_cos() -> None:
    rng = np.random.default_rng(4)
    drive = HarmonicDrive()
    p = _drive_params(rng, 30.0)
    grid = time_grid(TWIN_T)
    plain = np.asarray(drive.force(p, _sig(TWIN_T)))
    # scalar t (the simulator), a different length, a batch of ω: the grid is ignored
    s0 = _sig(np.asarray(TWIN_T[123]), grid)
    assert float(drive.force(p, s0)) == plain[123]
    short = TWIN_T[:100]
    np.testing.assert_array_equal(
        np.asarray(drive.force(p, _sig(short, grid))), np.asarray(drive.force(p, _sig(short)))
    )
    batch = jnp.asarray([20.0, 30.0, 40.0])[:, None]
    c, s = phasor(batch, _sig(TWIN_T, grid))
    np.testing.assert_array_equal(np.asarray(c), np.cos(np.asarray(batch) * TWIN_T))
    assert s.shape == (3, TWIN_T.size)


def test_grid_signals_are_still_four_signals_and_drop_the_grid_when_rebuilt() -> None:
    grid = time_grid(TWIN_T)
    s = _sig(TWIN_T, grid)
    assert isinstance(s, Signals) and s.grid is grid and len(s) == 4
    t, x, v, u = s  # unpacks like plain signals
    assert t is s.t
    # rebuilt signals may hold other times: they lose the hint, and the drive then reads t
    assert s._replace(v=v + 1.0).grid is None
    assert jax.tree.map(lambda a: a, s).grid is None
    assert Signals(t, x, v, u).grid is None
    rng = np.random.default_rng(5)
    p = _drive_params(rng, 40.0)
    reversed_ = jax.tree.map(lambda a: a[::-1], s)
    np.testing.assert_array_equal(
        np.asarray(HarmonicDrive().force(p, reversed_)),
        np.asarray(HarmonicDrive().force(p, _sig(TWIN_T[::-1]))),
    )
