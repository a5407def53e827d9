"""DSAA: simulated annealing on a binary coding of the box (seed paper eq. 13–14).

Each of the ``d`` parameters is coded in ``n`` bits (eq. 13; ``n = 10`` in the paper) over
its bounds ``[a, b]``: the integer ``i ∈ 0..2^n − 1`` stands for

    value = a + (b − a)·i/(2^n − 1),

read from the bits most-significant first, in plain binary or in Gray code (adjacent
integers differ in one Gray bit). A neighbour (eq. 14) differs in at most ``k`` bits: a
number ``m`` is drawn uniformly in ``1..k`` and ``m`` distinct positions among all ``d·n``
bits are flipped; the bits are decoded and the cost evaluated there.

Quantisation is intrinsic: DSAA only visits grid points, ``(b − a)/(2^n − 1)`` apart, so
its best point is a grid point and its accuracy is limited by the grid (the paper's
reason why CSAA ends more accurate than DSAA).

Binary or Gray: plain binary has Hamming cliffs (511 = 0111111111 and 512 = 1000000000
are neighbours in value but ten flips apart), and a chain that freezes on the wrong side
of one stays there. On a 5-D quadratic (8 chains, 6·10³ steps each) Gray DSAA put every
chain on the grid point nearest the minimum in all trial seeds; binary DSAA rarely did,
its best chain ending up to 0.3 of 6 (≈ 50 grid steps) away. Prefer ``"dsaa-gray"``;
``"dsaa"`` is the paper's code.
"""

from __future__ import annotations

import functools

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from fricjax.search.annealing import (
    Algorithm,
    AnnealSettings,
    ChainState,
    CostFn,
    commit,
    draw,
    metropolis_rule,
    no_adaptation,
    random_subset,
    start,
)


def _powers(n_bits: int) -> Int[Array, " n"]:
    return 2 ** jnp.arange(n_bits - 1, -1, -1, dtype=jnp.int64)


def to_index(
    x: Float[ArrayLike, "*batch d"],
    lower: Float[ArrayLike, " d"],
    upper: Float[ArrayLike, " d"],
    n_bits: int,
) -> Int[Array, "*batch d"]:
    """Nearest grid integer ``round((x − a)/(b − a)·(2^n − 1))``, clipped to ``0..2^n − 1``."""
    top = 2**n_bits - 1
    lower = jnp.asarray(lower)
    scaled = (jnp.asarray(x) - lower) / (jnp.asarray(upper) - lower) * top
    return jnp.clip(jnp.round(scaled), 0, top).astype(jnp.int64)


def from_index(
    index: Int[ArrayLike, "*batch d"],
    lower: Float[ArrayLike, " d"],
    upper: Float[ArrayLike, " d"],
    n_bits: int,
) -> Float[Array, "*batch d"]:
    """Grid value ``a + (b − a)·i/(2^n − 1)``, clipped so rounding never leaves the box."""
    lower = jnp.asarray(lower)
    upper = jnp.asarray(upper)
    value = lower + (upper - lower) * jnp.asarray(index).astype(lower.dtype) / (2**n_bits - 1)
    return jnp.clip(value, lower, upper)


def index_to_bits(
    index: Int[ArrayLike, "*batch d"], n_bits: int, gray: bool
) -> Bool[Array, "*batch d n"]:
    """Bits of integers (most significant first); Gray code ``g = i ⊕ (i >> 1)`` if ``gray``."""
    index = jnp.asarray(index, dtype=jnp.int64)
    code = index ^ (index >> 1) if gray else index
    shifts = jnp.arange(n_bits - 1, -1, -1, dtype=jnp.int64)
    return ((code[..., None] >> shifts) & 1).astype(bool)


def bits_to_index(bits: Bool[ArrayLike, "*batch d n"], gray: bool) -> Int[Array, "*batch d"]:
    """Integers of bit rows; Gray bits are turned to binary by a prefix XOR first."""
    bits = jnp.asarray(bits).astype(jnp.int64)
    if gray:
        bits = jnp.cumsum(bits, axis=-1) % 2
    return jnp.sum(bits * _powers(bits.shape[-1]), axis=-1)


