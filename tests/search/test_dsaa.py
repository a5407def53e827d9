"""DSAA: eq. 13 coding (binary and Gray), eq. 14 bit flips, search on the grid."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fricjax.search import dsaa
from fricjax.search.annealing import AnnealSettings
from fricjax.search.chains import run_chains

CENTRE = np.array([0.3, -1.2, 2.5, 0.7, -0.4])
LOWER, UPPER = np.full(5, -3.0), np.full(5, 3.0)
# Cold enough at the end (t ≈ 3e-6 against cost steps of ~1e-5 near the minimum) for every
# Gray chain to settle on the best grid point.
SETTINGS = AnnealSettings(steps_per_level=40, max_levels=165, alpha=0.88, t_min_rel=1e-9)
N_BITS = 10


def _quad(x):
    return jnp.sum((x - CENTRE) ** 2)


def _rastrigin(x):
    return 10.0 * x.shape[0] + jnp.sum(x**2 - 10.0 * jnp.cos(2.0 * jnp.pi * x))


@pytest.mark.parametrize("gray", [False, True])
def test_round_trip_exact_on_every_grid_point(gray):
    lo, hi = np.array([-0.7]), np.array([2.3])
    index = np.arange(2**N_BITS)[:, None]
    grid = np.asarray(dsaa.from_index(index, lo, hi, N_BITS))
    bits = np.asarray(dsaa.encode(grid, lo, hi, N_BITS, gray))
    np.testing.assert_array_equal(np.asarray(dsaa.bits_to_index(bits, gray)), index)
    np.testing.assert_array_equal(np.asarray(dsaa.decode(bits, lo, hi, gray)), grid)
    assert grid[0, 0] == lo[0] and grid[-1, 0] == hi[0]


@pytest.mark.parametrize("gray", [False, True])
def test_quantisation_error_at_most_half_a_grid_step(gray):
    lo, hi = np.array([-3.0, 0.0, 1e3]), np.array([3.0, 1e-4, 2e3])
    x = lo + np.random.default_rng(0).uniform(size=(5000, 3)) * (hi - lo)
    back = np.asarray(dsaa.decode(dsaa.encode(x, lo, hi, N_BITS, gray), lo, hi, gray))
    half_step = (hi - lo) / (2 * (2**N_BITS - 1))
    assert np.all(np.abs(back - x) <= half_step * (1 + 1e-9))


def test_binary_code_is_msb_first_and_gray_neighbours_differ_in_one_bit():
    index = np.arange(2**N_BITS)
    binary = np.asarray(dsaa.index_to_bits(index, N_BITS, gray=False))
    expected = np.array([[c == "1" for c in format(i, "010b")] for i in index])
    np.testing.assert_array_equal(binary, expected)
    gray = np.asarray(dsaa.index_to_bits(index, N_BITS, gray=True))
    assert np.all(np.sum(gray[1:] != gray[:-1], axis=1) == 1)
    # The Hamming cliff of plain binary: 511 → 512 changes all ten bits.
    assert np.sum(binary[511] != binary[512]) == 10


_flip = jax.jit(jax.vmap(dsaa.flip_bits, in_axes=(0, None, None)), static_argnums=2)


def test_flip_changes_between_one_and_k_distinct_bits_uniformly():
    bits = jnp.zeros((26, N_BITS), dtype=bool)
    u = np.random.default_rng(3).uniform(size=(30_000, 4))
    flipped = np.asarray(_flip(u, bits, 3))
    counts = flipped.reshape(len(u), -1).sum(axis=1)
    freq = np.bincount(counts, minlength=4) / len(u)
    assert freq[0] == 0.0
    # m uniform on {1, 2, 3}.
    np.testing.assert_allclose(freq[1:], 1 / 3, atol=5 * math.sqrt(2 / 9 / len(u)))
    # Every one of the 260 bit positions is used, evenly (mean 2 flips per proposal).
    per_bit = flipped.reshape(len(u), -1).mean(axis=0)
    np.testing.assert_allclose(per_bit, 2 / 260, atol=5 * math.sqrt(2 / 260 / len(u)))


@pytest.fixture(scope="module")
def quad_runs():
    return {
        m: run_chains(jax.random.key(5), _quad, LOWER, UPPER, m, SETTINGS, n_chains=8)
        for m in ("dsaa-gray", "dsaa")
    }


def _grid_index(x):
    return (x - LOWER) / (UPPER - LOWER) * (2**N_BITS - 1)


def test_best_points_are_grid_points_inside_box(quad_runs):
    for r in quad_runs.values():
        index = _grid_index(r.chain_x)
        np.testing.assert_allclose(index, np.round(index), rtol=0, atol=1e-9)
        assert np.all(r.chain_x >= LOWER) and np.all(r.chain_x <= UPPER)


def test_gray_quadratic_5d_every_chain_on_grid_point_nearest_minimum(quad_runs):
    nearest = np.asarray(dsaa.snap(jnp.asarray(CENTRE), LOWER, UPPER, SETTINGS))
    step = (UPPER - LOWER) / (2**N_BITS - 1)
    assert np.all(np.abs(nearest - CENTRE) <= step / 2)
    np.testing.assert_allclose(quad_runs["dsaa-gray"].chain_x, np.tile(nearest, (8, 1)), atol=1e-12)


def test_binary_quadratic_5d_best_chain_near_minimum(quad_runs):
    # Plain binary has Hamming cliffs (0111111111 → 1000000000, see the test below): a
    # chain that freezes on the wrong side of one stays there. The minimum of the first
    # parameter (0.3, grid index 562.6) lies 0.303 above the 511|512 cliff, and runs do end
    # there; so binary DSAA is held only to that distance (Gray, above, to the grid point).
    r = quad_runs["dsaa"]
    assert np.abs(r.best_x - CENTRE).max() < 0.31
    assert r.best_cost < 0.1
    assert r.best_cost >= quad_runs["dsaa-gray"].best_cost


def _neighbours_within_two_flips(index, gray):
    """All integers whose code differs from ``index``'s in 1 or 2 of the 10 bits."""
    bits = np.asarray(dsaa.index_to_bits(np.array([index]), N_BITS, gray))[0]
    flips = [np.eye(N_BITS, dtype=bool)[i] for i in range(N_BITS)]
    flips += [f | g for i, f in enumerate(flips) for g in flips[i + 1 :]]
    return np.asarray(dsaa.bits_to_index(np.array([bits ^ f for f in flips]), gray))


