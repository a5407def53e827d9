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

Pointwise residuals. Where ``r_i`` depends on ``(x_i, v_i, a_i)`` only (no decimation, no
stateful term), ``G = Σ_s diag(g_s)·L_s`` with the gains ``g_s = ∂r_i/∂s_i`` (three tangents
of ones), so the rows of ``D = Gᵀ`` are ``Σ_s g_s ∘ (L_s e_k)`` — the cached impulse responses
weighted, no tangent per impulse. The gains are trusted only where they predict the exact
change of one random perturbation of x to :data:`POINTWISE_RTOL`. An impulse reaches at most
h samples (:func:`_reach`: all but :data:`BAND_TOL` of its squared mass), so ``D Dᵀ`` is
banded and ``tr Σ² = σ⁴‖D Dᵀ‖²_F`` is summed over blocks of rows against their neighbours
only (the same numbers to 1e-8, tested; 1 s axis record, quiet 2-core CPU: 31–39 ms for
the whole noise, the 1 ms noise estimate included, against 46–48 ms with a tangent per
impulse and the dense ``D Dᵀ``, which alone took 20 ms).

Left out: noise of a measured drive input or force (``/u``, ``/F``) — it is independent of
x's, and the problem holds it only filtered, so its level cannot be read from the data here;
the record ends of a held-out window (the problem's :attr:`~fricjax.problem.Problem.window`)
are treated as record ends. Where the noise model cannot be built (preprocessing unknown,
fewer than 16 samples, σ_x = 0), :func:`residual_noise` returns None and the caller keeps
the Gauss–Newton σ.
"""

from __future__ import annotations

from collections.abc import Sequence
from functools import lru_cache, partial
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from fricjax.data.noise import NoiseEstimate, estimate_noise
from fricjax.data.preprocess import PreprocessSettings, derivative_columns
from fricjax.problem import EquationError, Problem, stack_trees
from fricjax.programs import stored
from fricjax.refine import ResidualNoise
from fricjax.units import axis_units

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


_tangents_jit = stored(_tangents)


@lru_cache(maxsize=4)
def _impulse_responses(
    settings: PreprocessSettings, n_raw: int, dt: float
) -> tuple[Float[np.ndarray, "N m"], Float[np.ndarray, "N m"], Float[np.ndarray, "N m"]]:
    """``(P, L_v, L_a)`` applied to every unit impulse of x [n_raw rows of m = n_raw − 2·trim]:
    the preprocessing's matrices, transposed. They depend on the settings, the length and
    the step only, not on the data, so a fleet or joint fit of equal records builds them once
    (three [n_raw, m] arrays, ≤ 24 MB at EXACT_UP_TO)."""
    t_raw = np.arange(n_raw) * dt
    out = tuple(
        np.ascontiguousarray(c.T) for c in derivative_columns(t_raw, np.eye(n_raw), settings)
    )
    for a in out:
        a.flags.writeable = False  # shared by every caller through the cache
    return out  # type: ignore[return-value]


#: Relative squared mass of the preprocessing's impulse responses left outside their reach
#: (the pointwise path's products are exact to about its square root, 1e-10).
BAND_TOL = 1e-20
#: A pointwise residual's gains are trusted when a random perturbation's exact change and
#: the gains' prediction of it agree to this (relative; rounding is ~1e-15).
POINTWISE_RTOL = 1e-9
#: Rows of D per block of the banded product D Dᵀ.
_BLOCK = 128


@lru_cache(maxsize=4)
def _stacked_responses(settings: PreprocessSettings, n_raw: int, dt: float) -> Array:
    """``(P, L_v, L_a)`` of :func:`_impulse_responses` as one [3, N, m] device array, put
    once per settings and length (≤ 24 MB at EXACT_UP_TO), not at every call."""
    return jax.device_put(np.stack(_impulse_responses(settings, n_raw, dt)))


@lru_cache(maxsize=4)
def _reach(settings: PreprocessSettings, n_raw: int, dt: float) -> int | None:
    """h: how far (in samples) the preprocessing carries an impulse of x, the smallest
    half-width that leaves at most :data:`BAND_TOL` of each of ``(P, L_v, L_a)``'s squared
    mass outside; None where ``2h + _BLOCK`` is not below the record's length (a dense
    product then costs as much)."""
    irs = _impulse_responses(settings, n_raw, dt)
    m = irs[0].shape[1]
    centre = np.arange(n_raw) - settings.trim
    dist = np.abs(np.arange(m)[None, :] - centre[:, None]).ravel()
    h = 0
    for ir in irs:
        mass = np.bincount(dist, weights=(ir * ir).ravel())
        outside = np.cumsum(mass[::-1])[::-1]  # outside[d]: the mass at distance >= d
        if outside[0] > 0:
            h = max(h, int(np.argmax(outside <= BAND_TOL * outside[0])) - 1)
    return h if 2 * h + _BLOCK < m else None


def _pointwise_moments(
    gains: Float[Array, "3 m"],
    responses: Float[Array, "3 N m"],
    jac: Float[Array, "m d"],
    trim: int,
    reach: int,
) -> tuple[Float[Array, "N d"], Float[Array, ""], Float[Array, ""]]:
    """``(D J, ‖D‖²_F, ‖D Dᵀ‖²_F)`` of a pointwise residual, ``D = Gᵀ`` [N, m] with
    ``G = Σ_s diag(g_s)·L_s`` (row k of D: ``Σ_s g_s ∘ (L_s e_k)``, which lives within
    ``reach`` samples of column ``k − trim``). D Dᵀ is then banded (rows more than 2·reach
    apart share no column): it is summed over blocks of :data:`_BLOCK` rows, each block
    against itself and the blocks within reach, on the block's own columns only."""
    # a sum of three products, not einsum: XLA's CPU dot with a batch axis ran 6x slower
    d = responses[0] * gains[0] + responses[1] * gains[1] + responses[2] * gains[2]
    n_rows, m = d.shape
    b = _BLOCK
    width = min(b + 2 * reach, m)
    n_blocks = -(-n_rows // b)
    ahead = -(-2 * reach // b)  # blocks after a block that can share its columns
    padded = jnp.pad(d, ((0, (n_blocks + ahead) * b - n_rows), (0, 0)))
    trace_sq = jnp.zeros((), d.dtype)
    # static slices (a few tens of small products): vmapped dynamic slices became gathers
    for i in range(n_blocks):
        start = min(max(i * b - trim - reach, 0), m - width)
        rows = padded[i * b : (i + 1) * b, start : start + width]
        trace_sq = trace_sq + jnp.sum((rows @ rows.T) ** 2)
        for q in range(1, ahead + 1):
            other = padded[(i + q) * b : (i + q + 1) * b, start : start + width]
            trace_sq = trace_sq + 2.0 * jnp.sum((rows @ other.T) ** 2)
    return d @ jac, jnp.sum(d * d), trace_sq


@partial(jax.jit, static_argnums=(3, 4))
def _pointwise_moments_many(
    gains: Float[Array, "B 3 m"],
    responses: Float[Array, "3 N m"],
    jacs: Float[Array, "B m d"],
    trim: int,
    reach: int,
) -> tuple[Float[Array, "B N d"], Float[Array, " B"], Float[Array, " B"]]:
    """:func:`_pointwise_moments` of B problems, one after another (``lax.map``): under
    vmap the block products became XLA CPU dots with a batch axis, 2-3x slower each."""
    return jax.lax.map(
        lambda gj: _pointwise_moments(gj[0], responses, gj[1], trim, reach), (gains, jacs)
    )


def _pointwise_gains(
    residuals: Sequence[EquationError],
    thetas: Float[np.ndarray, "B d"],
    irs: tuple[np.ndarray, ...],
) -> list[Float[np.ndarray, "3 m"] | None]:
    """``g_s = ∂r_i/∂s_i`` (s = x, v, a) of each residual where it is pointwise in its
    signals (the tangent of ones along each signal), checked against the exact change of
    one random perturbation of x through the preprocessing; None where they disagree (a
    decimated residual, a stateful term). One vmapped program over the residuals (equal
    structure)."""
    n_raw, m = irs[0].shape
    eps = np.random.default_rng(_KEY).standard_normal(n_raw)
    probe = [eps @ ir for ir in irs]
    eye = np.eye(3)
    rows = [np.stack([np.full(m, eye[i, s]) for i in range(3)] + [probe[s]]) for s in range(3)]
    stacked = stack_trees(residuals)
    out = np.asarray(_tangents_many(stacked, jnp.asarray(thetas), *rows))  # [B, 4, n]
    if out.shape[2] != m:
        return [None] * len(residuals)
    result: list[np.ndarray | None] = []
    for lane in out:
        gains, exact = lane[:3], lane[3]
        predicted = np.sum(gains * np.stack(probe), axis=0)
        ok = np.linalg.norm(exact - predicted) <= POINTWISE_RTOL * np.linalg.norm(exact)
        result.append(gains if ok else None)
    return result


@stored
def _tangents_many(
    residuals: EquationError, thetas: Float[Array, "B d"], dx: Array, dv: Array, da: Array
) -> Float[Array, "B K n"]:
    return eqx.filter_vmap(lambda r, th: _tangents(r, th, dx, dv, da))(residuals, thetas)


def residual_noise(
    problem: Problem,
    theta: Float[np.ndarray, " d"],
    jac: Float[np.ndarray, "n d"],
    *,
    scale: float = 1.0,
) -> ResidualNoise | None:
    """``JᵀΣJ``, ``tr Σ`` and ``tr Σ²`` of ``problem``'s residual at ``theta`` (module
    docstring).

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
    return residual_noises([problem], [theta], [jac], [scale])[0]


def residual_noises(
    problems: Sequence[Problem],
    thetas: Sequence[Float[np.ndarray, " d"]],
    jacs: Sequence[Float[np.ndarray, "n d"]],
    scales: Sequence[float] | None = None,
) -> list[ResidualNoise | None]:
    """:func:`residual_noise` of several problems, the same numbers as one by one: the
    pointwise ones of one preprocessing, length and residual structure (a fleet's shard)
    share one vmapped program for their gains and one for their moments."""
    scales = [1.0] * len(problems) if scales is None else list(scales)
    out: list[ResidualNoise | None] = [None] * len(problems)
    groups: dict[Any, list[tuple[int, NoiseEstimate]]] = {}
    for i, problem in enumerate(problems):
        settings = problem.preprocess
        if settings is None or problem.n < 16:
            continue
        noise = estimate_noise(problem.x)
        if not noise.sigma > 0.0:
            continue
        n_raw = problem.n + 2 * settings.trim
        dt = float(problem.t[-1] - problem.t[0]) / (problem.n - 1)
        structure = jax.tree.structure(eqx.filter(problem.residual_fn, eqx.is_array))
        groups.setdefault((settings, n_raw, dt, structure), []).append((i, noise))
    for (settings, n_raw, dt, _), members in groups.items():
        exact = n_raw <= EXACT_UP_TO
        reach = _reach(settings, n_raw, dt) if exact else None
        moments: dict[int, tuple[np.ndarray, float, float]] = {}
        if reach is not None:
            idx = [i for i, _ in members]
            gains = _pointwise_gains(
                [problems[i].residual_fn for i in idx],
                np.stack([np.asarray(thetas[i], np.float64) for i in idx]),
                _impulse_responses(settings, n_raw, dt),
            )
            ok = [k for k, g in enumerate(gains) if g is not None]
            if ok:
                w, sq, dd = (
                    np.asarray(a)
                    for a in _pointwise_moments_many(
                        np.stack([gains[k] for k in ok]),
                        _stacked_responses(settings, n_raw, dt),
                        np.stack([np.asarray(jacs[idx[k]], np.float64) for k in ok]),
                        settings.trim,
                        reach,
                    )
                )
                for j, k in enumerate(ok):
                    moments[idx[k]] = (w[j].T @ w[j], float(sq[j]), float(dd[j]))
        offsets = (np.arange(n_raw) - settings.trim) * dt
        how = "exact" if exact else f"{DRAWS} draws"
        for i, noise in members:
            var = noise.sigma**2 * scales[i] ** 2
            if i in moments:
                wtw, sq_i, dd_i = moments[i]
                jsj, trace, trace_sq = var * wtw, var * sq_i, var**2 * dd_i
            else:
                jsj, trace, trace_sq = _dense_moments(
                    problems[i].residual_fn,
                    jnp.asarray(thetas[i], dtype=jnp.float64),
                    np.asarray(jacs[i], dtype=np.float64),
                    settings,
                    problems[i].t[0] + offsets,
                    n_raw,
                    dt,
                    exact,
                    n_raw if exact else DRAWS,
                    var,
                )
            unit = axis_units(problems[i].axis).position
            label = f"x noise {noise.describe(unit)}; propagated through the preprocessing ({how})"
            out[i] = ResidualNoise(jsj=jsj, trace=trace, trace_sq=trace_sq, label=label)
    return out


def _dense_moments(
    residual: EquationError,
    theta: Array,
    jac: Float[np.ndarray, "n d"],
    settings: PreprocessSettings,
    t_raw: np.ndarray,
    n_raw: int,
    dt: float,
    exact: bool,
    count: int,
    var: float,
) -> tuple[np.ndarray, float, float]:
    """``(JᵀΣJ, tr Σ, tr Σ²)`` from the residual's change for every unit impulse of x
    (``exact``) or for ``count`` Gaussian draws, one tangent each (module docstring)."""
    rng = np.random.default_rng(_KEY)
    w_parts, sq_parts, dr_parts = [], [], []
    for start in range(0, count, _CHUNK):
        stop = min(start + _CHUNK, count)
        if exact:
            dx, dv, da = (c[start:stop] for c in _impulse_responses(settings, n_raw, dt))
        else:
            draws = rng.standard_normal((stop - start, n_raw))
            dx, dv, da = (c.T for c in derivative_columns(t_raw, draws.T, settings))
        pad = ((0, _CHUNK - (stop - start)), (0, 0))
        dx, dv, da = (np.pad(c, pad) for c in (dx, dv, da))
        dr = np.asarray(_tangents_jit(residual, theta, dx, dv, da))[: stop - start]
        w_parts.append(dr @ jac)
        sq_parts.append(np.sum(dr * dr, axis=1))
        if exact:
            dr_parts.append(dr)
    w, sq = np.concatenate(w_parts), np.concatenate(sq_parts)
    if exact:  # Σ = σ²·DᵀD with D = [G e_k]_k, so tr Σ² = σ⁴‖D Dᵀ‖²_F
        dmat = np.concatenate(dr_parts)
        trace_sq = var**2 * float(np.sum((dmat @ dmat.T) ** 2))
        return var * (w.T @ w), var * float(np.sum(sq)), trace_sq
    # ‖G ε‖² has variance 2 tr(GGᵀ)² for Gaussian ε
    v = var / count
    trace_sq = (v * count) ** 2 * float(np.var(sq, ddof=1)) / 2.0
    return v * (w.T @ w), v * float(np.sum(sq)), trace_sq


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
