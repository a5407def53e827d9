"""The measurement noise of a signal, estimated from the recording itself.

Why from the recording and not from a model's residual: a residual's scale is the noise
*plus* whatever the model under test leaves out, so a scale taken from it shrinks every test
exactly where a model is wrong. The high band of a sampled, smooth motion holds only noise,
and finite differences reach it without any model.

Differences. For a signal ``y_k = s(t_k) + e_k`` with white noise ``e`` (std σ) the k-th
forward difference is

    Δᵏy_j = Σ_{i=0..k} (−1)^(k−i) C(k, i) y_{j+i} = Δᵏs_j + Δᵏe_j,
    Var(Δᵏe_j) = C(2k, k)·σ²,                                           (1)

and ``Δᵏs_j ≈ dtᵏ·s⁽ᵏ⁾(t_j)`` shrinks like ``dtᵏ`` for a smooth motion. The scale

    σ̂_k = 1.4826·median|Δᵏy| / √C(2k, k)                                 (2)

(the normalised median absolute value, consistent for Gaussian noise) ignores the few
samples where the motion is not smooth (a stick/slip transition or an impact puts a kink in
v or a step in a, which spreads over ``k + 1`` differences). So σ̂_k falls with k while the
motion still shows through, and stays level once the differences hold noise alone. The
estimate is σ̂_k at the first order ``k`` (from 2 up) that no higher order undercuts by more
than their combined standard error; when every order is undercut, the smallest σ̂_k is reported as
an upper bound (the motion is not resolved from the noise at this rate).

Standard error. Differences of neighbouring samples are correlated (an MA(k) process), so
the sampling error is taken from the spread of (2) over ``B`` contiguous blocks,
``se = std_b(σ̂_k,b)/√B`` (the block scales are nearly independent when a block is much
longer than ``k``).

Quantisation. An encoder or a fixed-point logger stores values on a lattice ``q·ℤ``. Then
the differences of an axis that moves less than ``q`` a sample are mostly 0 and (2) says
little. When the first differences lie on such a lattice and (2) does not exceed the
rounding error by two standard errors (or by its own resolution, a median of lattice
values moving in steps of q), the noise model is quantisation with step ``q``,
``σ = q/√12`` (a uniform rounding error); on a lattice finer than the noise, (2) stands.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from jaxtyping import Float

__all__ = ["FLIP_KAPPA", "NoiseEstimate", "estimate_noise", "reversals"]

#: κ of the near-rest band: a noise-driven sign flip of v outside ``|v| < κ·σ_v`` has
#: probability 2·(1 − Φ(4)) = 6.3e-5 per sample, less than one flip in a 10 000-sample
#: record, where each flip inside would put a spike of 2·F_static into the residual.
FLIP_KAPPA = 4.0

#: Orders of differences tried, lowest first: order 1 still holds the velocity at any
#: speed that matters, and above 6 the noise gain C(2k, k) (924 at k = 6) amplifies
#: rounding and the occasional kink more than it removes motion.
ORDERS = (2, 3, 4, 5, 6)
#: Contiguous blocks for the standard error; fewer samples per block than 8·(k+1) and the
#: block scales stop being nearly independent, so short records use fewer blocks.
BLOCKS = 8
#: Gaussian consistency factor of the median absolute value: 1/Φ⁻¹(3/4).
_MAD_TO_STD = 1.482602218505602
#: Share of first differences that must sit on one lattice ``q·ℤ`` to call the signal
#: quantised; the remainder allows the few samples a resampler or a unit conversion moves.
_LATTICE_SHARE = 0.99


@dataclass(frozen=True)
class NoiseEstimate:
    """A signal's noise scale estimated from its own high band.

    Attributes:
        sigma: noise standard deviation, in the signal's unit (m for x, N for a force).
        se: standard error of ``sigma`` (same unit); nan for a quantised signal.
        model: ``"white"`` (differences at an order where the motion no longer shows),
            ``"upper_bound"`` (no order resolved the noise: ``sigma`` bounds it from above) or
            ``"quantised"`` (values on a lattice of step ``step``).
        order: the difference order k that gave ``sigma`` (0 for a quantised signal).
        step: lattice step ``q`` of a quantised signal, else nan.
        by_order: σ̂_k for every order tried, ``{k: sigma_k}``.
    """

    sigma: float
    se: float
    model: Literal["white", "upper_bound", "quantised"]
    order: int
    step: float
    by_order: dict[int, float]

    def describe(self, unit: str) -> str:
        """One line for a report: the scale with its error and the noise model."""
        if self.model == "quantised":
            return f"{self.sigma:.3g} {unit} (quantised, step {self.step:.3g} {unit}: q/√12)"
        if self.model == "upper_bound":
            return f"≤ {self.sigma:.3g} {unit} (motion not resolved from noise by differences)"
        return f"{self.sigma:.3g} ± {self.se:.2g} {unit} (white, differences of order {self.order})"


def _differences_scale(y: Float[np.ndarray, " n"], k: int) -> float:
    """Eq. (2): the normalised median absolute k-th difference."""
    d = np.diff(y, n=k)
    return _MAD_TO_STD * float(np.median(np.abs(d))) / math.sqrt(math.comb(2 * k, k))


def _block_se(y: Float[np.ndarray, " n"], k: int) -> float:
    """Standard error of eq. (2) from its spread over contiguous blocks (nan if < 2 fit).

    The blocks are ``np.array_split``'s (the first ``n mod blocks`` one sample longer),
    taken as two 2-D arrays of equal rows so that each order costs two medians, not one
    per block (a fleet estimates the noise of every recording)."""
    blocks = min(BLOCKS, y.shape[0] // (8 * (k + 1)))
    if blocks < 2:
        return math.nan
    q, r = divmod(y.shape[0], blocks)
    parts = (y[: r * (q + 1)].reshape(r, q + 1), y[r * (q + 1) :].reshape(blocks - r, q))
    root = math.sqrt(math.comb(2 * k, k))
    scales = np.concatenate(
        [
            _MAD_TO_STD * np.median(np.abs(np.diff(b, n=k, axis=1)), axis=1) / root
            for b in parts
            if b.size
        ]
    )
    return float(np.std(scales, ddof=1) / math.sqrt(blocks))


def _lattice_step(y: Float[np.ndarray, " n"]) -> float:
    """The step ``q`` of a lattice holding ≥ 99 % of the first differences, else nan.

    The smallest nonzero |Δy| is a multiple of ``q``; the largest ``q = min|Δy|/m``
    (m = 1 … 10) for which Δy/q is an integer to within 1e-3 is taken (float32 storage of an
    encoder count keeps about 1e-7 relative, far inside that).
    """
    d = np.abs(np.diff(y))
    scale = float(np.max(np.abs(y))) if y.size else 0.0
    nonzero = d[d > 1e-12 * max(scale, 1e-300)]
    if nonzero.size == 0:
        return math.nan
    smallest = float(np.min(nonzero))
    for m in range(1, 11):
        ratio = d / (smallest / m)
        # noise on a continuum puts Δy/q anywhere, so near-integers everywhere mean a lattice
        if np.mean(np.abs(ratio - np.round(ratio)) < 1e-3) >= _LATTICE_SHARE:
            return smallest / m
    return math.nan


def estimate_noise(y: Float[np.ndarray, " n"]) -> NoiseEstimate:
    """Noise scale of a uniformly sampled signal from its own high band (module docstring).

    Args:
        y: the recorded signal [n] (x in m, or a measured force in N), at least 16 samples.

    Returns:
        :class:`NoiseEstimate` in the unit of ``y``.
    """
    y = np.asarray(y, dtype=np.float64)
    if y.ndim != 1 or y.shape[0] < 16:
        raise ValueError(f"estimate_noise needs a 1-D signal of >= 16 samples, got {y.shape}")
    by_order = {k: _differences_scale(y, k) for k in ORDERS if y.shape[0] > 2 * k}
    white = _white(y, by_order)
    step = _lattice_step(y)
    # on a lattice finer than the noise, the differences measure the noise (rounding
    # included); where they are consistent with the rounding error or below it (an axis
    # that moves less than q a sample repeats values), the lattice explains the noise
    # (on a lattice the median in (2) moves in steps of q, so that is its resolution too)
    rounding = step / math.sqrt(12.0)
    k = max(white.order, 1)
    resolution = _MAD_TO_STD * step / math.sqrt(math.comb(2 * k, k))
    margin = max(2 * np.nan_to_num(white.se), resolution)
    if math.isfinite(step) and not white.sigma - margin > rounding:
        return NoiseEstimate(rounding, math.nan, "quantised", 0, step, by_order)
    return white


def _white(y: Float[np.ndarray, " n"], by_order: dict[int, float]) -> NoiseEstimate:
    """The white-noise estimate of eq. (2) at the order chosen as the docstring says."""
    orders = sorted(by_order)
    ses = {k: _block_se(y, k) for k in orders}
    for i, k in enumerate(orders[:-1]):
        # the first order whose scale no later order undercuts: motion only adds to (2)
        k_low = min(orders[i + 1 :], key=lambda j: by_order[j])
        tol = math.hypot(ses[k], ses[k_low])
        if math.isfinite(tol) and by_order[k] - by_order[k_low] <= tol:
            return NoiseEstimate(by_order[k], ses[k], "white", k, math.nan, by_order)
    k_min = min(orders, key=lambda k: by_order[k])
    return NoiseEstimate(by_order[k_min], ses[k_min], "upper_bound", k_min, math.nan, by_order)


def reversals(v: Float[np.ndarray, " n"], band: float) -> int:
    """Velocity reversals [count] of a filtered velocity [m/s]: crossings from above
    ``+band`` to below ``−band`` or back, ``band`` [m/s] the speed under which noise can
    flip the sign of v (``FLIP_KAPPA·σ_v``). Counting every sign change instead counts the
    noise's flips while the body rests or turns slowly (33 "reversals" on a record whose
    plot shows about 6)."""
    v = np.asarray(v, dtype=np.float64)
    side = np.sign(v[np.abs(v) > band])
    return int(np.sum(side[1:] != side[:-1])) if side.size else 0
