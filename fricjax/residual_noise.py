"""The equation-error residual's noise, propagated from the noise on the recorded x.

The residual ``r = m·a − F(θ; x, v, u)`` [n] (seed eq. 5/11, :class:`~fricjax.problem.Problem`)
is computed from ``v = L_v x`` and ``a = L_a x``, the linear preprocessing of
:func:`fricjax.data.preprocess.derivatives` (differences, zero-phase low-pass, trim), and,
when the residual is decimated, passed through the linear decimation of
:mod:`fricjax.data.decimate`. White noise ε on x (std σ_x [m], n_raw samples,
:func:`fricjax.data.noise.estimate_noise`) therefore reaches the residual linearly:

    δr = G ε,   G = ∂r/∂(x, v, a) · (P, L_v, L_a)     [N/m, shape n × n_raw]

(P the trim; ∂r/∂a = m, ∂r/∂v = −∂F/∂v, ∂r/∂x = −∂F/∂x, the decimation included), so
``Σ = σ_x² G Gᵀ`` is strongly coloured: two differentiations leave almost no power at the
low frequencies where the friction parameters live, and a white-residual σ (Gauss–Newton)
overstates their spread several times. What :func:`fricjax.refine.uncertainty_at` needs is

    JᵀΣJ = σ_x² Σ_k (Jᵀ G e_k)(Jᵀ G e_k)ᵀ,   tr Σ = σ_x² Σ_k ‖G e_k‖²      [N²·(J units)²]

summed over the unit vectors e_k of x: exact, and each term is the preprocessing of one
impulse (numpy, as the recording's own) followed by one Jacobian–vector product of the
residual with respect to its signals (jax, linear in them; decimation and the stick/slip
rule included as the residual has them). Why not G's matrix or its transpose: the
preprocessing is numpy (odd padding, steady-state starts), so its transpose is not at hand,
and rebuilding it in jax would state the filter twice. For records longer than
:data:`EXACT_UP_TO` samples, the sum runs over :data:`DRAWS` Gaussian draws ε_k ~ N(0, I)
(fixed key) divided by their number: the relative error of each variance is then
√(2/DRAWS) = 6.3 % (of σ: 3.1 %).

Left out: noise of a measured drive input or force (``/u``, ``/F``) — it is independent of
x's, and the problem holds it only filtered, so its level cannot be read from the data here;
the record ends of a held-out window (the problem's :attr:`~fricjax.problem.Problem.window`)
are treated as record ends. Where the noise model cannot be built (preprocessing unknown,
fewer than 16 samples, σ_x = 0), :func:`residual_noise` returns None and the caller keeps
the Gauss–Newton σ.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from fricjax.data.noise import estimate_noise
from fricjax.data.preprocess import PreprocessSettings, derivatives
from fricjax.problem import EquationError, Problem
from fricjax.refine import ResidualNoise

#: Records up to this many raw samples sum exactly over the unit vectors of x.
EXACT_UP_TO = 1024
#: Gaussian draws for longer records (relative error of a variance √(2/DRAWS)).
DRAWS = 512
#: Draws propagated per compiled call (the last chunk is padded with zero draws, which
#: add nothing: the propagation is linear).
_CHUNK = 128
_KEY = 0


def _tangents(
    residual: EquationError,
    theta: Float[Array, " d"],
    dx: Float[Array, "K m"],
    dv: Float[Array, "K m"],
    da: Float[Array, "K m"],
) -> Float[Array, "K n"]:
    """The residual's changes δr_k [K, n] for signal perturbations (δx, δv, δa)_k [K, m]."""

    def r_of(x: Array, v: Array, a: Array) -> Array:
        return eqx.tree_at(lambda m: (m.x, m.v, m.a), residual, (x, v, a))(theta)

    def one(ex: Array, ev: Array, ea: Array) -> Array:
        return jax.jvp(r_of, (residual.x, residual.v, residual.a), (ex, ev, ea))[1]

    return jax.vmap(one)(dx, dv, da)


_tangents_jit = eqx.filter_jit(_tangents)


@lru_cache(maxsize=4)
def _impulse_responses(
    settings: PreprocessSettings, n_raw: int, dt: float
) -> tuple[Float[np.ndarray, "N m"], Float[np.ndarray, "N m"], Float[np.ndarray, "N m"]]:
    """``(P, L_v, L_a)`` applied to every unit impulse of x [n_raw rows of m = n_raw − 2·trim]:
    the preprocessing's matrices, transposed. They depend on the settings, the length and
    the step only, not on the data, so a fleet or joint fit of equal records builds them once
    (three [n_raw, m] arrays, ≤ 24 MB at EXACT_UP_TO)."""
    t_raw = np.arange(n_raw) * dt
    rows = [derivatives(t_raw, e, settings) for e in np.eye(n_raw)]
    out = tuple(np.stack([getattr(d, f) for d in rows]) for f in ("x", "v", "a"))
    for a in out:
        a.flags.writeable = False  # shared by every caller through the cache
    return out  # type: ignore[return-value]


