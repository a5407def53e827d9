"""Drive terms ``F_p`` (force applied to the body by the feeding system or actuator)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from fricjax.model.term import Basis, Groups, Signals, Term, grid_layout
from fricjax.params import POSITIVE, Named, Param


def phasor(
    omega: Float[Array, ""], s: Signals, dtype: Any = None
) -> tuple[Float[Array, "..."], Float[Array, "..."]]:
    """``(cos ωt, sin ωt)`` [1], each of the shape of ``s.t``; ``omega`` [rad/s] (the phasor
    ``e^{iωt}`` of seed eq. 4's fundamental).

    Plain path: one cosine and one sine of ``θ = ω·t`` per sample. Grid path, when
    ``s.grid`` (:class:`~fricjax.model.term.GridSignals`) is a
    :class:`~fricjax.model.term.TimeGrid` that fits ``t`` (``t [n]`` in
    sample order or ``t [J, R]`` in the grid layout, :func:`~fricjax.model.term.grid_layout`)
    and ``omega`` is a scalar: by angle addition over ``t_k = o_j + i_r``, ``k = j·R + r``,

        cos ωt_k = cos ωo_j·cos ωi_r − sin ωo_j·sin ωi_r,
        sin ωt_k = sin ωo_j·cos ωi_r + cos ωo_j·sin ωi_r,

    i.e. ``J + R`` cosine/sine pairs (15 + 16 instead of 232 on the paper twin) and one
    complex product (4 multiplications, 2 additions) per sample. Anything else (no grid,
    the simulator's scalar ``t``, a batch of ω) takes the plain path, which is always right.

    Error against the exact ``cos/sin(ω·t_k)`` (u = 2⁻⁵³, XLA's sin/cos within ~1 ulp):
    plain ≤ ``u·(|ωt_k| + 2)`` (rounding of the argument, then of the sine); grid ≤
    ``u·(|ωt_k| + 8) + |ω|·δ_k`` (rounding of ``ω·o_j`` and ``ω·i_r``, of the four factors
    and the complex product), ``δ_k = |o_j + i_r − t_k| ≤ 8u·max|t|`` being the grid's own
    tolerance (:func:`~fricjax.model.term.time_grid`). Both are ~u·|ωt| for long records;
    measured against a 64-bit-mantissa reference: 1.4e-14 (plain) and 2.7e-14 (grid) at
    ω = 988 rad/s over the twin's 0.25 s, 1.8e-12 and 4.9e-12 over 25 s. The two paths
    differ by ≤ 1.9e-15 over the paper config's ω box (≤ 3.4e-14 up to ω = 1e3 rad/s).

    ``dtype``: cast ``t`` and the grid first (None: as given).
    """
    t = jnp.asarray(s.t, dtype=dtype)
    grid = getattr(s, "grid", None)
    layout = grid_layout(grid, t) if jnp.ndim(omega) == 0 else None
    if layout is None:
        theta = omega * t
        return jnp.cos(theta), jnp.sin(theta)
    j, r = grid.outer.shape[-1], grid.inner.shape[-1]
    angle = omega * jnp.concatenate([grid.outer, grid.inner]).astype(t.dtype)  # [J + R]
    # XLA's CPU fusion counts sin/cos as cheap and fuses them into their consumers, where
    # a broadcast recomputes them for every sample (measured 2.5x slower than the plain
    # path). A product with an identity matrix is exact (one term 1·x, the others 0·x,
    # x finite) and is a GEMM, which XLA never fuses: each barrier below makes XLA write
    # its operand once. The first keeps the J + R sines.
    cs = jnp.stack([jnp.cos(angle), jnp.sin(angle)], axis=-1) @ np.eye(2, dtype=t.dtype)
    co, so = cs[:j, 0, None], cs[:j, 1, None]
    ci, si = cs[None, j:, 0], cs[None, j:, 1]
    cos_t, sin_t = co * ci - so * si, so * ci + co * si  # [J, R]
    if layout == "grid":
        return cos_t, sin_t
    # t [n]: the second barrier keeps the [2, J, R] phasors, which the per-sample loop then
    # reads contiguously (R ≤ 16 multiply-adds per sample); fused, they would be rebuilt
    # through a div/mod index per sample.
    pair = jnp.stack([cos_t, sin_t]) @ np.eye(r, dtype=t.dtype)
    flat = pair.reshape(2, j * r)[:, : t.shape[0]]
    return flat[0], flat[1]


@dataclass(frozen=True)
class HarmonicDrive(Term):
    """``F_p(t) = F0 + Σ_{i=1..N} Fp_i·sin(i·ω·t + φ_i)`` [N] (seed eq. 4).

    Parameters: F0 [N] mean push, omega [rad/s] fundamental, Fp_i [N] amplitudes,
    phi_i [rad] phases, i = 1..N (N = ``harmonics``, 10 in the seed).
    """

    harmonics: int = 10
    name: ClassVar[str] = "harmonic_drive"
    role: ClassVar = "drive"

    def __post_init__(self) -> None:
        # an option of the config's [model.harmonic_drive] table: a float or a string here
        # would only fail later, deep in building the parameter names
        h = self.harmonics
        if not isinstance(h, int | np.integer) or isinstance(h, bool) or h < 1:
            raise ValueError(f"harmonics: must be an integer >= 1, got {h!r}")

    def parameters(self) -> tuple[Param, ...]:
        amps = tuple(
            Param(f"Fp_{i}", "N", 0.0, 1e4, 0.0, null=0.0) for i in range(1, self.harmonics + 1)
        )
        phases = tuple(
            Param(f"phi_{i}", "rad", -math.pi, math.pi, 0.0) for i in range(1, self.harmonics + 1)
        )
        return (
            Param("F0", "N", -1e4, 1e4, 0.0, null=0.0),
            Param("omega", "rad/s", 1.0, 1e3, 2 * math.pi * 5, domain=POSITIVE),
            *amps,
            *phases,
        )

    def force(self, p: Named, s: Signals) -> Float[Array, "..."]:
        """``F_p(t) = F0 + Σ_i A_i·sin(iωt) + B_i·cos(iωt)`` [N] (seed eq. 4 with
        ``A_i = Fp_i cos φ_i``, ``B_i = Fp_i sin φ_i``), shape of ``s.t``.

        ``sin/cos(iωt)`` by the Chebyshev recurrence ``s_{i+1} = 2cos(ωt)·s_i − s_{i−1}``
        from one ``(cos ωt, sin ωt)`` per sample, :func:`phasor`: on a uniform time grid
        (``s.grid`` of :class:`~fricjax.model.term.GridSignals`) by angle addition from
        ``J + R`` sines and cosines, 31 instead of 232 on the paper twin. XLA's CPU sine and
        cosine dominate the cost: ten of each per sample were the seed's formula, two per
        sample the recurrence, none per sample the grid (the paper twin's cost 1.4-1.7x
        faster than with two on batches of 64-4096 θ, measured).
        """
        c1, s1 = phasor(p["omega"], s)
        two_c = 2.0 * c1
        sin_prev, cos_prev = jnp.zeros_like(s1), jnp.ones_like(c1)
        sin_i, cos_i = s1, c1
        total = p["F0"] + jnp.zeros_like(c1)
        for k in range(1, self.harmonics + 1):
            amp, phase = p[f"Fp_{k}"], p[f"phi_{k}"]
            total = total + (amp * jnp.cos(phase)) * sin_i + (amp * jnp.sin(phase)) * cos_i
            sin_prev, sin_i = sin_i, two_c * sin_i - sin_prev
            cos_prev, cos_i = cos_i, two_c * cos_i - cos_prev
        return total

    def linear_groups(self) -> Groups:
        return (("F0",), *((f"Fp_{i}", f"phi_{i}") for i in range(1, self.harmonics + 1)))

    def basis(self, p: Named, s: Signals) -> Basis:
        """``F_p = F0·1 + Σ_i A_i·sin(iωt) + B_i·cos(iωt)`` (seed eq. 4 rewritten).

        Columns ``[1, sin ωt, cos ωt, …, sin Nωt, cos Nωt]`` [1], shape [..., 1 + 2N],
        depending on ω only (same :func:`phasor` and Chebyshev recurrence as :meth:`force`);
        coefficients ``[F0, A_1, B_1, …]`` with ``A_i = Fp_i cos φ_i``, ``B_i = Fp_i sin φ_i``
        (:meth:`to_linear`; inverse ``Fp_i = √(A_i² + B_i²)``, ``φ_i = atan2(B_i, A_i)``).
        """
        c1, s1 = phasor(p["omega"], s, dtype=jnp.float64)
        two_c = 2.0 * c1

        # The recurrence as a scan: unrolled, XLA re-derives every column from the first
        # inside each consumer's fusion (measured 2x slower and slower to compile).
        def harmonic(carry: tuple[Array, ...], _: None) -> tuple[tuple[Array, ...], Array]:
            sin_prev, sin_i, cos_prev, cos_i = carry
            nxt = (sin_i, two_c * sin_i - sin_prev, cos_i, two_c * cos_i - cos_prev)
            return nxt, jnp.stack([sin_i, cos_i], axis=-1)

        start = (jnp.zeros_like(s1), s1, jnp.ones_like(c1), c1)
        _, pairs = jax.lax.scan(harmonic, start, None, length=self.harmonics)  # [N, ..., 2]
        pairs = jnp.moveaxis(pairs, 0, -2).reshape(*c1.shape, 2 * self.harmonics)
        return Basis(
            jnp.concatenate([jnp.ones_like(c1)[..., None], pairs], axis=-1),
            self.linear_groups(),
        )

    def linear_coefficients(self, values: Float[Array, " k"], p: Named) -> Float[Array, " k"]:
        """``[F0, Fp_1, φ_1, …] -> [F0, A_1, B_1, …]`` [N], ``A_i = Fp_i cos φ_i``,
        ``B_i = Fp_i sin φ_i`` (one vector cos/sin over the N phases)."""
        pairs = values[1:].reshape(self.harmonics, 2)
        amp, phase = pairs[:, 0], pairs[:, 1]
        ab = jnp.stack([amp * jnp.cos(phase), amp * jnp.sin(phase)], axis=-1)
        return jnp.concatenate([values[:1], ab.reshape(-1)])

    def linear_values(self, coef: Float[Array, " k"], p: Named) -> Float[Array, " k"]:
        """``[F0, A_1, B_1, …] -> [F0, Fp_1, φ_1, …]``: ``Fp_i = √(A_i² + B_i²)`` [N],
        ``φ_i = atan2(B_i, A_i)`` ∈ (−π, π] [rad]."""
        pairs = coef[1:].reshape(self.harmonics, 2)
        a, b = pairs[:, 0], pairs[:, 1]
        polar = jnp.stack([jnp.hypot(a, b), jnp.arctan2(b, a)], axis=-1)
        return jnp.concatenate([coef[:1], polar.reshape(-1)])


#: Recorded signals a :class:`MeasuredInput` may read: the drive input ``/u`` (any unit,
#: ``u_unit``) or the measured force on the body ``/F`` [N].
INPUT_SIGNALS = ("u", "F")


@dataclass(frozen=True)
class MeasuredInput(Term):
    """``F_p(t) = g·u(t) − offset`` [N], for rigs whose drive signal ``u`` is recorded.

    Parameters: gain [N per unit of u] (e.g. gτ = 35.15 N/V on EMPS), offset [N] — a
    constant force opposing the drive, with the sign convention of the EMPS inverse
    dynamic model ``M·q̈ + Fv·q̇ + Fc·sgn(q̇) + offset = gτ·vir``.

    Option ``signal``: ``"u"`` (default) reads the drive input ``/u``; ``"F"`` reads the
    measured force on the body ``/F`` [N] (a load cell), with ``gain`` in N/N (fixed at 1
    unless the sensor's calibration is in doubt) and ``offset`` the sensor's zero error.
    Either way the signal reaches the terms as ``s.u``, filtered like ``m·a``
    (:func:`fricjax.data.preprocess.derivatives`).
    """

    signal: str = "u"
    name: ClassVar[str] = "measured_input"
    role: ClassVar = "drive"

    def __post_init__(self) -> None:
        if self.signal not in INPUT_SIGNALS:
            # TypeError: the config reports it as a bad option of the term
            known = ", ".join(INPUT_SIGNALS)
            raise TypeError(f"signal must be one of {known}, got {self.signal!r}")

    def parameters(self) -> tuple[Param, ...]:
        return (
            Param("gain", "N/u", 1.0, 1.0, 1.0, free=False),
            Param("offset", "N", -1e4, 1e4, 0.0, null=0.0),
        )

    def force(self, p: Named, s: Signals) -> Float[Array, "..."]:
        return p["gain"] * s.u - p["offset"]

    def linear_groups(self) -> Groups:
        return (("gain",), ("offset",))

    def basis(self, p: Named, s: Signals) -> Basis:
        """Columns ``[u, −1]`` [u_unit, 1], shape [..., 2]; coefficients gain, offset."""
        u = jnp.asarray(s.u, dtype=jnp.float64)
        return Basis(jnp.stack([u, -jnp.ones_like(u)], axis=-1), self.linear_groups())
