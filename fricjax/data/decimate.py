"""Zero-phase anti-alias filtering and decimation of equation-error residuals (IDIM-LS).

The IDIM-LS recipe (Gautier; Janot, Gautier & Brunot 2019 for EMPS) low-pass filters and
decimates *every column* of the observation matrix ``W`` and the force ``τ`` by ``nd``
(MATLAB ``decimate``: 8th-order Chebyshev I, 0.05 dB ripple, cutoff 0.8·(fs/2)/nd, run
forward and backward), then solves ``D τ = (D W) θ`` by least squares. ``D`` is linear, so
that is least squares on the decimated residual ``D r``, ``r = τ − W θ``:

    (D y)_i = Σ_j k_j · ỹ_{i·q + j},      i = 0 … ⌈n/q⌉ − 1,   j = −h … h

with ``k = g ⋆ g̃`` the impulse response of the zero-phase filter (``g`` the causal
Chebyshev response, normalised to unit DC gain, ``g̃`` its time reverse), truncated where
``|k_j| < tol·max|k|``, and ``ỹ`` the record extended by odd reflection about its end
samples (``ỹ_{−j} = 2·y_0 − y_j``), which keeps value and slope continuous at the ends.

Decimating the *columns* is not the same as decimating the signals and recomputing the
columns: the Coulomb column ``sgn(v)`` becomes a smooth step across each reversal in the
first case and stays a jump in the second. On EMPS the two differ by 2.5 published σ on
Fv, which is why this operates on residuals, not on recordings.

Unit DC gain (scipy's and MATLAB's filter keep the Chebyshev pass-band ripple at DC,
(1 − 0.0057)² = 0.9886 after two passes) makes a constant force — an offset — decimate to
itself; it matters only when some columns are decimated and others not. On DATA_EMPS the
error norm of the published parameters is 108.78 N with it, 107.54 N without; the
publication prints 108.76 N.

The result equals a forward-backward pass of the same filter in second-order sections
(``scipy.signal.sosfiltfilt`` with odd padding of ``h`` samples) to 1e-12 relative, ends
included. ``scipy.signal.decimate`` itself filters in transfer-function form (≈1e-8
relative rounding at q = 10) with 27 samples of padding, so it differs from this in the
first and last ~30 output samples (by up to 1 % of the signal there).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from fricjax.errors import FricjaxError, where

__all__ = ["antialias_kernel", "check_factor", "decimate", "decimate_np", "decimated_length"]

#: MATLAB / scipy ``decimate`` default anti-alias filter: Chebyshev I, order 8, 0.05 dB.
CHEBY_ORDER = 8
CHEBY_RIPPLE_DB = 0.05


def antialias_kernel(q: int, *, tol: float = 1e-13) -> Float[np.ndarray, " L"]:
    """Two-sided impulse response ``k`` [L = 2h + 1] of the zero-phase anti-alias filter.

    The causal filter is the Chebyshev I low-pass of order 8, ripple 0.05 dB, cutoff
    0.8/q of the Nyquist frequency (``scipy.signal.decimate``'s default), scaled to unit DC
    gain; ``k = g ⋆ g̃`` is its forward-backward (zero-phase) response, symmetric,
    ``Σ k = 1``, truncated where ``|k_j| < tol·max|k|`` (h = 1545 samples at q = 10).

    Raises:
        FricjaxError: ``q`` not an integer ≥ 2.
    """
    if isinstance(q, bool) or not isinstance(q, int | np.integer) or q < 2:
        raise FricjaxError(f"{where('decimate', 'q')}: must be an integer >= 2, got {q!r}")
    from scipy import signal  # lazily: importing scipy.signal costs ~0.6 s of CPU

    sos = signal.cheby1(CHEBY_ORDER, CHEBY_RIPPLE_DB, 0.8 / int(q), output="sos")
    # The slowest pole decays within a few hundred samples per unit of q; 400·q samples
    # hold the response down to far below tol.
    impulse = np.zeros(400 * int(q))
    impulse[0] = 1.0
    g = signal.sosfilt(sos, impulse)
    g /= g.sum()
    k = np.convolve(g, g[::-1])
    centre = g.shape[0] - 1
    big = np.flatnonzero(np.abs(k) >= tol * np.max(np.abs(k)))
    half = int(max(centre - big[0], big[-1] - centre))
    k = k[centre - half : centre + half + 1]
    k = 0.5 * (k + k[::-1])  # exactly symmetric: zero phase to rounding
    return k / k.sum()


def decimated_length(n: int, q: int) -> int:
    """Number of samples ``⌈n/q⌉`` kept by :func:`decimate` (indices 0, q, 2q, …)."""
    return -(-int(n) // int(q))


@partial(jax.jit, static_argnames=("q",))
def decimate(y: Float[Array, " n"], kernel: Float[Array, " L"], q: int) -> Float[Array, " m"]:
    """Zero-phase low-pass of ``y`` [n] with ``kernel`` [L = 2h + 1], kept at 0, q, 2q, ….

    Pure JAX and linear in ``y`` (so ``jax.jvp``/``vmap`` pass straight through, e.g. for
    Levenberg–Marquardt on a decimated residual). Needs ``n > h``; returns shape
    [⌈n/q⌉], same unit as ``y``.
    """
    y = jnp.asarray(y, dtype=jnp.float64)
    kernel = jnp.asarray(kernel, dtype=jnp.float64)
    n, length = y.shape[0], kernel.shape[0]
    half = (length - 1) // 2
    if n <= half:
        raise FricjaxError(
            f"{where('decimate', 'y')}: {n} samples, need more than the filter's half length "
            f"{half} to decimate by {q}"
        )
    left = 2.0 * y[0] - y[half:0:-1]
    right = 2.0 * y[-1] - y[-2 : -half - 2 : -1]
    padded = jnp.concatenate([left, y, right])
    out = jax.lax.conv_general_dilated(
        padded[None, None, :],
        kernel[::-1][None, None, :],
        window_strides=(q,),
        padding="VALID",
    )
    return out[0, 0]


def decimate_np(y: Float[np.ndarray, " n"], q: int) -> Float[np.ndarray, " m"]:
    """:func:`decimate` with the default kernel, numpy in and out (``q = 1``: unchanged)."""
    if q == 1:
        return np.asarray(y, dtype=np.float64)
    k = antialias_kernel(q)
    return np.asarray(decimate(jnp.asarray(y, dtype=jnp.float64), jnp.asarray(k), q))


def check_factor(q: object, source: str | None = None) -> int:
    """``q`` as an int ≥ 1, or a one-line :class:`FricjaxError` naming ``source``."""
    if isinstance(q, bool) or not isinstance(q, int | np.integer) or q < 1:
        raise FricjaxError(f"{where(source, 'decimate')}: must be an integer >= 1, got {q!r}")
    return int(q)
