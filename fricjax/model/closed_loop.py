"""Closed-loop simulation of a position-controlled rig (the EMPS cascaded P/PD loop).

A rig whose plant holds a pure integrator (EMPS: motor + ball screw + load) runs in closed
loop, and an open-loop simulation driven by the recorded input drifts away: any error in
the identified forces integrates twice. Re-simulating the loop needs the reference
position ``r`` and the controller. With the EMPS law (Janot, Gautier & Brunot 2019, eq. 7;
``shared/data/real/emps/README.md``), at every controller sample ``k`` (period ``dt``, the
record's step):

    q_f(k) = ½·q(k) + ½·q(k−1)                               2-tap FIR on the position
    q̇_f(k) = (q_f(k) − q_f(k−1))/dt = (q(k) − q(k−2))/(2·dt)   backward difference
    ν(k)   = sat_{±u_max}( kp·kv·(r(k) − q(k)) − kv·q̇_f(k) + w(k) )               [V]

``kp`` [1/s] position gain, ``kv`` [V/(m/s)] velocity gain, ``u_max`` [V] drive
saturation, ``w`` [V] an additive input (pulses injected on top of the controller output;
zero for a plain tracking run). ``ν`` is held over [t_k, t_{k+1}) (zero-order hold) and
drives the model through its input ``u`` (``measured_input``: F_p = gain·ν − offset);
the plant ``m·ẍ = F_p − F_f`` (seed eq. 3/5) is integrated over each hold interval by
:func:`fricjax.model.simulate.simulate` (RK4 sub-steps, located stops and breakaways), so
the model's own force functions are used and nothing is re-implemented. Before ``t_0`` the
body is taken in uniform motion, ``q(−j) = x0 − j·v0·dt`` (EMPS records start moving).

Checked on DATA_EMPS: the recorded ``vir`` equals ν computed from the recorded ``qm``,
``qg`` at the same sample (no delay) to 3.7 mV rms (the drive swings ±4.3 V); on
DATA_EMPS_PULSES, ``vir − ν = 1.0139·pulses_N`` to 4.7 mV rms, i.e. the pulses enter as
``w``. :func:`input_disturbance` recovers ``w`` from a recording that way.
"""

from __future__ import annotations

from collections.abc import Mapping
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from fricjax.errors import FricjaxError, where
from fricjax.model.simulate import sampled_accel, simulate
from fricjax.model.system import Model
from fricjax.model.term import Signals

__all__ = [
    "EMPS_CONTROLLER",
    "CascadePD",
    "ClosedLoopTrajectory",
    "feedback_law",
    "input_disturbance",
    "simulate_closed_loop",
]


class CascadePD(NamedTuple):
    """Cascaded P (position) / P (velocity) controller with a saturated output.

    kp: position-loop gain [1/s]; kv: velocity-loop gain [V/(m/s)] (output unit per m/s);
    u_max: output saturation [V] (the drive clips ν to ±u_max).
    """

    kp: float
    kv: float
    u_max: float = 10.0


#: EMPS values (stored in the MAT files as ``kp``, ``kv``; ``viradm = 10`` V in the
#: published simulation scripts).
EMPS_CONTROLLER = CascadePD(kp=160.18, kv=243.45, u_max=10.0)


class ClosedLoopTrajectory(NamedTuple):
    """Simulated closed-loop run at the sample times, each of shape [n].

    x [m] position, v [m/s] velocity, a [m/s²] acceleration on the sampled state,
    u [V] controller output ν(k) applied over [t_k, t_{k+1}) (after saturation).
    """

    x: Float[Array, " n"]
    v: Float[Array, " n"]
    a: Float[Array, " n"]
    u: Float[Array, " n"]


def feedback_law(
    controller: CascadePD,
    r: Float[ArrayLike, "..."],
    q: Float[ArrayLike, "..."],
    q2: Float[ArrayLike, "..."],
    dt: float,
) -> Float[Array, "..."]:
    """Unsaturated ν = kp·kv·(r − q) − kv·(q − q2)/(2·dt) [V]; ``q2`` is q two samples back."""
    kp, kv = controller.kp, controller.kv
    return kp * kv * (r - q) - kv * (q - q2) / (2.0 * dt)