def residual_noise(
    problem: Problem,
    theta: Float[np.ndarray, " d"],
    jac: Float[np.ndarray, "n d"],
    *,
    scale: float = 1.0,
) -> ResidualNoise | None:
    """``JᵀΣJ`` and ``tr Σ`` of ``problem``'s residual at ``theta`` (module docstring).

    Args:
        problem: the preprocessed recording and model (its ``preprocess`` settings made v, a).
        theta: [d] the free parameters where the residual is linearised.
        jac: [n_residual, d] the residual's Jacobian rows of this problem, in the units of
            ``scale·r`` (a joint fit's rows are its member's residual over its noise scale).
        scale: the factor that multiplies this problem's residual [N] in ``jac``'s rows.

    Returns:
        :class:`~fricjax.refine.ResidualNoise` in (scale·N)² units, or None where the noise
        model cannot be built (the caller then keeps the Gauss–Newton σ).
    """
    settings = problem.preprocess
    if settings is None or problem.n < 16:
        return None
    noise = estimate_noise(problem.x)
    if not noise.sigma > 0.0:
        return None
    trim, n = settings.trim, problem.n
    n_raw = n + 2 * trim
    dt = float(problem.t[-1] - problem.t[0]) / (n - 1)
    t_raw = problem.t[0] + (np.arange(n_raw) - trim) * dt
    exact = n_raw <= EXACT_UP_TO
    count = n_raw if exact else DRAWS
    rng = np.random.default_rng(_KEY)
    residual = problem.residual_fn
    theta_j = jnp.asarray(theta, dtype=jnp.float64)
    jac = np.asarray(jac, dtype=np.float64)
    w_parts, sq_parts, dr_parts = [], [], []
    for start in range(0, count, _CHUNK):
        stop = min(start + _CHUNK, count)
        if exact:
            dx, dv, da = (c[start:stop] for c in _impulse_responses(settings, n_raw, dt))
        else:
            draws = [
                derivatives(t_raw, rng.standard_normal(n_raw), settings) for _ in range(start, stop)
            ]
            dx, dv, da = (np.stack([getattr(d, f) for d in draws]) for f in ("x", "v", "a"))
        pad = ((0, _CHUNK - (stop - start)), (0, 0))
        dx, dv, da = (np.pad(c, pad) for c in (dx, dv, da))
        dr = np.asarray(_tangents_jit(residual, theta_j, dx, dv, da))[: stop - start]
        w_parts.append(dr @ jac)
        sq_parts.append(np.sum(dr * dr, axis=1))
        if exact:
            dr_parts.append(dr)
    w, sq = np.concatenate(w_parts), np.concatenate(sq_parts)
    var = noise.sigma**2 * scale**2
    if exact:  # Σ = σ²·DᵀD with D = [G e_k]_k, so tr Σ² = σ⁴‖D Dᵀ‖²_F
        dmat = np.concatenate(dr_parts)
        trace_sq = var**2 * float(np.sum((dmat @ dmat.T) ** 2))
    else:  # ‖G ε‖² has variance 2 tr(GGᵀ)² for Gaussian ε
        var /= count
        trace_sq = (var * count) ** 2 * float(np.var(sq, ddof=1)) / 2.0
    how = "exact" if exact else f"{count} draws"
    label = f"x noise {noise.describe('m')}; propagated through the preprocessing ({how})"
    return ResidualNoise(
        jsj=var * (w.T @ w), trace=var * float(np.sum(sq)), trace_sq=trace_sq, label=label
    )


def stacked_noise(
    problems: Sequence[Problem],
    thetas: Sequence[Float[np.ndarray, " d"]],
    jac: Float[np.ndarray, "n D"],
    scales: Sequence[float],
) -> ResidualNoise | None:
    """:func:`residual_noise` of a residual that stacks several problems' residuals, problem
    ``k`` times ``scales[k]`` (a joint fit): the recordings' noises are independent, so
    ``JᵀΣJ`` and ``tr Σ`` are the sums of theirs over their rows of ``jac`` [Σ n_k, D].
    None where one member's noise model cannot be built."""
    parts, offset = [], 0
    for problem, theta, scale in zip(problems, thetas, scales, strict=True):
        m = problem.n_residual
        part = residual_noise(problem, theta, jac[offset : offset + m], scale=scale)
        offset += m
        if part is None:
            return None
        parts.append(part)
    labels = "; ".join(f"[{k}] {p.label}" for k, p in enumerate(parts))
    return ResidualNoise(
        jsj=sum(p.jsj for p in parts),
        trace=sum(p.trace for p in parts),
        trace_sq=sum(p.trace_sq for p in parts),
        label=labels,
    )
