"""Forward simulation of the force balance ``m·ẍ = F_p(t, x, ẋ, u) − F_f(t, x, ẋ)``
(seed eq. 3/5) with exact stiction: the body is either sliding or stuck, never chattering.

Scheme
------
The record's sample times ``t`` [s], shape [n], are assumed uniform (``dt = t[1] − t[0]``;
the actual ``t[k]`` anchor each interval). Every interval is split into ``substeps`` sub-steps
of length ``h = dt/substeps`` (outer ``lax.scan`` over intervals, inner ``lax.fori_loop``
over sub-steps). Between two samples the recorded input ``u`` is interpolated linearly:
``u(τ) = u[k] + (u[k+1] − u[k])·(τ − t[k])/dt`` (first-order hold, i.e. ``numpy.interp``
of the record), so the drive is continuous and smooth inside every interval.

The body is in one of two modes:

* **sliding** in direction ``d = sgn(v) = ±1``. Friction has no discontinuity as long as
  ``sgn(v)`` stays ``d``, so the smooth ODE of that branch is advanced with classical RK4.
  RK4 stages that overshoot ``v = 0`` evaluate a C³ extension of the branch's friction
  across ``v = 0`` (Hestenes reflection ``F_d(v) = Σ_j c_j·F_f(μ_j·v)``, μ = −1, −2, −3, −4,
  c = 10, −20, 15, −4, matching value and three derivatives of the one-sided limit
  ``F_f(0^d) = static(d)``); they never see the jump of ``sgn``. If ``d·v`` is ≤ 0 at the
  end of the step, ``v`` reached zero inside it: the zero is located on the cubic Hermite
  interpolant of ``v`` built from ``v, ẍ`` at both ends (regula falsi, Illinois variant,
  fixed iteration count, then one Newton step), ``x`` is advanced to it by the exact
  integral of that cubic, and ``v`` is set to exactly 0. The body is then at rest and the
  stick/slip test below decides the rest of the sub-step.
* **stuck** (``v = 0``). The body stays put while ``|F_p| ≤ |static(sgn F_p)|`` (the friction
  can hold the drive). If the drive exceeds the limit at the start of the remaining
  interval, the body breaks away at once in the drive's direction; if it exceeds it only at
  the end, the breakaway instant is located by regula falsi (Illinois) on
  ``d·F_p(τ) − |static(d, τ)|`` with ``x`` fixed and ``v = 0``, and the rest of the sub-step
  is integrated in the sliding mode. Stuck samples have ``v == 0`` and ``x`` unchanged
  *bit for bit*.

A sub-step is therefore: slide (may stop) → stick/slip test (may break away) → slide (may
stop) → stick/slip test. This resolves a stop, a reversal (stop followed by immediate
breakaway the other way) and a breakaway anywhere inside a sub-step, and up to three such
events in one sub-step (e.g. stop, breakaway, stop); a breakaway that would be the fourth
event in the same sub-step (``h`` = 0.125 ms at 1 kHz and 8 sub-steps) is postponed to the
next sub-step boundary.

Order of accuracy
-----------------
Away from events: classical RK4, global error O(h⁴). At events: the Hermite interpolant
and the C³ friction extension are O(h⁴) accurate, the root finders converge to rounding, so
every stop, reversal and breakaway adds an O(h⁴) (position and velocity) error; the scheme
is fourth-order overall (measured on the seed's CSAA model: the error falls 250× from 4 to
16 sub-steps), as long as the drive and the friction branches are smooth up to ``v = 0⁺``.
For Stribeck friction that holds for integer ``delta`` (``delta = 1``, Tustin, in the seed);
otherwise the branch is only C^⌊δ⌋ at ``v = 0⁺`` (infinite slope for ``delta < 1``) and the
order drops near stops. ``u`` enters through its linear interpolant, reproduced exactly (its
kinks sit on sub-step boundaries).

Everything is written with ``jnp.where`` and ``lax.cond`` inside the scan, so
:func:`simulate` can be ``jit``-compiled, ``vmap``-ed over parameter dicts and
differentiated with respect to them (forward and reverse mode). The root iterations run on
``stop_gradient``-ed values and end with one Newton step on the live parameters, which
carries the implicit-function derivative of every event time (checked against finite
differences) without unrolling the iterations in reverse mode.

Cost of a step
--------------
Events are rare: on most sub-steps the body slides without reaching ``v = 0``, or stays
stuck under a drive it can hold. Each part of the event machinery therefore sits behind a
``lax.cond`` and runs only when it has work: the RK4 slide only for a moving body with time
left (so the second phase of a quiet sub-step costs nothing), the stop location only when
the slide ended with ``d·v ≤ 0``, the stick/slip test only for a body at rest, the
breakaway location only when the drive overcomes the static limit inside the interval. A
quiet sliding sub-step costs one RK4 step (5 force evaluations); a quiet stuck one the
drive and the static limits at the interval's ends, twice (one test per phase). The skipped branch
returns exactly what the ``jnp.where`` selections would have picked, so values and
derivatives are unchanged (tested against the path that evaluates everything, to rounding).

Under ``vmap`` (parameter batches, the output error's segments) a ``lax.cond`` on a batched
predicate would become a select that evaluates both branches. The predicates are therefore
reduced over the batch first (:func:`_for_all_members`, a ``custom_vmap``): the machinery is
skipped when no member needs it, and otherwise runs for all (it is right for idle members
too). Forward tangents (``jax.jvp`` vmapped over tangent directions, as the output error
does) keep the branch: the predicate is a primal value, the same for every tangent, and
reduced over the batch it stays one branch.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from fricjax.errors import FricjaxError, where
from fricjax.model.system import Model
from fricjax.model.term import Signals
from fricjax.programs import stored

# Hestenes reflection: Σ_j c_j·μ_j^k = 1 for k = 0..3, so the extension matches the branch's
# value and first three derivatives at v = 0 (smooth enough for RK4 and the cubic Hermite).
_EXT_MU = (-1.0, -2.0, -3.0, -4.0)
_EXT_C = (10.0, -20.0, 15.0, -4.0)
# Classical RK4 as a Butcher tableau; row 4 holds the weights b, so "stage" 4 evaluates ẍ at
# the end of the step, which the Hermite interpolant needs.
_RK_A = np.array(
    [
        [0.0, 0.0, 0.0, 0.0, 0.0],
        [0.5, 0.0, 0.0, 0.0, 0.0],
        [0.0, 0.5, 0.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0, 0.0],
        [1 / 6, 1 / 3, 1 / 3, 1 / 6, 0.0],
    ]
)
_RK_C = np.array([0.0, 0.5, 0.5, 1.0, 1.0])
# Illinois regula falsi converges superlinearly; 12 iterations reach rounding on a sub-step.
_ROOT_ITERS = 12
# (slide, stick/slip test) pairs per sub-step: the events a sub-step can resolve (see above).
_PHASES = 2


class Trajectory(NamedTuple):
    """Simulated motion at the sample times, each of shape [n].

    x [m] position, v [m/s] velocity, a [m/s²] acceleration ``(F_p − F_f)/m`` evaluated on
    the sampled state: 0 while stuck, the one-sided value ``(F_p − static(sgn F_p))/m`` at a
    sample where the body is at rest but the drive already exceeds the static limit.
    """

    x: Float[Array, " n"]
    v: Float[Array, " n"]
    a: Float[Array, " n"]


class _Interval(NamedTuple):
    """Data of one sample interval: start time [s], input at the start, input slope [u/s]."""

    t0: Float[Array, ""]
    u0: Float[Array, ""]
    du: Float[Array, ""]


@jax.custom_batching.custom_vmap
def _for_all_members(flag: Bool[Array, ""]) -> Bool[Array, ""]:
    """``flag``; under ``vmap``, whether it holds for every member of the batch, unbatched.

    A ``lax.cond`` on a batched predicate becomes a select that runs both branches; on this
    reduction it stays a branch, taken for the whole batch (so the working branch must be
    right for every member, which the event machinery is)."""
    return flag


@_for_all_members.def_vmap
def _for_all_members_vmap(
    axis_size: int, in_batched: list[bool], flag: Bool[Array, " b"]
) -> tuple[Bool[Array, ""], bool]:
    del axis_size
    return (jnp.all(flag, axis=0) if in_batched[0] else flag), False


def _illinois(fn: Callable[[Array], Array], f_lo: Array, f_hi: Array) -> Float[Array, ""]:
    """Root of ``fn`` on [0, 1] given ``fn(0) = f_lo`` and ``fn(1) = f_hi`` of opposite sign
    (or zero); a fixed number of Illinois steps so the cost and the graph are static."""

    def body(_: int, carry: tuple) -> tuple:
        lo, hi, flo, fhi, side = carry
        den = fhi - flo
        c = lo - flo * (hi - lo) / jnp.where(den == 0, 1.0, den)
        c = jnp.clip(jnp.where(den == 0, lo, c), lo, hi)
        fc = fn(c)
        # fc on the lo side (same sign as flo, flo ≠ 0) moves lo; otherwise hi moves.
        move_lo = fc * flo > 0
        new_lo = jnp.where(move_lo, c, lo)
        new_hi = jnp.where(move_lo, hi, c)
        new_flo = jnp.where(move_lo, fc, jnp.where(side == -1, 0.5 * flo, flo))
        new_fhi = jnp.where(move_lo, jnp.where(side == 1, 0.5 * fhi, fhi), fc)
        new_side = jnp.where(move_lo, 1.0, -1.0)
        return new_lo, new_hi, new_flo, new_fhi, new_side

    zero = jnp.zeros_like(f_lo)
    init = (zero, zero + 1.0, f_lo, f_hi, zero)
    lo, hi, flo, fhi, _ = jax.lax.fori_loop(0, _ROOT_ITERS, body, init)
    den = fhi - flo
    c = lo - flo * (hi - lo) / jnp.where(den == 0, 1.0, den)
    return jnp.clip(jnp.where(den == 0, lo, c), 0.0, 1.0)


def _root(
    fn: Callable[[Array, Any], Array], args: Any, f_lo: Array, f_hi: Array
) -> Float[Array, ""]:
    """Root in [0, 1] of ``s ↦ fn(s, args)``, bracketed by ``f_lo = fn(0)``, ``f_hi = fn(1)``.

    The bracketing iterations run on constants (``stop_gradient``); one Newton step on the
    live ``args`` then carries the implicit-function derivative ``ds/dargs = −∂fn/∂args /
    ∂fn/∂s``, so reverse mode never unrolls the iterations (smaller graph, faster compile).
    """
    const = jax.lax.stop_gradient(args)
    s = jax.lax.stop_gradient(
        _illinois(lambda q: fn(q, const), *jax.lax.stop_gradient((f_lo, f_hi)))
    )
    f, slope = jax.jvp(lambda q: fn(q, const), (s,), (jnp.ones_like(s),))
    slope = jnp.where(jnp.abs(slope) > 0, slope, 1.0)
    live = fn(s, args)
    # live − f is zero in value: only the derivative of the Newton step w.r.t. args remains,
    # plus the (tiny) Newton correction −f/slope itself.
    return jnp.clip(s - (f + (live - f)) / slope, 0.0, 1.0)


def _hermite_v(s: Array, v0: Array, v1: Array, m0: Array, m1: Array) -> Array:
    """Cubic Hermite interpolant of v at fraction s of a step; m = step·ẍ at the ends."""
    s2, s3 = s * s, s * s * s
    return (
        (2 * s3 - 3 * s2 + 1) * v0
        + (s3 - 2 * s2 + s) * m0
        + (-2 * s3 + 3 * s2) * v1
        + (s3 - s2) * m1
    )


def _hermite_x(s: Array, v0: Array, v1: Array, m0: Array, m1: Array) -> Array:
    """∫_0^s of :func:`_hermite_v` (displacement divided by the step length)."""
    s2, s3, s4 = s * s, s * s * s, s * s * s * s
    return (
        (0.5 * s4 - s3 + s) * v0
        + (0.25 * s4 - 2.0 / 3.0 * s3 + 0.5 * s2) * m0
        + (-0.5 * s4 + s3) * v1
        + (0.25 * s4 - s3 / 3.0) * m1
    )


def _check(model: Model, p: Mapping[str, Array], t: Array, u: Array | None, substeps: int) -> None:
    loc = "simulate"
    if not isinstance(substeps, int) or substeps < 1:
        raise FricjaxError(
            f"{where(loc, 'substeps')}: must be a positive integer, got {substeps!r}"
        )
    if t.ndim != 1 or t.shape[0] < 2:
        raise FricjaxError(
            f"{where(loc, 't')}: needs a 1-D array of at least 2 samples, got shape {t.shape}"
        )
    if u is not None and u.shape != t.shape:
        raise FricjaxError(f"{where(loc, 'u')}: shape {u.shape} differs from t's {t.shape}")
    missing = [q.name for q in model.parameters() if q.name not in p]
    if missing:
        raise FricjaxError(
            f"{where(loc, 'p')}: missing parameter(s) {', '.join(missing)} of model {model.name}"
        )


def simulate(
    model: Model,
    p: Mapping[str, Float[ArrayLike, ""]],
    t: Float[Array, " n"],
    x0: Float[ArrayLike, ""],
    v0: Float[ArrayLike, ""],
    u: Float[Array, " n"] | None = None,
    *,
    substeps: int = 8,
) -> Trajectory:
    """Integrate ``m·ẍ = F_p − F_f`` (seed eq. 3/5) from ``(x0 [m], v0 [m/s])`` at ``t[0]``.

    Args:
        model: the terms (hashable; static under ``jit``).
        p: every parameter the model reads, ``mass`` [kg] included; scalar leaves (batch
            them with ``jax.vmap``).
        t: uniform sample times [s], shape [n], n ≥ 2.
        x0, v0: initial position [m] and velocity [m/s].
        u: recorded input at the sample times, shape [n] (zeros if ``None``), linearly
            interpolated between samples.
        substeps: RK4 sub-steps per sample interval (error ∝ substeps⁻⁴).

    Returns:
        :class:`Trajectory` (x, v, a), each [n], ``x[0] = x0``, ``v[0] = v0``.

    Compiled once per (model, substeps, shapes): every argument but those two is traced,
    Python numbers included; called on arrays, its program is stored
    (:mod:`fricjax.programs`).
    """
    return _simulate_program(
        model,
        {name: jnp.asarray(value) for name, value in p.items()},
        jnp.asarray(t),
        jnp.asarray(x0),
        jnp.asarray(v0),
        None if u is None else jnp.asarray(u),
        substeps,
    )


@stored
def _simulate_program(
    model: Model,
    p: Mapping[str, Float[Array, ""]],
    t: Float[Array, " n"],
    x0: Float[Array, ""],
    v0: Float[Array, ""],
    u: Float[Array, " n"] | None,
    substeps: int,
) -> Trajectory:
    return _simulate(model, p, t, x0, v0, u, substeps, skip_idle=True)


def _simulate(
    model: Model,
    p: Mapping[str, Float[ArrayLike, ""]],
    t: Float[Array, " n"],
    x0: Float[ArrayLike, ""],
    v0: Float[ArrayLike, ""],
    u: Float[Array, " n"] | None,
    substeps: int,
    skip_idle: bool,
) -> Trajectory:
    """:func:`simulate`; ``skip_idle=False`` runs every part of the event machinery on every
    sub-step (the arithmetic the skipping must reproduce; the tests compare the two)."""
    t = jnp.asarray(t, dtype=jnp.float64)
    _check(model, p, t, None if u is None else jnp.asarray(u), substeps)
    u = jnp.zeros_like(t) if u is None else jnp.asarray(u, dtype=jnp.float64)
    x0 = jnp.asarray(x0, dtype=jnp.float64)
    v0 = jnp.asarray(v0, dtype=jnp.float64)
    mass = p["mass"]
    dt = t[1] - t[0]
    h = dt / substeps

    def unless(idle: Array, passthrough: Callable[[], Any], work: Callable[[], Any]) -> Any:
        """``work()``, or ``passthrough()`` when ``idle`` holds (for the whole batch):
        ``passthrough`` returns what ``work`` would for an idle state, bit for bit."""
        if not skip_idle:
            return work()
        return jax.lax.cond(_for_all_members(idle), passthrough, work)

    def signals(iv: _Interval, tau: Array, x: Array, v: Array) -> Signals:
        return Signals(tau, x, v, iv.u0 + iv.du * (tau - iv.t0))

    def friction_branch(s: Signals, d: Array) -> Array:
        """Friction of the sliding branch ``d``, smoothly continued past v = 0."""
        # One vectorised call at [v, μ_1·v, ..., μ_4·v] keeps the traced graph small.
        scale = jnp.asarray((1.0, *_EXT_MU))
        forces = model.friction(p, s._replace(v=s.v * scale))
        on_branch, extended = forces[0], jnp.dot(jnp.asarray(_EXT_C), forces[1:])
        dv = d * s.v
        return jnp.where(dv > 0, on_branch, jnp.where(dv < 0, extended, model.static(p, s, d)))

    def accel(iv: _Interval, d: Array, tau: Array, x: Array, v: Array) -> Array:
        s = signals(iv, tau, x, v)
        return (model.drive(p, s) - friction_branch(s, d)) / mass

    def slide(iv: _Interval, tau: Array, x: Array, v: Array, r: Array, d: Array) -> tuple:
        """RK4 over ``r`` in direction ``d``; stops at v = 0 if it is reached. ``d = 0`` or
        ``r = 0``: nothing happens. Returns (tau, x, v, r_left)."""
        moving = (d != 0) & (r > 0)
        return unless(~moving, lambda: (tau, x, v, r), lambda: _slide(iv, tau, x, v, r, d))

    def _slide(iv: _Interval, tau: Array, x: Array, v: Array, r: Array, d: Array) -> tuple:
        rk_a, rk_c = jnp.asarray(_RK_A), jnp.asarray(_RK_C)

        def stage(i: int, ks: tuple[Array, Array]) -> tuple[Array, Array]:
            kx, kv = ks
            xs = x + r * jnp.dot(rk_a[i], kx)
            vs = v + r * jnp.dot(rk_a[i], kv)
            return kx.at[i].set(vs), kv.at[i].set(accel(iv, d, tau + rk_c[i] * r, xs, vs))

        # The stages run in a loop (one traced force evaluation instead of five) to keep the
        # compiled graph, and above all its reverse-mode derivative, small.
        zeros = jnp.zeros(5, dtype=x.dtype) + 0 * x
        kx, kv = jax.lax.fori_loop(0, 5, stage, (zeros, zeros))
        x1 = x + r * jnp.dot(rk_a[4], kx)
        v1 = v + r * jnp.dot(rk_a[4], kv)
        k1, a1 = kv[0], kv[4]
        moving = (d != 0) & (r > 0)
        stops = moving & (d * v1 <= 0)
        m0, m1 = r * k1, r * a1
        theta = unless(
            ~stops,
            lambda: jnp.zeros_like(v),
            lambda: _root(lambda s, a: _hermite_v(s, *a), (v, v1, m0, m1), v, v1),
        )
        xc = x + r * _hermite_x(theta, v, v1, m0, m1)
        tau_n = jnp.where(stops, tau + theta * r, jnp.where(moving, tau + r, tau))
        x_n = jnp.where(stops, xc, jnp.where(moving, x1, x))
        v_n = jnp.where(stops, 0.0, jnp.where(moving, v1, v))
        r_n = jnp.where(stops, (1 - theta) * r, jnp.where(moving, 0.0, r))
        return tau_n, x_n, v_n, r_n

    def excess(pp: Mapping, iv: _Interval, tau: Array, x: Array, d: Array) -> Array:
        """``d·F_p − |static(d)|`` at rest [N]: > 0 means the friction cannot hold."""
        s = signals(iv, tau, x, jnp.zeros_like(x))
        return d * model.drive(pp, s) - jnp.abs(model.static(pp, s, d))

    def stick_or_slip(iv: _Interval, tau: Array, x: Array, v: Array, r: Array) -> tuple:
        """At rest: when (if at all within ``r``) and which way the body breaks away.
        Returns (tau, r_left, direction); a sliding body passes through with d = sgn v."""
        rest = v == 0
        return unless(
            ~rest, lambda: (tau, r, jnp.sign(v)), lambda: _stick_or_slip(iv, tau, x, v, r)
        )

    def _stick_or_slip(iv: _Interval, tau: Array, x: Array, v: Array, r: Array) -> tuple:
        rest = v == 0
        s0 = signals(iv, tau, x, jnp.zeros_like(x))
        s1 = signals(iv, tau + r, x, jnp.zeros_like(x))
        f0, f1 = model.drive(p, s0), model.drive(p, s1)
        d0, d1 = jnp.sign(f0), jnp.sign(f1)
        now = d0 * f0 - jnp.abs(model.static(p, s0, d0)) > 0
        # Excess in the direction of the drive at the end of the interval, at both ends.
        e_lo = d1 * f0 - jnp.abs(model.static(p, s0, d1))
        e_hi = d1 * f1 - jnp.abs(model.static(p, s1, d1))
        later = (~now) & (e_hi > 0) & (r > 0)
        theta = unless(
            ~later,
            lambda: jnp.zeros_like(x),
            lambda: _root(
                lambda s, a: excess(a[0], a[1], a[2] + s * a[3], a[4], a[5]),
                (p, iv, tau, r, x, jax.lax.stop_gradient(d1)),
                e_lo,
                e_hi,
            ),
        )
        d = jnp.where(now, d0, jnp.where(later, d1, 0.0))
        tau_b = jnp.where(now, tau, jnp.where(later, tau + theta * r, tau + r))
        r_b = jnp.where(now, r, jnp.where(later, (1 - theta) * r, 0.0))
        return (
            jnp.where(rest, tau_b, tau),
            jnp.where(rest, r_b, r),
            jnp.where(rest, d, jnp.sign(v)),
        )

    def substep(iv: _Interval, tau: Array, x: Array, v: Array) -> tuple[Array, Array]:
        def phase(_: int, state: tuple) -> tuple:
            tau, x, v, r, d = state
            tau, x, v, r = slide(iv, tau, x, v, r, d)
            tau, r, d = stick_or_slip(iv, tau, x, v, r)
            return tau, x, v, r, d

        # A loop rather than two inlined phases halves the traced graph (compile time).
        state = (tau, x, v, h + jnp.zeros_like(x), jnp.sign(v))
        _, x, v, _, _ = jax.lax.fori_loop(0, _PHASES, phase, state)
        return x, v

    def interval(carry: tuple[Array, Array], data: tuple) -> tuple:
        t0, u0, u1 = data
        iv = _Interval(t0, u0, (u1 - u0) / dt)

        def body(j: int, state: tuple[Array, Array]) -> tuple[Array, Array]:
            return substep(iv, t0 + j * h, *state)

        x, v = jax.lax.fori_loop(0, substeps, body, carry)
        return (x, v), (x, v)

    _, (xs, vs) = jax.lax.scan(interval, (x0, v0), (t[:-1], u[:-1], u[1:]))
    x = jnp.concatenate([x0[None], xs])
    v = jnp.concatenate([v0[None], vs])
    return Trajectory(x, v, sampled_accel(model, p, Signals(t, x, v, u)))


def sampled_accel(model: Model, p: Mapping[str, Array], s: Signals) -> Float[Array, " n"]:
    """``(F_p − F_f)/m`` on sampled states, with the stick/slip rule at rest [m/s²]."""
    sliding = model.force(p, s) / p["mass"]
    return jnp.where(s.v != 0, sliding, model.rest_force(p, s) / p["mass"])