def encode(
    x: Float[ArrayLike, "*batch d"],
    lower: Float[ArrayLike, " d"],
    upper: Float[ArrayLike, " d"],
    n_bits: int,
    gray: bool = False,
) -> Bool[Array, "*batch d n"]:
    """Eq. 13 code of the grid point nearest to ``x`` (error ≤ half a grid step)."""
    return index_to_bits(to_index(x, lower, upper, n_bits), n_bits, gray)


def decode(
    bits: Bool[ArrayLike, "*batch d n"],
    lower: Float[ArrayLike, " d"],
    upper: Float[ArrayLike, " d"],
    gray: bool = False,
) -> Float[Array, "*batch d"]:
    """Parameter values of a code: ``a + (b − a)·i/(2^n − 1)``, ``n = bits.shape[-1]``."""
    bits = jnp.asarray(bits)
    return from_index(bits_to_index(bits, gray), lower, upper, bits.shape[-1])


def snap(
    x: Float[Array, " d"],
    lower: Float[Array, " d"],
    upper: Float[Array, " d"],
    settings: AnnealSettings,
) -> Float[Array, " d"]:
    """Nearest grid point (the ``prepare`` of DSAA: start points must lie on the grid)."""
    return from_index(to_index(x, lower, upper, settings.n_bits), lower, upper, settings.n_bits)


def flip_bits(u: Float[ArrayLike, " k+1"], bits: Bool[Array, "d n"], k: int) -> Bool[Array, "d n"]:
    """Eq. 14 neighbour: flip ``m ~ U{1..k'}`` distinct bits among all ``d·n``,
    ``k' = min(k, d·n)``.

    ``u``: ``k' + 1`` uniforms in [0, 1) (the first picks ``m``, the others the bits).
    """
    u = jnp.asarray(u)
    size = bits.size
    k = min(k, size)
    m = 1 + jnp.minimum(jnp.floor(u[0] * k), k - 1).astype(int)
    positions = random_subset(u[1 : k + 1], size, m)
    flips = jnp.zeros((size,), dtype=bool).at[positions].set(True, mode="drop")
    return bits ^ flips.reshape(bits.shape)


def init(
    key: Array,
    x0: Float[ArrayLike, " d"],
    cost0: Float[ArrayLike, ""],
    lower: Float[ArrayLike, " d"],
    upper: Float[ArrayLike, " d"],
    settings: AnnealSettings,
    gray: bool = False,
) -> ChainState:
    """Chain state at the grid point nearest ``x0``, its code ``[d, n]`` (most significant
    bit first) as ``adapt``; ``cost0`` must be the cost of that grid point (``x0`` already
    snapped with :func:`snap`, as ``run_chains`` does)."""
    bits = encode(x0, lower, upper, settings.n_bits, gray)
    return start(key, decode(bits, lower, upper, gray), cost0, bits)


def step(
    state: ChainState,
    cost_fn: CostFn,
    temperature: Float[ArrayLike, ""],
    lower: Float[Array, " d"],
    upper: Float[Array, " d"],
    settings: AnnealSettings,
    gray: bool = False,
) -> ChainState:
    """One bit-flip proposal (``settings.dsaa_k``), decode, Metropolis decision."""
    n = min(settings.dsaa_k, state.adapt.size) + 1
    key, u = draw(state.key, n + 1, state.x.dtype)
    bits_new = flip_bits(u[:n], state.adapt, settings.dsaa_k)
    x_new = decode(bits_new, lower, upper, gray)
    cost_new = cost_fn(x_new)
    accepted = metropolis_rule(u[n], state.cost, cost_new, temperature)
    state = commit(state._replace(key=key), accepted, x_new, cost_new)
    return state._replace(adapt=jnp.where(accepted, bits_new, state.adapt))


#: Plain binary code (method ``"dsaa"``).
BINARY = Algorithm(
    "dsaa",
    snap,
    functools.partial(init, gray=False),
    functools.partial(step, gray=False),
    no_adaptation,
)
#: Gray code (method ``"dsaa-gray"``).
GRAY = Algorithm(
    "dsaa-gray",
    snap,
    functools.partial(init, gray=True),
    functools.partial(step, gray=True),
    no_adaptation,
)