def input_disturbance(
    controller: CascadePD,
    t: Float[np.ndarray, " n"],
    x: Float[np.ndarray, " n"],
    r: Float[np.ndarray, " n"],
    u: Float[np.ndarray, " n"],
) -> Float[np.ndarray, " n"]:
    """``w = u − ν_fb(r, x)`` [V]: the part of the recorded drive input the feedback law
    does not explain from the recorded position (EMPS pulses; ~mV noise otherwise).

    ``ν_fb`` is :func:`feedback_law` on the recorded x, extended before t_0 by its first
    difference (``x(−j) = x_0 − j·(x_1 − x_0)``, as :func:`simulate_closed_loop` does).
    """
    t, x, r, u = (np.asarray(a, dtype=np.float64) for a in (t, x, r, u))
    dt = float((t[-1] - t[0]) / (t.shape[0] - 1))
    step = x[1] - x[0]
    x2 = np.concatenate([[x[0] - 2.0 * step, x[0] - step], x[:-2]])
    return u - np.asarray(feedback_law(controller, r, x, x2, dt))


def _check(t: Array, r: Array, w: Array | None, controller: CascadePD) -> None:
    loc = "simulate_closed_loop"
    if t.ndim != 1 or t.shape[0] < 2:
        raise FricjaxError(f"{where(loc, 't')}: needs a 1-D array of >= 2 samples, got {t.shape}")
    if r.shape != t.shape:
        raise FricjaxError(f"{where(loc, 'r')}: shape {r.shape} differs from t's {t.shape}")
    if w is not None and w.shape != t.shape:
        raise FricjaxError(f"{where(loc, 'w')}: shape {w.shape} differs from t's {t.shape}")
    if not isinstance(controller, CascadePD):
        raise FricjaxError(f"{where(loc, 'controller')}: expected CascadePD")


@partial(jax.jit, static_argnames=("model", "substeps"))
def simulate_closed_loop(
    model: Model,
    p: Mapping[str, Float[ArrayLike, ""]],
    t: Float[Array, " n"],
    r: Float[Array, " n"],
    x0: Float[ArrayLike, ""],
    v0: Float[ArrayLike, ""],
    controller: CascadePD,
    w: Float[Array, " n"] | None = None,
    *,
    substeps: int = 4,
) -> ClosedLoopTrajectory:
    """Simulate the loop (module docstring) from ``(x0 [m], v0 [m/s])`` at ``t[0]``.

    Args:
        model: force model whose drive reads the input ``u`` (e.g. ``measured_input``).
        p: every parameter of the model, ``mass`` [kg] included; scalar leaves (vmap
            over parameter sets, differentiate through it: it is one ``lax.scan``).
        t: uniform sample times [s], shape [n]; the controller runs at these samples.
        r: reference position [m], shape [n].
        x0, v0: initial position [m] and velocity [m/s].
        controller: :class:`CascadePD` gains (traced: they may be batched too).
        w: additive input [V], shape [n] (zeros if None), added before saturation.
        substeps: RK4 sub-steps of the plant per controller period.

    Returns:
        :class:`ClosedLoopTrajectory`, each field [n]; x[0] = x0, v[0] = v0.
    """
    t = jnp.asarray(t, dtype=jnp.float64)
    r = jnp.asarray(r, dtype=jnp.float64)
    w = None if w is None else jnp.asarray(w, dtype=jnp.float64)
    _check(t, r, w, controller)
    w = jnp.zeros_like(t) if w is None else w
    x0 = jnp.asarray(x0, dtype=jnp.float64)
    v0 = jnp.asarray(v0, dtype=jnp.float64)
    dt = t[1] - t[0]
    u_max = jnp.asarray(controller.u_max, dtype=jnp.float64)

    def step(carry: tuple, data: tuple) -> tuple:
        x, v, q1, q2 = carry
        tk, rk, wk = data
        nu = jnp.clip(feedback_law(controller, rk, x, q2, dt) + wk, -u_max, u_max)
        hold = jnp.stack([nu, nu])
        traj = simulate(model, p, jnp.stack([tk, tk + dt]), x, v, hold, substeps=substeps)
        return (traj.x[1], traj.v[1], x, q1), (x, v, nu)

    init = (x0, v0, x0 - v0 * dt, x0 - 2.0 * v0 * dt)
    _, (xs, vs, us) = jax.lax.scan(step, init, (t, r, w))
    a = sampled_accel(model, p, Signals(t, xs, vs, us))
    return ClosedLoopTrajectory(xs, vs, a, us)
