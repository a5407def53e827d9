"""Levenberg–Marquardt on an explicit Jacobian, as an ``init``/``step`` pair.

For residuals that hand over ``r`` and ``J = ∂r/∂θ`` together (the output-error residual
builds J from K + 2 forward tangents, :meth:`fricjax.output_error.OutputError.value_and_jacobian`),
this minimises ``E(θ) = ‖r(θ)‖²`` inside the box ``[lower, upper]`` through the box transform
of :class:`fricjax.refine.RefineSettings` (sine by default, θ = T(z)), with the Jacobian in
z ``J_z = J·diag(T'(z))``. It is optimistix's ``LevenbergMarquardt`` (damped Newton step,
classical trust region, Cauchy termination) written on that Jacobian::

    (J_zᵀJ_z + μ·I) h = −J_zᵀ r,   μ = 1/s,  s = 1 at the start

solved by Cholesky ([D, D], D the length of θ). With the predicted change
``P = ½‖r + J_z h‖² − ½‖r‖²`` (< 0) and the actual one ``Δ = ½‖r(z + h)‖² − ½‖r‖²``, the
step is accepted if ``Δ ≤ 0.01·P`` (else s ← s/4) and s ← 3.5·s if ``Δ < 0.99·P``. A trial
point costs one residual, an accepted one a Jacobian more.

Why not :func:`fricjax.refine.refine` (optimistix itself): optimistix linearises the residual
function, and linearising a residual whose forward derivative is a custom JVP that calls the
Jacobian program traces the tangent simulation again inside the linearisation (about 10 s of
Python per process for the seed model's superset, measured); here the Jacobian program is
called, never transformed. Components outside ``free`` get zero columns, so the damped step
leaves them at rest.

Stopping (``success``), on an accepted step: ``max_i |h_i|/(atol + rtol·|z_i|) < 1`` and
``max_i |Δr_i|/(atol + rtol·|r_i|) < 1`` (optimistix's Cauchy rule with its max norm).
Otherwise the loop ends after ``max_steps`` iterations (``success`` False).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from fricjax.refine import Refined, RefineSettings, _from_box, _to_box

#: ``θ ↦ (r [m], J [m, D])``, both at θ (box units).
ValueAndJacobian = Callable[[Float[Array, " D"]], tuple[Float[Array, " m"], Float[Array, "m D"]]]
#: ``θ ↦ r [m]``.
Value = Callable[[Float[Array, " D"]], Float[Array, " m"]]


class LMState(NamedTuple):
    """The iteration's state: z [D] (transformed θ, the last accepted point), r [m],
    J [m, D] (in θ) and J_z [m, D] (in z, held columns zero) at z, E = ‖r‖², the
    trust-region step size s (damping μ = 1/s), the iteration count, E at the start, and
    whether it has stopped (``done``) by the tolerances (``converged``). Before the first
    iteration nothing is evaluated (``step`` 0): the first iteration evaluates the start."""

    z: Float[Array, " D"]
    r: Float[Array, " m"]
    jac: Float[Array, "m D"]
    jac_z: Float[Array, "m D"]
    cost: Float[Array, ""]
    step_size: Float[Array, ""]
    step: Int[Array, ""]
    cost_start: Float[Array, ""]
    done: Bool[Array, ""]
    converged: Bool[Array, ""]


class LMProblem(NamedTuple):
    """What a step needs besides the state: the residual (value, and value with Jacobian),
    the box, the mask of components that move, and the settings."""

    value: Value
    value_and_jacobian: ValueAndJacobian
    lower: Float[Array, " D"]
    upper: Float[Array, " D"]
    free: Bool[Array, " D"]
    settings: RefineSettings


# optimistix.ClassicalTrustRegion's constants
_LOW_CUTOFF, _HIGH_CUTOFF, _LOW_CONSTANT, _HIGH_CONSTANT = 0.01, 0.99, 0.25, 3.5


def _slope(z: Array, lower: Array, upper: Array, transform: str) -> Array:
    """dθ/dz of the box transform."""
    if transform == "sine":
        return 0.5 * (upper - lower) * jnp.cos(z)
    if transform == "sigmoid":
        s = jax.nn.sigmoid(z)
        return (upper - lower) * s * (1.0 - s)
    return jnp.ones_like(z)


def lm_init(pb: LMProblem, x0: Float[Array, " D"]) -> LMState:
    """The state at ``x0`` [D] (moved ``eps_bound`` inside a bound it sits on), not yet
    evaluated: the residual's shapes only, so that the loop holds the one call of the
    Jacobian program (each call site compiles the tangent simulation again)."""
    s = pb.settings
    z = _from_box(x0, pb.lower, pb.upper, s.transform, s.eps_bound)
    r, jac = jax.eval_shape(pb.value_and_jacobian, x0)
    nan = jnp.asarray(jnp.nan, r.dtype)
    return LMState(
        z=z,
        r=jnp.zeros(r.shape, r.dtype),
        jac=jnp.zeros(jac.shape, jac.dtype),
        jac_z=jnp.zeros(jac.shape, jac.dtype),
        cost=nan,
        step_size=jnp.asarray(1.0, r.dtype),
        step=jnp.asarray(0),
        cost_start=nan,
        done=jnp.asarray(False),
        converged=jnp.asarray(False),
    )


def lm_step(pb: LMProblem, state: LMState) -> LMState:
    """One iteration (module docstring): solve the damped system, try the point, accept it
    (then take the Jacobian there) or shrink the trust region, test the tolerances. The
    first iteration tries the start itself and always takes it."""
    s = pb.settings
    first = state.step == 0
    jac_z, r = state.jac_z, state.r
    A = jac_z.T @ jac_z
    g = jac_z.T @ r
    chol = jnp.linalg.cholesky(A + jnp.eye(A.shape[0], dtype=A.dtype) / state.step_size)
    h = jnp.where(pb.free & ~first, -jax.scipy.linalg.cho_solve((chol, True), g), 0.0)
    z_new = state.z + h
    r_new = pb.value(_to_box(z_new, pb.lower, pb.upper, s.transform))
    cost_new = jnp.sum(r_new * r_new)
    lin = r + jac_z @ h
    predicted = 0.5 * (jnp.sum(lin * lin) - state.cost)
    actual = 0.5 * (cost_new - state.cost)
    finite = jnp.all(jnp.isfinite(h)) & jnp.isfinite(cost_new)
    accept = first | (finite & (actual <= _LOW_CUTOFF * predicted))
    good = ~first & accept & (actual < _HIGH_CUTOFF * predicted) & (predicted < 0)
    factor = jnp.where(good, _HIGH_CONSTANT, jnp.where(accept, 1.0, _LOW_CONSTANT))

    def take(st: LMState) -> LMState:
        x = _to_box(z_new, pb.lower, pb.upper, s.transform)
        r1, jac1 = pb.value_and_jacobian(x)
        slope = jnp.where(pb.free, _slope(z_new, pb.lower, pb.upper, s.transform), 0.0)
        return st._replace(z=z_new, r=r1, jac=jac1, jac_z=jac1 * slope[None, :], cost=cost_new)

    new = jax.lax.cond(accept, take, lambda st: st, state)
    small_z = jnp.max(jnp.abs(h) / (s.atol + s.rtol * jnp.abs(state.z))) < 1.0
    small_r = jnp.max(jnp.abs(r_new - r) / (s.atol + s.rtol * jnp.abs(r))) < 1.0
    converged = ~first & accept & small_z & small_r
    step = state.step + 1
    step_size = state.step_size * factor
    return new._replace(
        step_size=step_size,
        step=step,
        cost_start=jnp.where(first, cost_new, state.cost_start),
        done=converged | (step > s.max_steps) | ~(step_size > 0) | ~jnp.isfinite(new.cost),
        converged=converged,
    )


class LMResult(NamedTuple):
    """:class:`fricjax.refine.Refined` of the fit and the residual r [m] and its Jacobian
    J [m, D] (in θ, held columns as the residual gives them) at its end point."""

    refined: Refined
    r: Float[Array, " m"]
    jac: Float[Array, "m D"]


def levenberg_marquardt(
    value: Value,
    value_and_jacobian: ValueAndJacobian,
    x0: Float[Array, " D"],
    lower: Float[Array, " D"],
    upper: Float[Array, " D"],
    free: Bool[Array, " D"],
    settings: RefineSettings,
) -> LMResult:
    """Minimise ‖r(θ)‖² from ``x0`` [D] inside [lower, upper], the components outside
    ``free`` held (module docstring); traceable (jit and vmap it from outside).

    ``cost_before`` is E at the start (moved ``eps_bound`` inside a bound it sits on);
    ``n_steps`` counts the iterations after the start's evaluation, at most ``max_steps``;
    ``success`` says the tolerances were met. Accepted steps only lower E, so the end point
    is never worse than the start; where E is not finite at the start, nothing moves."""
    pb = LMProblem(value, value_and_jacobian, lower, upper, free, settings)
    state = jax.lax.while_loop(lambda st: ~st.done, lambda st: lm_step(pb, st), lm_init(pb, x0))
    x = jnp.where(free, _to_box(state.z, lower, upper, settings.transform), x0)
    refined = Refined(
        x=x,
        cost_before=state.cost_start,
        cost_after=state.cost,
        n_steps=state.step - 1,
        success=state.converged,
    )
    return LMResult(refined, state.r, state.jac)
