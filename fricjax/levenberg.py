"""Levenberg–Marquardt on an explicit Jacobian, as an ``init``/``step`` pair.

For residuals that hand over ``r`` and ``J = ∂r/∂θ`` together (the output-error residual
builds J from K + 2 forward tangents, :meth:`fricjax.output_error.OutputError.value_and_jacobian`),
this minimises ``E(θ) = ‖r(θ)‖²`` inside the box ``[lower, upper]`` through the box transform
of :class:`fricjax.refine.RefineSettings` (sine by default, θ = T(z)), with the Jacobian in
z ``J_z = J·diag(T'(z))``. It is optimistix's ``LevenbergMarquardt`` (damped Newton step,
classical trust region, Cauchy termination) written on that Jacobian, with geodesic
acceleration (Transtrum & Sethna 2012, arXiv:1201.5885)::

    (J_zᵀJ_z + μ·I) h = −J_zᵀ r,   μ = 1/s,  s = 1 at the start
    r_vv = (2/δ)·((r(z + δ·h) − r)/δ − J_z h),   δ = 0.1
    (J_zᵀJ_z + μ·I) a = −J_zᵀ r_vv,   trial point z + h + a/2

solved by Cholesky ([D, D], D the length of θ). ``h`` is the first-order step, ``a`` the
second-order correction that bends it along the residual's curvature, from one extra
residual at the probe ``z + δ·h``. Why: the output-error cost of a friction model is a
narrow curved valley (the drive's harmonics, Coulomb and viscous friction trade against
each other through the simulation), in which the straight damped step leaves the floor
after a short distance; the bent step follows it (seed model's 4 s twin, free segments:
70 steps to 3882.57 σ_x² instead of 130). With the predicted change
``P = ½‖r + J_z h‖² − ½‖r‖²`` (< 0) and the actual one ``Δ = ½‖r(z + h + a/2)‖² − ½‖r‖²``,
the step is accepted if ``Δ ≤ 0.01·P`` (else s ← s/4), and s ← 3.5·s if ``Δ < 0.99·P``. The
bend is trusted only while it is a correction, ``2‖a‖ ≤ 0.75‖h‖`` (Transtrum's α). A larger
one is dropped and the plain step h tried instead, accepted only where the linear model
predicted it well (``Δ ≤ 0.75·P``, the ratio at which trust-region methods call a step very
successful), and the trust region then shrinks (s ← s/4). Refusing such steps outright
(Transtrum's rule) shrank the trust region in the seed model's most curved directions until
the stop rules mistook the creep for convergence (0.272 s twin's base: 189.21 σ_x² in 48
steps, against 189.0016 in 34 this way and a reference minimum of 189.0015), while taking
them at the ordinary ratio 0.01 led a force-driven axis's fit from a poor start into a
region it never left (6.2·10⁶ σ_x² instead of 859; ``benchmarks/fit_convergence.py``).
A trial point costs two residuals, an accepted one a Jacobian more.

Two kinds of step (``accelerate``). The bend is a finite-difference estimate of the
residual's second derivative along h; where the simulation crosses stick–slip events
between z and the probe, that estimate describes the events, not the valley, and the bent
steps stall: EMPS's first 4 s with a quadratic drag stopped at 5.53·10¹⁰ σ_x² where scipy's
trust-region reflective method reaches 5.165·10¹⁰. Plain damped steps (no probe, no bend,
the classical acceptance ratio 0.01) reach 5.1645·10¹⁰ from the same start, but from a
poor start they can leave the valley (the force-driven axis's 6.2·10⁶ above). So a fit and
its restarts bend their steps until a restart gains little, and then the judge's rounds
(:func:`fricjax.diagnose.judge.converged`) restart with plain ones: near a minimum the plain
step cannot stray, and Levenberg–Marquardt never accepts an uphill step, so a restart never
loses (the twins, the force-driven axis and the stick-slip rig end where they did to 10⁻³
σ_x²; plain restarts alone, without the bent ones first, left a ram's base 0.73 σ_x²
higher).

Why not :func:`fricjax.refine.refine` (optimistix itself): optimistix linearises the residual
function, and linearising a residual whose forward derivative is a custom JVP that calls the
Jacobian program traces the tangent simulation again inside the linearisation (about 10 s of
Python per process for the seed model's superset, measured); here the Jacobian program is
called, never transformed. Components outside ``free`` get zero columns, so the damped step
leaves them at rest.

Stopping (``success``), at an accepted point, on either of two rules:

* the Gauss–Newton decrement ``δ = gᵀ(JᵀJ)⁺g = ‖P_J r‖²`` (g = Jᵀr in θ, P_J the
  projection on the columns of J) is below ``gain_tol``. δ is what the full Gauss–Newton
  step would take off E if the residual were linear, and ``√δ`` that step's length in
  the metric ``JᵀJ`` (standard errors, when r is in units of its noise's std): a
  point where it is small is a minimum to within that many standard errors, however the
  damping has been creeping. (Column-scaled and regularised so that exactly flat
  directions count as nothing to gain; where the full step leaves the box, the gain the
  box allows: :func:`_decrement`.)
* ``max_i |h_i|/(atol + rtol·|z_i|) < 1`` and ``max_i |Δr_i|/(atol + rtol·|r_i|) < 1``
  (optimistix's Cauchy rule with its max norm).

Otherwise the loop ends after ``max_steps`` iterations (``success`` False).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from fricjax.refine import Refined, RefineSettings, from_box, to_box

#: ``θ ↦ (r [m], J [m, D])``, both at θ (box units).
ValueAndJacobian = Callable[[Float[Array, " D"]], tuple[Float[Array, " m"], Float[Array, "m D"]]]
#: ``θ ↦ r [m]``.
Value = Callable[[Float[Array, " D"]], Float[Array, " m"]]


class LMState(NamedTuple):
    """The iteration's state: z [D] (transformed θ, the last accepted point), r [m],
    J [m, D] (in θ) and J_z [m, D] (in z, held columns zero) at z, E = ‖r‖², the
    Gauss–Newton decrement δ at z (module docstring), the trust-region step size s (damping
    μ = 1/s), the iteration count, E at the start, and
    whether it has stopped (``done``) by the tolerances (``converged``). Before the first
    iteration nothing is evaluated (``step`` 0): the first iteration evaluates the start."""

    z: Float[Array, " D"]
    r: Float[Array, " m"]
    jac: Float[Array, "m D"]
    jac_z: Float[Array, "m D"]
    cost: Float[Array, ""]
    decrement: Float[Array, ""]
    step_size: Float[Array, ""]
    step: Int[Array, ""]
    cost_start: Float[Array, ""]
    done: Bool[Array, ""]
    converged: Bool[Array, ""]


class LMProblem(NamedTuple):
    """What a step needs besides the state: the residual (value, and value with Jacobian),
    the box, the mask of components that move, the settings, and the decrement below which
    a point is a minimum (``gain_tol``, in units of E; 0: the Cauchy rule only), and whether
    steps are bent by geodesic acceleration (``accelerate``, a traced bool)."""

    value: Value
    value_and_jacobian: ValueAndJacobian
    lower: Float[Array, " D"]
    upper: Float[Array, " D"]
    free: Bool[Array, " D"]
    settings: RefineSettings
    gain_tol: float = 0.0
    accelerate: Bool[ArrayLike, ""] = True


# optimistix.ClassicalTrustRegion's constants
_LOW_CUTOFF, _HIGH_CUTOFF, _LOW_CONSTANT, _HIGH_CONSTANT = 0.01, 0.99, 0.25, 3.5
# geodesic acceleration (Transtrum & Sethna 2012): the probe's fraction δ of the step, and
# the largest 2‖a‖/‖h‖ a step may have (beyond it the second-order path is not trusted)
_PROBE, _ACCEL_RATIO = 0.1, 0.75
_BENT_CUTOFF = 0.75


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
    z = from_box(x0, pb.lower, pb.upper, s.transform, s.eps_bound)
    r, jac = jax.eval_shape(pb.value_and_jacobian, x0)
    nan = jnp.asarray(jnp.nan, r.dtype)
    return LMState(
        z=z,
        r=jnp.zeros(r.shape, r.dtype),
        jac=jnp.zeros(jac.shape, jac.dtype),
        jac_z=jnp.zeros(jac.shape, jac.dtype),
        cost=nan,
        decrement=nan,
        step_size=jnp.asarray(1.0, r.dtype),
        step=jnp.asarray(0),
        cost_start=nan,
        done=jnp.asarray(False),
        converged=jnp.asarray(False),
    )


def _decrement(
    jac: Float[Array, "m D"],
    r: Float[Array, " m"],
    theta: Float[Array, " D"],
    lower: Float[Array, " D"],
    upper: Float[Array, " D"],
    free: Bool[Array, " D"],
) -> Float[Array, ""]:
    """The Gauss–Newton decrement in θ that the box allows (module docstring).

    Unconstrained: ``δ = gᵀ(JᵀJ)⁺g`` (g = Jᵀr, the columns outside ``free`` removed),
    solved in column-scaled form (each column over its norm, ``1e-12`` added to the unit
    diagonal) so that its regularisation removes only the directions that are flat in every
    unit, not those whose parameters are merely small. Where the full step h leaves the box,
    the larger of two gains that stay inside it: the crossing components held (δ of the
    rest), or the whole step scaled to the box, ``α·h`` with the largest α ≤ 1 inside,
    which gains ``δ·α(2 − α)`` on the linear model. Both are taken in θ, where the box is a
    box: in the sine transform's z a long step folds back across a bound it never reached
    (a sloppy direction whose full Gauss–Newton step is long counted as crossing, and its
    gain as nothing: the seed model's base stopped 2.9 σ_x² above its minimum)."""

    def solve(j: Array) -> tuple[Array, Array]:
        norms = jnp.sqrt(jnp.sum(j * j, axis=0))
        scale = jnp.where(norms > 0, 1.0 / jnp.where(norms > 0, norms, 1.0), 0.0)
        js = j * scale[None, :]
        A = js.T @ js + 1e-12 * jnp.eye(js.shape[1], dtype=js.dtype)
        g = js.T @ r
        chol = jnp.linalg.cholesky(A)
        hs = -jax.scipy.linalg.cho_solve((chol, True), g)
        return -(g @ hs), hs * scale

    j = jnp.where(free[None, :], jac, 0.0)
    gain, h = solve(j)
    # fraction of h that stays inside the box, per component and for the whole step
    room = jnp.where(h > 0, upper - theta, jnp.where(h < 0, lower - theta, jnp.inf))
    ratio = jnp.where(h != 0, room / jnp.where(h != 0, h, 1.0), jnp.inf)
    crossing = ratio < 1.0
    alpha = jnp.clip(jnp.min(ratio), 0.0, 1.0)
    held, _ = solve(jnp.where(crossing[None, :], 0.0, j))
    scaled = gain * alpha * (2.0 - alpha)
    return jnp.where(jnp.any(crossing), jnp.maximum(held, scaled), gain)


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

    def damped(b: Array) -> Array:
        return jnp.where(pb.free & ~first, -jax.scipy.linalg.cho_solve((chol, True), b), 0.0)

    h = damped(g)
    accelerate = jnp.asarray(pb.accelerate, dtype=bool)

    def accel(r_probe: Array) -> Array:
        # geodesic acceleration: r_vv from the residual at z + δ·h (module docstring); a
        # bend larger than Transtrum's α of the step is not trusted, and dropped
        r_vv = (2.0 / _PROBE) * ((r_probe - r) / _PROBE - jac_z @ h)
        a = damped(jac_z.T @ r_vv)
        return jnp.where(too_bent(a) | ~accelerate, 0.0, a)

    def too_bent(a: Array) -> Array:
        return 2.0 * jnp.linalg.norm(a) > _ACCEL_RATIO * jnp.linalg.norm(h)

    def probe_then_trial(i: Array, carry: tuple[Array, Array]) -> tuple[Array, Array]:
        # one call site of the residual for both points: the probe, then the trial
        r_probe, _ = carry
        point = jnp.where(i == 0, state.z + _PROBE * h, state.z + h + 0.5 * accel(r_probe))
        r_i = pb.value(to_box(point, pb.lower, pb.upper, s.transform))
        return jnp.where(i == 0, r_i, r_probe), r_i

    # plain steps skip the probe: the loop starts at the trial
    r_probe, r_new = jax.lax.fori_loop(jnp.where(accelerate, 0, 1), 2, probe_then_trial, (r, r))
    a = accel(r_probe)
    bent = accelerate & too_bent(
        damped(jac_z.T @ ((2.0 / _PROBE) * ((r_probe - r) / _PROBE - jac_z @ h)))
    )
    z_new = state.z + h + 0.5 * a
    cost_new = jnp.sum(r_new * r_new)
    lin = r + jac_z @ h
    predicted = 0.5 * (jnp.sum(lin * lin) - state.cost)
    actual = 0.5 * (cost_new - state.cost)
    finite = jnp.all(jnp.isfinite(z_new)) & jnp.isfinite(cost_new)
    # a step whose bend was dropped is taken only where the linear model predicted it well
    cutoff = jnp.where(bent, _BENT_CUTOFF, _LOW_CUTOFF)
    accept = first | (finite & (actual <= cutoff * predicted))
    good = ~first & accept & (actual < _HIGH_CUTOFF * predicted) & (predicted < 0)
    # a step whose bend was dropped left the curved valley's floor: the next one shorter
    factor = jnp.where(good & ~bent, _HIGH_CONSTANT, jnp.where(accept & ~bent, 1.0, _LOW_CONSTANT))

    def take(st: LMState) -> LMState:
        x = to_box(z_new, pb.lower, pb.upper, s.transform)
        r1, jac1 = pb.value_and_jacobian(x)
        slope = jnp.where(pb.free, _slope(z_new, pb.lower, pb.upper, s.transform), 0.0)
        jac_z1 = jac1 * slope[None, :]
        return st._replace(
            z=z_new,
            r=r1,
            jac=jac1,
            jac_z=jac_z1,
            cost=cost_new,
            decrement=_decrement(jac1, r1, x, pb.lower, pb.upper, pb.free),
        )

    new = jax.lax.cond(accept, take, lambda st: st, state)
    small_z = jnp.max(jnp.abs(z_new - state.z) / (s.atol + s.rtol * jnp.abs(state.z))) < 1.0
    small_r = jnp.max(jnp.abs(r_new - r) / (s.atol + s.rtol * jnp.abs(r))) < 1.0
    cauchy = ~first & small_z & small_r
    converged = accept & (cauchy | (new.decrement < pb.gain_tol))
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
    gain_tol: float = 0.0,
    accelerate: Bool[ArrayLike, ""] = True,
) -> LMResult:
    """Minimise ‖r(θ)‖² from ``x0`` [D] inside [lower, upper], the components outside
    ``free`` held (module docstring); traceable (jit and vmap it from outside).

    ``cost_before`` is E at the start (moved ``eps_bound`` inside a bound it sits on);
    ``n_steps`` counts the iterations after the start's evaluation, at most ``max_steps``;
    ``success`` says the tolerances were met. Accepted steps only lower E, so the end point
    is never worse than the start; where E is not finite at the start, nothing moves.
    ``gain_tol``: the Gauss–Newton decrement that counts as converged (module docstring).
    ``accelerate`` (traced: one program for both): geodesic acceleration on, or plain
    damped steps (module docstring, "Two kinds of step")."""
    pb = LMProblem(value, value_and_jacobian, lower, upper, free, settings, gain_tol, accelerate)
    state = jax.lax.while_loop(lambda st: ~st.done, lambda st: lm_step(pb, st), lm_init(pb, x0))
    x = jnp.where(free, to_box(state.z, lower, upper, settings.transform), x0)
    refined = Refined(
        x=x,
        cost_before=state.cost_start,
        cost_after=state.cost,
        n_steps=state.step - 1,
        success=state.converged,
    )
    return LMResult(refined, state.r, state.jac)
