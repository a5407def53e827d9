"""Whitening of equation-error residuals: the space every diagnosis statistic lives in.

Noise model. White noise ``e`` (std σ_x [m]) on the displacement reaches the equation-error
residual ``r = m·a − (F_p − F_f(v))`` (seed eq. 5/11) through the preprocessing
(:func:`fricjax.data.preprocess.derivatives`), which is linear in x: ``v = L_v x``,
``a = L_a x``. Linearising the friction in v (damping ``c = mean ∂F_f/∂v`` [N·s/m]; the
friction enters r with a plus sign),

    r_noise ≈ K·e,      K = m·L_a + c·L_v          [N per m],  shape [n, n + 2·trim],

and away from the record ends K is a convolution with frequency response

    H(f) = m·H_a(f) + c·H_v(f)      [N/m]          (H_a ≈ −(2πf)², H_v ≈ i·2πf in the pass band).

(The sign of c only conjugates H in the interior, a rotation of each bin's (Re, Im) pair
that leaves whiteness unchanged; at the record ends it matters, measured up to 0.043 in
the covariance of the 0.272 s paper twin, tested.)

A held-out part of a record (:attr:`fricjax.problem.Problem.window`) is a set of rows of
the whole record's K: at a cut end its rows are the stationary kernel reaching into the
x-samples beyond the cut, and the edge correction below uses those rows, not the
record-end rows of a record that really ended there.

Whitened vector (``z = W·y``, shape [M], unit metres). With ``Y_k`` the rfft of y [n] and
``keep`` the kept bins,

    z⁰ = [Re(Y_k·g_k), Im(Y_k·g_k)]_{k ∈ keep},   g_k = 1 / (H_k·√(n/2))   (√n at DC/Nyquist)

(the imaginary parts of DC and Nyquist, always zero, are dropped). If K were circulant,
``z⁰`` of the residual noise would be exactly the normalised Fourier coefficients of e, i.e.
i.i.d. N(0, σ_x²). It is not: the record is a finite window of a longer filtered record
(``trim`` samples cut at each end, odd padding and filter start-up at the ends), and the
rectangular window leaks the strong mid-band noise into the weak low and high bins. On the
0.272 s paper twin the bin variances of ``z⁰`` are off by up to ×16 and neighbouring bins
correlate up to 0.99 (2 s record: ×380 near the band edge), so ``z⁰`` alone is not usable.

Exact correction. ``K`` differs from the circulant ``K_c`` (the stationary kernel wrapped
on the n-sample window) only in the rows within the kernel's reach ``L`` of either window
end: ``K = K_c·S + P_Rᵀ·Δ_R`` (S selects the window columns, R the edge rows). The edge
rows are measured exactly, by running :func:`derivatives` on unit impulses placed near the
record ends (trim, padding and start-up included). Then ``C = Cov(z⁰)/σ_x² =
I + P·G_Rᵀ + G_R·Pᵀ + G_R·Δ_RΔ_Rᵀ·G_Rᵀ`` with ``G_R`` the whitener's columns at the rows R and
``P = A·Δ_Rᵀ`` (A the circulant part), a rank ≤ 2|R| update of the identity, and

    W·y = C^(-1/2)·z⁰ = z⁰ + U·(s ⊙ (Uᵀ z⁰)),    U [M, q] orthonormal, s = λ^(-1/2) − 1,

the symmetric (Löwdin) orthogonalisation: of all exact whiteners it is the one closest to
``z⁰``, so each entry still belongs to one frequency bin. Under the linearised noise model
``W·r_noise ~ N(0, σ_x²·I_M)`` exactly (up to the kernel cut at 1e-13 of its peak).

Velocity reversals. The linearisation fails where a Coulomb/Stribeck term meets noise on v
near v = 0: ``sgn(v + δv)`` flips and the residual gets spikes of ±2·F_s (380 N on the paper
twin) that ``K·e`` does not contain. Spikes are broadband in r while ``|H|`` vanishes at low
frequency, so they swamp the low bins: on the 2 s paper twin at its true parameters
(σ_x = 24 µm, exact trajectory plus preprocessed noise, 51 reversals) the whitened power was
16 000 σ_x² per bin below 2 Hz, 1 600 at 2–5 Hz, 360 at 5–10 Hz, 40 at 10–20 Hz, 5 at 20–50 Hz
and ≈ 1 above. ``exclude`` (the near-rest band of :mod:`fricjax.diagnose.evidence`) treats
such samples as missing: the whitened vector is projected off ``W·e_i`` for every excluded
sample i, which removes the spikes exactly (they live on those samples) at the price of one
degree of freedom each (``dof = M − rank``); with ``|v| < 4·σ_v`` excluded (127 of 1 980
samples) the same records gave 1.6 σ_x² below 2 Hz (time-varying Stribeck slope, not
modelled), 1.0–1.1 elsewhere.
A plant that sticks at reversals has far more such samples (198–214 of 960 on 1 s records of
the concealed benchmark), and one degree of freedom each would leave little to test. Spikes
on neighbouring samples share a few low-frequency directions, so ``spike`` (the largest
spike over σ_x) projects out only the directions where a spike would keep more than
``SPIKE_TOL``·σ_x: on those records at their true parameters 145 and 116 σ_x² at 120 dof,
where exact exclusion of the 80 samples of smallest |v| (the former cap) left 852 and 289.

Kept bins: ``|H_k| ≥ rel_floor·max|H|`` AND ``f_k`` below the stop band of the smoothing
(:func:`stop_band_hz`), whichever is lower. Both are needed: the floor drops the bins where
the residual noise vanishes (DC: derivatives of x have no DC noise at all), and the stop-band
cut drops the bins where the preprocessing has removed the signal but not the model force
(``F*`` is evaluated from t and the smoothed v, ``m·a`` is smoothed twice more): there the
residual is derivative bias and model force, not noise, and dividing by the small ``H_k``
would turn that into spurious significance. For Savitzky–Golay smoothing only the stop-band
cut removes the side lobes, where ``|H|`` rises above the floor again.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float
from scipy import sparse

from fricjax.data.preprocess import PreprocessSettings, derivatives
from fricjax.errors import FricjaxError, where
from fricjax.problem import Problem

# Impulse responses are cut where both fall below this fraction of their peak; the rows of K
# beyond that reach equal the circulant rows to this relative precision.
_KERNEL_EPS = 1e-13
# Stop band: first frequency where the smoothing gain on acceleration, |H_a(f)|/(2πf)², falls
# below this value (module docstring). At the Butterworth default (order 4, 100 Hz, 1 kHz)
# that is 108 Hz. Measured on the noise-free 2 s paper twin at its true parameters: with the
# band cut at gain 0.02 (121 Hz) the whitened residual at 115 Hz held 85 σ² (σ_x = 24 µm) of
# derivative bias, at 0.005 (132 Hz) 540 σ², at 0.1 none of the 5 largest bins lay above
# 20 Hz (those are the drive harmonics, which the fitted harmonic parameters absorb).
_STOP_GAIN = 0.1
# Frequency grid (points per Nyquist interval) on which the stop band is located.
_STOP_GRID = 1 << 14
# Largest whitened norm [σ_x] that one spike on an excluded sample may keep after the
# projection (make_whitener's ``spike``). Measured at the true parameters of two 1 s null
# records of the concealed benchmark (stick phases: 198 and 214 samples with |v| < 4·σ_v):
# projecting out the directions with s_j·spike > 0.25 (≤ 80 of M = 200) leaves 145 and
# 116 σ_x² at 120 dof, where excluding the 80 samples of smallest |v| exactly left 852 and
# 289 σ_x² at the same dof (the flips on the other samples); the noise-free records keep
# 0.8 and 5.1 σ_x² of flip/stick residual.
SPIKE_TOL = 0.25


@dataclass(frozen=True, eq=False)
class Whitener:
    """The linear map ``W``: residual-like vectors [n] -> whitened vectors [M] (metres).

    Attributes:
        n: residual length (samples of the trimmed record).
        keep: rfft bin indices kept, increasing, shape [K].
        gain: complex ``1/(H_k·√(n/2))`` (``√n`` at DC/Nyquist) for the kept bins [m/N],
            shape [K]; ``|gain|`` is ``1/|H(f_k)|`` with the Fourier normalisation.
        M: length of a whitened vector, ``2K − len(drop_imag)``.
        drop_imag: positions in ``keep`` (DC/Nyquist) whose imaginary part is not stored.
        U, s: exact edge correction ``W y = z⁰ + U (s ⊙ Uᵀ z⁰)``, U [M, q] orthonormal
            columns, s [q] (module docstring); q = 0 when no correction is needed.
        freqs: frequencies of the kept bins [Hz], shape [K].
        dt: sample step [s]; mass [kg] and damping [N·s/m] of the noise model;
        f_stop: stop-band edge used [Hz]; H_max: ``max|H|`` over the rfft grid [N/m].
        N: orthonormal basis [M, e] of the whitened excluded samples; ``W`` projects it out,
            so ``W·r_noise ~ N(0, σ_x²·(I − N Nᵀ))`` with ``dof = M − e`` degrees of freedom
            (e = 0 without ``exclude``).
        excluded: bool [n], the samples treated as missing.
        spectral: True when the bins are scaled by a fitted residual spectrum
            (:func:`noise_spectrum`) instead of the displacement-noise response; the
            whitened vector is then unitless (noise variance ≈ 1 per entry).
    """

    n: int
    keep: np.ndarray
    gain: np.ndarray
    M: int
    drop_imag: tuple[int, ...]
    U: np.ndarray
    s: np.ndarray
    freqs: np.ndarray
    dt: float
    mass: float
    damping: float
    f_stop: float
    H_max: float
    N: np.ndarray
    excluded: np.ndarray
    spectral: bool = False
    rank_cap: int = 0

    @property
    def dof(self) -> int:
        """Degrees of freedom of a whitened noise vector: ``M`` minus the excluded samples."""
        return self.M - int(self.N.shape[1])

    @property
    def im_keep(self) -> np.ndarray:
        """Positions in ``keep`` whose imaginary part is stored, shape [M − K]."""
        mask = np.ones(self.keep.shape[0], dtype=bool)
        mask[list(self.drop_imag)] = False
        return np.flatnonzero(mask)

    def base(self, y: Float[np.ndarray, "n ..."]) -> Float[np.ndarray, "M ..."]:
        """``z⁰``: scaled in-band Fourier coefficients of y, before the edge correction."""
        y = np.asarray(y, dtype=np.float64)
        if y.shape[0] != self.n:
            raise FricjaxError(
                f"{where('whitener', 'y')}: has {y.shape[0]} samples, the whitener {self.n}"
            )
        spec = np.fft.rfft(y, axis=0)[self.keep]
        spec = spec * self.gain.reshape((-1,) + (1,) * (y.ndim - 1))
        return np.concatenate([spec.real, spec.imag[self.im_keep]], axis=0)

    def correct(self, z0: Float[np.ndarray, "M ..."]) -> Float[np.ndarray, "M ..."]:
        """``C^(-1/2)·z⁰`` (exact whitening of the finite, trimmed record)."""
        if self.s.size == 0:
            return z0
        coef = np.tensordot(self.U.T, z0, axes=1)
        coef = coef * self.s.reshape((-1,) + (1,) * (z0.ndim - 1))
        return z0 + np.tensordot(self.U, coef, axes=1)

    def __call__(self, y: Float[np.ndarray, "n ..."]) -> Float[np.ndarray, "M ..."]:
        """``W·y``: y [n] -> [M] or [n, k] -> [M, k] (numpy)."""
        z = self.correct(self.base(y))
        if self.N.shape[1]:
            z = z - np.tensordot(self.N, np.tensordot(self.N.T, z, axes=1), axes=1)
        return z

    def apply_jax(self, y: Float[Array, "n ..."]) -> Float[Array, "M ..."]:
        """``W·y`` in jax.numpy (traceable; the whitener's arrays become constants)."""
        return self.module(y)

    @property
    def module(self) -> WhitenOp:
        """The same map as an equinox Module: arrays are leaves, so a jitted function taking
        it as an argument compiles once for every whitener of the same shape.

        U and s are padded with zero columns to a multiple of 32 (at most M; none when U is
        empty), N to ``rank_cap`` (when the whitener was made with ``max_rank``): zero
        columns change neither the edge correction nor the projection, and the ranks vary
        from record to record (N: 31 to 80 columns over twelve 1 s benchmark records, U: 197
        to 200), so without the padding every record recompiled every jitted residual of
        the diagnosis. The multiple of 32, not M, keeps a long record's few correction
        columns few."""
        q = min(self.M, -(-self.U.shape[1] // 32) * 32)
        return WhitenOp(
            jnp.asarray(self.keep),
            jnp.asarray(self.gain),
            jnp.asarray(self.im_keep),
            jnp.asarray(_pad_columns(self.U, q)),
            jnp.asarray(_pad_columns(self.s[None, :], q)[0]),
            jnp.asarray(_pad_columns(self.N, self.rank_cap)),
        )


def _pad_columns(a: np.ndarray, width: int) -> np.ndarray:
    if width <= a.shape[1]:
        return a
    return np.pad(a, ((0, 0), (0, width - a.shape[1])))


class WhitenOp(eqx.Module):
    """``y [n, ...] -> W·y [M, ...]`` in jax (see :class:`Whitener`)."""

    keep: Array
    gain: Array
    im_keep: Array
    U: Array
    s: Array
    N: Array

    def __call__(self, y: Float[Array, "n ..."]) -> Float[Array, "M ..."]:
        y = jnp.asarray(y, dtype=jnp.float64)
        shape = (-1,) + (1,) * (y.ndim - 1)
        spec = jnp.fft.rfft(y, axis=0)[self.keep] * self.gain.reshape(shape)
        z0 = jnp.concatenate([spec.real, spec.imag[self.im_keep]], axis=0)
        coef = jnp.tensordot(self.U.T, z0, axes=1) * self.s.reshape(shape)
        z = z0 + jnp.tensordot(self.U, coef, axes=1)
        return z - jnp.tensordot(self.N, jnp.tensordot(self.N.T, z, axes=1), axes=1)


# -- responses of the preprocessing ---------------------------------------------------------


@lru_cache(maxsize=16)
def _kernels(settings: PreprocessSettings, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Stationary impulse responses ``(g_v, g_a)`` of x -> v, x -> a, each [2L + 1], index
    ``L + d`` holding the response d samples after the impulse (d = −L … L) [1/s, 1/s²]."""
    fs = 1.0 / dt
    if settings.method == "butterworth":
        # As in noise_gains: 20·order cutoff periods hold all but e^(-40π) of the response.
        half = math.ceil(20.0 * settings.order * fs / settings.cutoff_hz)
    else:
        half = settings.savgol_window
    n = 2 * half + 1
    impulse = np.zeros(n)
    impulse[half] = 1.0
    d = derivatives(np.arange(n) * dt, impulse, replace(settings, trim=0))
    big = (np.abs(d.v) > _KERNEL_EPS * np.abs(d.v).max()) | (
        np.abs(d.a) > _KERNEL_EPS * np.abs(d.a).max()
    )
    reach = int(np.max(np.abs(np.flatnonzero(big) - half)))
    cut = slice(half - reach, half + reach + 1)
    return d.v[cut].copy(), d.a[cut].copy()


def _wrap(g: np.ndarray, n: int) -> np.ndarray:
    """Kernel [2L + 1] (centred) folded onto a circle of n samples: ``gw[d mod n] += g[d]``."""
    reach = (g.shape[0] - 1) // 2
    out = np.zeros(n)
    np.add.at(out, np.arange(-reach, reach + 1) % n, g)
    return out


def noise_response(
    settings: PreprocessSettings, dt: float, n: int
) -> tuple[np.ndarray, np.ndarray]:
    """Frequency responses ``(H_v [1/s], H_a [1/s²])`` of x -> v and x -> a on the rfft grid
    ``f_k = k/(n·dt)``, k = 0 … n//2 (complex, shape [n//2 + 1]).

    Measured exactly: :func:`derivatives` is applied to a unit impulse in the middle of a
    record long enough for its response to decay to 1e-13 of its peak before the ends, so
    the response is the operator's stationary (interior) kernel g; ``H(f_k) = Σ_d g[d]
    e^(−2πi k d / n)`` is its DTFT at the grid frequencies (evaluated as the rfft of g folded
    onto n samples, which is exact). The ends of a finite record (padding, start-up, trim)
    are not part of H; :func:`make_whitener` measures and corrects for them.
    """
    if n < 2 or dt <= 0:
        raise FricjaxError(f"{where('noise_response', 'n, dt')}: need n >= 2 and dt > 0")
    g_v, g_a = _kernels(settings, float(dt))
    return np.fft.rfft(_wrap(g_v, n)), np.fft.rfft(_wrap(g_a, n))


def stop_band_hz(settings: PreprocessSettings, dt: float) -> float:
    """Lower edge of the smoothing's stop band [Hz]: the first frequency where the gain on
    acceleration ``|H_a(f)|/(2πf)²`` drops below 0.1 (the Nyquist frequency if never)."""
    n = 2 * _STOP_GRID
    _, h_a = noise_response(settings, dt, n)
    f = np.fft.rfftfreq(n, dt)
    gain = np.abs(h_a[1:]) / (2 * np.pi * f[1:]) ** 2
    low = np.flatnonzero(gain < _STOP_GAIN)
    return float(f[1 + low[0]]) if low.size else float(f[-1])


# -- the whitener ---------------------------------------------------------------------------


def make_whitener(
    problem: Problem,
    *,
    damping: float | None = None,
    rel_floor: float = 1e-3,
    mass: float | None = None,
    exclude: Float[np.ndarray, " n"] | None = None,
    spectrum: Float[np.ndarray, " k"] | None = None,
    spike: float | None = None,
    max_rank: int | None = None,
) -> Whitener:
    """The exact whitener of ``problem``'s residual noise (module docstring).

    Args:
        problem: a problem with its :class:`PreprocessSettings` (``problem.preprocess``).
        damping: linearised damping ``c = mean ∂F_f/∂v`` of the fitted model [N·s/m]
            (default 0: the noise is ``m·L_a e``).
        rel_floor: bins with ``|H_k| < rel_floor·max|H|`` are dropped.
        mass: moving mass [kg] (default ``problem.spec["mass"].init``; pass the fitted
            mass when it is free).
        exclude: optional bool mask [n] of samples treated as missing (e.g.
            :func:`~fricjax.diagnose.evidence.near_rest_band`); default none.
        spike: largest residual spike an excluded sample can carry, over σ_x [1/m·N]
            (``2·|F_static|/σ_x`` for a Coulomb sign flip). Given, only the whitened
            directions of the excluded samples along which such a spike would leave more
            than ``SPIKE_TOL·σ_x`` are projected out (singular values ``s_j·spike >
            SPIKE_TOL``), instead of all of them: spikes on neighbouring samples share a
            few (low-frequency) directions, so a whole stick phase costs a few degrees of
            freedom, not one per sample. Default: every direction (exact).
        max_rank: at most this many directions projected out (the largest first).
        spectrum: optional noise power S_k [N²] of the residual on the rfft grid
            (k = 0 … n//2, e.g. :func:`noise_spectrum`): the bins are scaled by
            ``1/√S_k`` instead of ``1/|H_k|``. For residuals whose noise is not the
            displacement sensor's alone (a recorded drive input u enters ``g·u − m·a − F``
            directly, with current ripple and the controller's feedback of encoder noise).
            The edge correction, derived for displacement noise, is skipped (its rows
            reach ``L`` samples from each end: 0.5 % of a 24.8 s EMPS record).

    Returns:
        :class:`Whitener` with ``W·r_noise ~ N(0, σ_x²·I_M)`` under the linearised model
        (``σ_x²·(I − N Nᵀ)`` with ``dof`` degrees of freedom when samples are excluded).
    """
    settings = problem.preprocess
    src = problem.source or problem.name or None
    if settings is None:
        raise FricjaxError(
            f"{where(src, 'preprocess')}: the problem carries no preprocessing settings, "
            "so its residual noise cannot be modelled"
        )
    c = 0.0 if damping is None else float(damping)
    m = float(problem.spec["mass"].init if mass is None else mass)
    if not (math.isfinite(c) and math.isfinite(m) and m > 0):
        raise FricjaxError(
            f"{where(src, 'mass, damping')}: need a positive mass and a finite damping, "
            f"got {m!r}, {c!r}"
        )
    if not 0.0 <= rel_floor < 1.0:
        raise FricjaxError(f"{where(src, 'rel_floor')}: must be in [0, 1), got {rel_floor!r}")
    t = np.asarray(problem.t, dtype=np.float64)
    n = int(t.shape[0])
    if n < 3:
        raise FricjaxError(f"{where(src, '/t')}: {n} samples, need at least 3 to whiten")
    dt = float((t[-1] - t[0]) / (n - 1))

    g_v, g_a = _kernels(settings, dt)
    g = m * g_a + c * g_v
    H = np.fft.rfft(_wrap(g, n))
    freqs = np.fft.rfftfreq(n, dt)
    f_stop = stop_band_hz(settings, dt)
    if spectrum is not None:
        spec_k = np.asarray(spectrum, dtype=np.float64)
        if spec_k.shape != H.shape or not np.all(np.isfinite(spec_k) & (spec_k >= 0)):
            raise FricjaxError(
                f"{where(src, 'spectrum')}: must be finite, ≥ 0 and of shape {H.shape}"
            )
        # Only |H| matters for whiteness (a per-bin phase is a rotation of the pair).
        H = np.sqrt(spec_k)
    H_max = float(np.abs(H).max())
    keep = np.flatnonzero((np.abs(H) >= rel_floor * H_max) & (freqs < f_stop) & (H_max > 0))
    if keep.size == 0:
        raise FricjaxError(
            f"{where(src, 'preprocess')}: no frequency bin passes the noise floor below the "
            f"stop band ({f_stop:g} Hz): the record is too short to whiten"
        )
    edge = (keep == 0) | ((n % 2 == 0) & (keep == n // 2))
    norm = np.where(edge, math.sqrt(n), math.sqrt(n / 2.0))
    gain = 1.0 / (H[keep] * norm)
    drop_imag = tuple(int(i) for i in np.flatnonzero(edge))
    M = 2 * keep.size - len(drop_imag)
    proto = Whitener(
        n=n,
        keep=keep,
        gain=gain,
        M=M,
        drop_imag=drop_imag,
        U=np.zeros((M, 0)),
        s=np.zeros(0),
        freqs=freqs[keep],
        dt=dt,
        mass=m,
        damping=c,
        f_stop=f_stop,
        H_max=H_max,
        N=np.zeros((M, 0)),
        excluded=np.zeros(n, dtype=bool),
        spectral=spectrum is not None,
    )
    if spectrum is not None:
        wh = proto
    else:
        U, s = _edge_correction(proto, settings, g, n, m, c, problem.window)
        wh = replace(proto, U=U, s=s)
    if exclude is None:
        return wh
    mask = np.asarray(exclude)
    if mask.shape != (n,) or mask.dtype != bool:
        raise FricjaxError(
            f"{where(src, 'exclude')}: must be a bool mask of shape ({n},), "
            f"got {mask.dtype} {mask.shape}"
        )
    idx = np.flatnonzero(mask)
    if idx.size == 0:
        return wh
    unit = np.zeros((n, idx.size))
    unit[idx, np.arange(idx.size)] = 1.0
    basis, sv, _ = np.linalg.svd(wh(unit), full_matrices=False)
    rank = int(np.sum(sv > 1e-10 * sv[0])) if sv.size and sv[0] > 0 else 0
    if spike is not None:
        rank = min(rank, int(np.sum(sv * spike > SPIKE_TOL)))
    if max_rank is not None:
        rank = min(rank, int(max_rank))
    if rank >= M:
        raise FricjaxError(
            f"{where(src, 'exclude')}: excluding {idx.size} samples leaves no degree of "
            f"freedom of the {M} whitened ones"
        )
    return replace(wh, N=basis[:, :rank], excluded=mask.copy(), rank_cap=int(max_rank or 0))


@lru_cache(maxsize=8)
def _edge_probe(
    settings: PreprocessSettings, dt: float, n: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Exact edge rows of ``L_v`` and ``L_a``: ``(rows [R], cols [C], Lv [R, C], La [R, C])``,
    the window rows the record ends influence and their entries in the columns near the
    ends (all other entries of these rows are the stationary kernel or zero)."""
    trim = settings.trim
    n_full = n + 2 * trim
    g_v, g_a = _kernels(settings, dt)
    reach = (g_v.shape[0] - 1) // 2
    # End effects reach the kernel's reach plus the end padding (Butterworth: as in
    # preprocess, the longer of 3·(2·sections + 1) samples and 3 cutoff periods) or the
    # end-window polynomial fit (Savitzky–Golay) into the record. Measured deepest
    # deviating rows: 143 for reach 142 (order 4, 100 Hz), 951 for 882 (order 8, 30 Hz),
    # 12 for Savitzky–Golay's 13.
    if settings.method == "butterworth":
        sections = (settings.order + 1) // 2
        pad = max(3 * (2 * sections + 1), math.ceil(3.0 / (dt * settings.cutoff_hz)))
    else:
        pad = settings.savgol_window
    depth = min(n, reach + pad + 8)
    rows = np.unique(np.concatenate([np.arange(depth), np.arange(n - depth, n)]))
    # Columns within `probe` of an end see the padding or the one-sided differences; the
    # others respond with the stationary kernel. Up to `span`, the edge rows see them.
    probe = min(n_full, reach + pad + 8)
    span = min(n_full, depth + trim + reach + 1)
    cols = np.unique(np.concatenate([np.arange(span), np.arange(n_full - span, n_full)]))
    # Probes run on a shortened record whose ends are the record's ends and whose middle
    # is long enough (≥ 2·reach beyond the probed columns) for the far end's influence to
    # have decayed below the kernel cut.
    n_probe = min(n_full, 2 * (span + 2 * reach))
    shift = n_full - n_probe
    start = rows < n // 2
    rows_probe = np.where(start, rows, rows - shift)
    # Stationary entries first: row i (record index i + trim) from column j is g[i + trim − j].
    lag = rows[:, None] + trim - cols[None, :]
    inside = np.abs(lag) <= reach
    Lv = np.where(inside, g_v[np.clip(lag + reach, 0, 2 * reach)], 0.0)
    La = np.where(inside, g_a[np.clip(lag + reach, 0, 2 * reach)], 0.0)
    t_probe = np.arange(n_probe) * dt
    impulse = np.zeros(n_probe)
    for c_idx, j in enumerate(cols):
        near_start = j < probe
        near_end = j >= n_full - probe
        if not (near_start or near_end or shift == 0):
            continue
        jp = j if j < n_full // 2 else j - shift
        impulse[jp] = 1.0  # one derivatives() call per probed column
        d = derivatives(t_probe, impulse, settings)
        impulse[jp] = 0.0
        # On a shortened record a column only reaches the rows at its own end.
        hit = (start == (j < n_full // 2)) | (shift == 0)
        Lv[hit, c_idx] = d.v[rows_probe[hit]]
        La[hit, c_idx] = d.a[rows_probe[hit]]
    return rows, cols, Lv, La


@lru_cache(maxsize=8)
def noise_operators(settings: PreprocessSettings, dt: float, n: int) -> tuple[Any, Any]:
    """``(L_v, L_a)``: the preprocessing's exact linear maps from the raw x [n + 2·trim] to
    the kept v [n] [1/s] and a [n] [1/s²], as scipy CSR matrices [n, n + 2·trim].

    Banded: the stationary kernel (:func:`_kernels`, cut at 1e-13 of its peak) everywhere
    except the end rows, which are the measured rows of :func:`_edge_probe`. Cached (the
    whitener of a record and of its held-out parts share them); do not modify the result."""
    trim = settings.trim
    n_full = n + 2 * trim
    g_v, g_a = _kernels(settings, dt)
    reach = (g_v.shape[0] - 1) // 2
    p_rows, p_cols, Lv_p, La_p = _edge_probe(settings, dt, n)
    probed = np.zeros(n, dtype=bool)
    probed[p_rows] = True
    lags = np.arange(-reach, reach + 1)
    rows = np.repeat(np.flatnonzero(~probed), lags.size)
    cols = rows + trim - np.tile(lags, int((~probed).sum()))
    kern = np.tile(lags + reach, int((~probed).sum()))
    ok = (cols >= 0) & (cols < n_full)
    out = []
    for g, dense in ((g_v, Lv_p), (g_a, La_p)):
        pr, pc = np.nonzero(dense)
        mat = sparse.coo_matrix(
            (
                np.concatenate([g[kern[ok]], dense[pr, pc]]),
                (np.concatenate([rows[ok], p_rows[pr]]), np.concatenate([cols[ok], p_cols[pc]])),
            ),
            shape=(n, n_full),
        )
        out.append(mat.tocsr())
    return out[0], out[1]


def _edge_correction(
    wh: Whitener,
    settings: PreprocessSettings,
    g: np.ndarray,
    n: int,
    m: float,
    c: float,
    window: tuple[int, int] | None,
) -> tuple[np.ndarray, np.ndarray]:
    """``U [M, q]``, ``s [q]`` with ``C^(-1/2) = I + U diag(s) Uᵀ`` (module docstring).

    ``window = (offset, n_parent)``: the n samples are rows ``offset …`` of a longer record
    (:attr:`fricjax.problem.Problem.window`). The rows of K near a cut end are then the
    stationary kernel reaching into the x-samples beyond the cut, not the end rows measured
    at a record end; ``None`` = the n samples are the whole record."""
    trim = settings.trim
    offset, n_parent = window or (0, n)
    reach = (g.shape[0] - 1) // 2
    rows_p, *_ = _edge_probe(settings, wh.dt, n_parent)  # cached: shared with the whole record
    end_depth = int(np.sum(rows_p < n_parent // 2)) if n_parent > 1 else 1
    # Rows whose K row differs from the circulant one: within the kernel's reach of either
    # window end (the wrap), and the parent record's measured end rows.
    depth = max(reach, end_depth)
    rows = np.unique(np.concatenate([np.arange(min(n, depth)), np.arange(max(0, n - depth), n)]))
    L_v, L_a = noise_operators(settings, wh.dt, n_parent)
    K_R = (m * L_a[rows + offset] + c * L_v[rows + offset]).toarray()

    # Circulant rows: response at window row i to window column j' is gw[(i − j') mod n].
    gw = _wrap(g, n)
    circ = gw[(rows[:, None] - np.arange(n)[None, :]) % n]
    delta = K_R
    first = trim + offset
    delta[:, first : first + n] -= circ
    # Only the x-samples some edge row reaches matter for the covariance.
    used = np.flatnonzero(np.any(delta != 0.0, axis=0))
    delta = delta[:, used] if used.size else delta[:, :1] * 0.0
    window_cols = (used >= first) & (used < first + n)

    # G_R: base whitener applied to unit vectors at the rows R.
    unit = np.zeros((n, rows.size))
    unit[rows, np.arange(rows.size)] = 1.0
    G_R = wh.base(unit)
    # P = A·Δ_Rᵀ, A = the base whitener times the circulant part: gain·H = 1/√(n/2).
    delta_win = np.zeros((rows.size, n))
    delta_win[:, used[window_cols] - first] = delta[:, window_cols]
    spec = np.fft.rfft(delta_win.T, axis=0)[wh.keep] / _norm(wh)[:, None]
    P = np.concatenate([spec.real, spec.imag[wh.im_keep]], axis=0)
    DD = delta @ delta.T

    M = wh.M
    if 2 * rows.size < M:
        Q, _ = np.linalg.qr(np.concatenate([P, G_R], axis=1))
        qp, qg = Q.T @ P, Q.T @ G_R
        Z = qp @ qg.T + qg @ qp.T + qg @ DD @ qg.T
    else:
        Q = np.eye(M)
        Z = P @ G_R.T + G_R @ P.T + G_R @ DD @ G_R.T
    lam, V = np.linalg.eigh(np.eye(Z.shape[0]) + 0.5 * (Z + Z.T))
    if lam[0] <= 1e-12 * lam[-1]:
        raise FricjaxError(
            f"{where('whitener', 'noise covariance')}: singular in the kept band "
            f"(eigenvalue ratio {lam[0] / lam[-1]:.2g}); raise rel_floor"
        )
    s = lam**-0.5 - 1.0
    active = np.abs(s) > 1e-15
    return Q @ V[:, active], s[active]


def dc_scale(wh: Whitener, settings: PreprocessSettings) -> float:
    """Noise of the residual's mean per unit of displacement noise [N/m]: ``‖Kᵀ·1‖/n`` with
    ``K = m·L_a + c·L_v`` the exact noise operator of the record (:func:`noise_operators`),
    so ``std(mean r_noise) = σ_x·dc_scale``; 0 where the whitener keeps the DC bin itself
    (a spectral whitener) and the mean needs no separate weight.

    Why. ``H(0) = 0``: the derivatives of x carry almost no noise at DC, so the whitener
    drops that bin, and with it every constraint on the residual's mean: an offset, and any
    combination of parameters that moves only the mean, is then free in the whitened metric
    (the 0.272 s paper twin's GLS base left a mean residual of 225 N, EMS 62 000 N², where
    identify reaches 4 504). The mean is measured with the tiny noise this gives it."""
    if wh.spectral or (wh.keep.size and wh.keep[0] == 0):
        return 0.0
    l_v, l_a = noise_operators(settings, wh.dt, wh.n)
    k_t_one = wh.mass * (l_a.T @ np.ones(wh.n)) + wh.damping * (l_v.T @ np.ones(wh.n))
    return float(np.linalg.norm(k_t_one)) / wh.n


def _norm(wh: Whitener) -> np.ndarray:
    edge = np.zeros(wh.keep.size, dtype=bool)
    edge[list(wh.drop_imag)] = True
    return np.where(edge, math.sqrt(wh.n), math.sqrt(wh.n / 2.0))


# -- helpers for callers --------------------------------------------------------------------


def friction_slope(
    problem: Problem, theta: Float[np.ndarray, " d"], model: Any = None, spec: Any = None
) -> Float[np.ndarray, " n"]:
    """``∂F_f/∂v`` [N·s/m] at every sample of ``model`` (default ``problem.model``, with
    ``spec``) at ``theta`` (jax.jvp of the friction in v; sgn(v) contributes 0 off v = 0)."""
    model = problem.model if model is None else model
    spec = problem.spec if spec is None else spec
    p = spec.unflatten(jnp.asarray(theta, dtype=jnp.float64))
    sig = problem.signals

    def friction_of_v(v: Array) -> Array:
        return model.friction(p, sig._replace(v=v))

    _, slope = jax.jvp(friction_of_v, (sig.v,), (jnp.ones_like(sig.v),))
    return np.asarray(slope)


def linear_damping(problem: Problem, theta: Float[np.ndarray, " d"]) -> float:
    """Linearised damping ``c = mean over samples of ∂F_f/∂v`` [N·s/m] of ``problem``'s
    model at ``theta`` (:func:`friction_slope`)."""
    return float(np.mean(friction_slope(problem, theta)))


def noise_spectrum(
    r: Float[np.ndarray, " n"], dt: float, *, min_bins: int = 8, n_bands: int = 24
) -> Float[np.ndarray, " k"]:
    """Smoothed noise power ``Ŝ_k`` [N²] of a residual r [n] on its rfft grid (k = 0 … n//2).

    The periodogram ``|R_k|²/(n/2)`` is cut into log-spaced frequency bands of at least
    ``min_bins`` bins; in each the median over ln 2 (the median of an exponential
    variable, the distribution of one complex bin's power) estimates S at the band's
    geometric centre, robust to the few bins a drive harmonic or a narrow structure
    occupies; ``log Ŝ`` is interpolated linearly in ``log f`` between centres and held
    flat beyond them (DC takes the first band's value). Broadband model error left in r
    raises Ŝ where it lives: the tests built on it become less sensitive there, never
    over-confident.
    """
    r = np.asarray(r, dtype=np.float64)
    n = r.shape[0]
    power = np.abs(np.fft.rfft(r)) ** 2 / (n / 2.0)
    f = np.fft.rfftfreq(n, dt)
    k = np.arange(1, f.shape[0])
    edges = np.unique(np.geomspace(1, f.shape[0], n_bands + 1).astype(int))
    centres, levels = [], []
    lo = 1
    for hi in edges[1:]:
        if hi - lo < min_bins and hi < f.shape[0]:
            continue
        sel = k[(k >= lo) & (k < hi)]
        if sel.size:
            centres.append(math.sqrt(f[sel[0]] * f[sel[-1]]))
            levels.append(max(float(np.median(power[sel]) / math.log(2.0)), 1e-300))
        lo = hi
    if not levels:
        return np.full(f.shape, max(float(np.mean(power)), 1e-300))
    log_s = np.interp(
        np.log(np.maximum(f, f[1] if f.shape[0] > 1 else 1.0)), np.log(centres), np.log(levels)
    )
    return np.exp(log_s)
