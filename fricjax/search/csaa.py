"""CSAA: simulated annealing in the continuous box (seed paper section 3.2.3, eq. 12).

Two neighbourhoods of a point ``x`` (shape ``[d]``, parameters in their own units, box
``[a, b]``):

* ``"csaa"`` (eq. 12): ``k`` of the ``d`` parameters, chosen at random without
  replacement, are redrawn uniformly in their bounds, ``B = rand·(b − a) + a``; the rest
  are kept. The paper's move: global, but at low temperature nearly all proposals are
  rejected, so refinement is slow.
* ``"csaa-gauss"``: a Gaussian step ``x + s·(b − a)·z``, ``z ~ N(0, I)``, on all
  parameters (``gauss_k = 0``) or on ``gauss_k`` random ones, folded back into the box by
  reflection. The scale ``s`` (a fraction of each range) adapts after every level,
  ``s ← s·exp(γ·(acceptance − target))``, so the step length follows the temperature.

Both accept with the Metropolis rule of :func:`fricjax.search.annealing.metropolis_rule`.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from fricjax.search.annealing import (
    Algorithm,
    AnnealSettings,
    ChainState,
    CostFn,
    commit,
    draw,
    keep_point,
    metropolis_rule,
    no_adaptation,
    normal_from_uniform,
    random_mask,
    reflect,
    start,
)

# The adapted Gaussian scale stays within these fractions of the parameter ranges: below
# 1e-12 steps vanish in float64 rounding, above 1 the reflection makes it a uniform draw.
SCALE_MIN = 1e-12
SCALE_MAX = 1.0


def init(
    key: Array,
    x0: Float[ArrayLike, " d"],
    cost0: Float[ArrayLike, ""],
    lower: Float[ArrayLike, " d"],
    upper: Float[ArrayLike, " d"],
    settings: AnnealSettings,
) -> ChainState:
    """Chain state at ``x0`` with ``cost0 = f(x0)``; ``adapt`` is the Gaussian step as a
    fraction of the ranges (``gauss_scale0``; unused by eq. 12)."""
    x0 = jnp.asarray(x0)
    return start(key, x0, cost0, jnp.asarray(settings.gauss_scale0, dtype=x0.dtype))


def redraw(
    u: Float[ArrayLike, " d+k"],
    x: Float[ArrayLike, " d"],
    lower: Float[ArrayLike, " d"],
    upper: Float[ArrayLike, " d"],
    k: int,
) -> Float[Array, " d"]:
    """Eq. 12 neighbour: ``min(k, d)`` random parameters redrawn as ``rand·(b − a) + a``.

    ``u``: ``d + min(k, d)`` uniforms in [0, 1) (``d`` values, the ``rand`` of eq. 12,
    then the choice of the parameters).
    """
    x = jnp.asarray(x)
    u = jnp.asarray(u)
    d = x.shape[0]
    mask = random_mask(u[d:], d, min(k, d))
    fresh = jnp.clip(lower + u[:d] * (jnp.asarray(upper) - lower), lower, upper)
    return jnp.where(mask, fresh, x)


def gauss_proposal(
    u: Float[ArrayLike, " d+k"],
    x: Float[ArrayLike, " d"],
    lower: Float[ArrayLike, " d"],
    upper: Float[ArrayLike, " d"],
    scale: Float[ArrayLike, ""],
    k: int,
) -> Float[Array, " d"]:
    """Gaussian neighbour ``reflect(x + scale·(b − a)·z)``, ``z ~ N(0, 1)``, on ``k``
    random parameters (all of them if ``k == 0``).

    ``u``: ``d + k'`` uniforms in [0, 1) (``z`` by inverse CDF, then the choice of the
    ``k' = min(k, d)`` parameters; ``k' = 0`` if all move).
    """
    x = jnp.asarray(x)
    u = jnp.asarray(u)
    d = x.shape[0]
    mask = random_mask(u[d:], d, d if k == 0 else min(k, d))
    z = normal_from_uniform(u[:d])
    moved = x + jnp.where(mask, scale * (jnp.asarray(upper) - lower) * z, 0.0)
    return reflect(moved, lower, upper)


def _n_choice(d: int, k: int) -> int:
    """Uniforms needed to choose ``k`` of ``d`` parameters (none if all are taken)."""
    return 0 if k >= d else k


def step(
    state: ChainState,
    cost_fn: CostFn,
    temperature: Float[ArrayLike, ""],
    lower: Float[Array, " d"],
    upper: Float[Array, " d"],
    settings: AnnealSettings,
) -> ChainState:
    """One eq. 12 proposal (``settings.csaa_k`` parameters) and Metropolis decision."""
    n = state.x.shape[0] + _n_choice(state.x.shape[0], settings.csaa_k)
    key, u = draw(state.key, n + 1, state.x.dtype)
    x_new = redraw(u[:n], state.x, lower, upper, settings.csaa_k)
    cost_new = cost_fn(x_new)
    accepted = metropolis_rule(u[n], state.cost, cost_new, temperature)
    return commit(state._replace(key=key), accepted, x_new, cost_new)


def gauss_step(
    state: ChainState,
    cost_fn: CostFn,
    temperature: Float[ArrayLike, ""],
    lower: Float[Array, " d"],
    upper: Float[Array, " d"],
    settings: AnnealSettings,
) -> ChainState:
    """One Gaussian proposal at the chain's current scale and Metropolis decision."""
    d = state.x.shape[0]
    n = d + (0 if settings.gauss_k == 0 else _n_choice(d, settings.gauss_k))
    key, u = draw(state.key, n + 1, state.x.dtype)
    x_new = gauss_proposal(u[:n], state.x, lower, upper, state.adapt, settings.gauss_k)
    cost_new = cost_fn(x_new)
    accepted = metropolis_rule(u[n], state.cost, cost_new, temperature)
    return commit(state._replace(key=key), accepted, x_new, cost_new)


def adapt_scale(
    state: ChainState, acceptance: Float[ArrayLike, ""], settings: AnnealSettings
) -> ChainState:
    """End of level: ``s ← clip(s·exp(γ·(acceptance − target)), 1e-12, 1)``.

    A chain whose current cost is not finite (it started in a forbidden region) counts as
    fully accepting: its steps widen until they reach finite ground instead of shrinking
    to nothing.
    """
    acceptance = jnp.where(jnp.isfinite(state.cost), acceptance, 1.0)
    factor = jnp.exp(settings.gauss_gamma * (acceptance - settings.gauss_target))
    scale = jnp.clip(state.adapt * factor, SCALE_MIN, SCALE_MAX)
    return state._replace(adapt=scale.astype(state.adapt.dtype))


#: Eq. 12 redraw of ``csaa_k`` parameters (method ``"csaa"``).
REDRAW = Algorithm("csaa", keep_point, init, step, no_adaptation)
#: Adaptive Gaussian steps with reflection (method ``"csaa-gauss"``).
GAUSS = Algorithm("csaa-gauss", keep_point, init, gauss_step, adapt_scale)
