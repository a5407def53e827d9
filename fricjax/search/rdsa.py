"""RDSA: random direction search (seed paper section 3.1, eq. 6).

    x^(k+1) = x^(k) + α·s^(k)

``s`` is a random unit direction in the range-scaled space (a normalised Gaussian vector
``z/|z|``, multiplied by each parameter's range ``b − a``), ``α`` the step factor as a
fraction of the ranges. The move is greedy: only a finite, strictly better candidate is
taken. ``α`` grows (×grow) after each success and shrinks (×shrink) after ``patience``
consecutive failures (grows instead while the current cost is not finite); the box is
kept by reflection.

RDSA ignores the temperature, but runs on the same level/step structure as the annealing
algorithms so that their traces (cost against evaluations) are comparable.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Int

from fricjax.search.annealing import (
    Algorithm,
    AnnealSettings,
    ChainState,
    CostFn,
    commit,
    draw,
    greedy_accept,
    keep_point,
    no_adaptation,
    normal_from_uniform,
    reflect,
    start,
)

# α stays within these fractions of the ranges: below 1e-12 a step is lost in float64
# rounding, beyond 1 every step reflects off the box.
ALPHA_MIN = 1e-12
ALPHA_MAX = 1.0


class Step(NamedTuple):
    """RDSA's own chain state: ``alpha []``, the step factor (a fraction of the ranges),
    and ``n_fail []``, the consecutive failures since the last success or shrink. The
    chain's ``x`` is always its best point."""

    alpha: Float[Array, ""]
    n_fail: Int[Array, ""]


def init(
    key: Array,
    x0: Float[ArrayLike, " d"],
    cost0: Float[ArrayLike, ""],
    lower: Float[ArrayLike, " d"],
    upper: Float[ArrayLike, " d"],
    settings: AnnealSettings,
) -> ChainState:
    """Chain state at ``x0`` with ``cost0 = f(x0)`` and ``α = rdsa_alpha0``."""
    x0 = jnp.asarray(x0)
    alpha = jnp.asarray(settings.rdsa_alpha0, dtype=x0.dtype)
    return start(key, x0, cost0, Step(alpha, jnp.zeros((), dtype=int)))


def direction(u: Float[ArrayLike, " d"]) -> Float[Array, " d"]:
    """Uniform random unit vector in ``d`` dimensions (a normalised Gaussian vector) from
    ``d`` uniforms in [0, 1)."""
    z = normal_from_uniform(u)
    return z / jnp.linalg.norm(z)


def step(
    state: ChainState,
    cost_fn: CostFn,
    temperature: Float[ArrayLike, ""],
    lower: Float[Array, " d"],
    upper: Float[Array, " d"],
    settings: AnnealSettings,
) -> ChainState:
    """One eq. 6 trial ``reflect(x + α·(b − a)·s)``, greedy acceptance, α update.

    ``temperature`` is ignored (same signature as the annealing steps).
    """
    del temperature
    key, u = draw(state.key, state.x.shape[0], state.x.dtype)
    s = direction(u)
    alpha0, n_fail0 = state.adapt
    x_new = reflect(state.x + alpha0 * (upper - lower) * s, lower, upper)
    cost_new = cost_fn(x_new)
    accepted = greedy_accept(state.cost, cost_new)
    n_fail = jnp.where(accepted, 0, n_fail0 + 1)
    shrink = n_fail >= settings.rdsa_patience
    # A chain stranded on a non-finite cost widens its step on failures instead, until it
    # reaches finite ground.
    stranded = ~jnp.isfinite(state.cost)
    alpha = jnp.where(
        accepted | (stranded & shrink),
        alpha0 * settings.rdsa_grow,
        jnp.where(shrink, alpha0 * settings.rdsa_shrink, alpha0),
    )
    state = commit(state._replace(key=key), accepted, x_new, cost_new)
    alpha = jnp.clip(alpha, ALPHA_MIN, ALPHA_MAX).astype(alpha0.dtype)
    return state._replace(adapt=Step(alpha, jnp.where(shrink, 0, n_fail)))


#: Random direction search (method ``"rdsa"``).
ALGORITHM = Algorithm("rdsa", keep_point, init, step, no_adaptation)