def test_binary_has_hamming_cliff_where_gray_has_none():
    # Minimum of |i − 520| (520 = 1000001000) seen from 511 = 0111111111: no binary code
    # within two flips is closer, so a cold binary chain is stuck 9 grid steps away (the reason
    # for the loose tolerance above). In Gray code every integer has its
    # two neighbours i ± 1 one flip away, so no such trap exists on a unimodal cost.
    assert np.min(np.abs(_neighbours_within_two_flips(511, gray=False) - 520)) > 9
    for i in (511, 512, 519, 3, 1000):
        near = set(_neighbours_within_two_flips(i, gray=True).tolist())
        assert {i - 1, i + 1} <= near
        assert np.min(np.abs(_neighbours_within_two_flips(i, gray=True) - 520)) < abs(i - 520)


def test_gray_rastrigin_2d_global_minimum_on_most_chains():
    box = np.full(2, 5.12)
    r = run_chains(jax.random.key(8), _rastrigin, -box, box, "dsaa-gray", SETTINGS, n_chains=8)
    # The origin is not on the grid; the nearest grid points are half a step away. (It
    # sits on the 511|512 cliff of the binary code: plain binary ends there on only
    # 4–7 chains of 8, in 16 trial seeds; Gray on all 8 every time.)
    step = 2 * 5.12 / (2**N_BITS - 1)
    on_minimum = np.all(np.abs(r.chain_x) <= step / 2 + 1e-12, axis=1)
    assert on_minimum.sum() >= 7
