"""The scale every test of the diagnosis is measured against, taken from the recording.

Why not from the residual. A residual's scale is the noise *plus* whatever the model under
test leaves out, so σ̂ from the residual grows exactly where the model is wrong: every test
loses power, the BIC's penalty shrinks relative to the misfit it should judge, and a band
sized by σ̂ (the samples near rest) widens over the physics it hides. The displacement
noise is measured instead from the recorded x alone (:func:`fricjax.data.noise.
estimate_noise`: the high band of x by differences, or a quantisation lattice). The judge
divides its output-error residual (simulated minus recorded x) by it, so where the model is
right that residual's noise is ``N(0, I)`` and ``σ_x²`` *is* the variance every statistic is
measured in.

Its own uncertainty. σ̂_x comes with a standard error ``se`` (of σ̂, not of σ̂²). For a
scale estimated from ν independent squares, ``σ̂²/σ² ~ χ²_ν/ν``, so ``Var(σ̂²)/σ⁴ = 2/ν``
and, to first order, ``se(σ̂)/σ = 1/√(2ν)``: the estimate carries the effective degrees
of freedom

    ν = ½·(σ̂/se)²                                                         (1)

(Satterthwaite's matching of the first two moments; ``2·(σ̂²/se(σ̂²))²`` is the same
number). A statistic ``S`` with k regressors
divided by σ̂² then follows ``S/k ~ F(k, ν)`` rather than ``χ²_k/k``
(:func:`fricjax.diagnose.judge.f_pvalue`), and a lack-of-fit ratio
``(RSS_w/dof)/σ̂² ~ F(dof, ν)``. A quantised signal's σ = q/√12 is exact (the rounding
error of a known lattice), ν = ∞ (:data:`EXACT_DOF` stands for it).

Noise that is not displacement noise. The model of the noise is displacement noise (white,
or a quantisation lattice), and the report says which. Where a model's drive is a recorded
input, that input's own noise and a controller's feedback enter the simulation as force, which
the displacement record cannot measure: they show as misfit beyond σ_x, which the lack-of-fit
test reports (``unexplained``) rather than a catalogue term.

Near rest. A sample is near rest where noise can flip the sign of the filtered velocity:
``|v| < κ·σ_v``, ``σ_v = g_v·σ_x`` with ``g_v`` the preprocessing's white-noise gain from x
to v (:func:`fricjax.data.preprocess.noise_gains`). :class:`NearRest` holds that speed in
the axis' unit and the real share of samples below it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from jaxtyping import Bool, Float

from fricjax.data.noise import FLIP_KAPPA, NoiseEstimate, estimate_noise
from fricjax.data.preprocess import noise_gains
from fricjax.errors import FricjaxError, where
from fricjax.problem import Problem

__all__ = ["EXACT_DOF", "FLIP_KAPPA", "Evidence", "NearRest", "near_rest_band", "record_noise"]

#: ν standing for "exact" (a quantised signal, σ = q/√12): F(k, 10⁶) equals χ²_k/k to
#: within 1e-3 in every quantile the tests use.
EXACT_DOF = 1_000_000


@dataclass(frozen=True)
class NearRest:
    """The samples where noise can flip the sign of v: ``|v| < speed``.

    Attributes:
        speed: the band's edge ``κ·g_v·σ_x`` [m/s, or rad/s on a rotary axis].
        kappa: κ of the band (σ_v units).
        mask: bool [n], the samples inside it.
    """

    speed: float
    kappa: float
    mask: Bool[np.ndarray, " n"]

    @property
    def share(self) -> float:
        """Share of the record's samples inside the band (0 … 1)."""
        return float(np.mean(self.mask)) if self.mask.size else 0.0


@dataclass(frozen=True)
class Evidence:
    """The recording's own noise, the scale every test of the diagnosis uses.

    Attributes:
        noise: σ̂_x of the recorded displacement with its standard error and noise model
            (:class:`~fricjax.data.noise.NoiseEstimate`, metres).
    """

    noise: NoiseEstimate

    @property
    def sigma_x(self) -> float:
        """σ̂_x [m]."""
        return float(self.noise.sigma)

    @property
    def nu(self) -> int:
        """Effective degrees of freedom of σ̂_x², eq. (1); :data:`EXACT_DOF` when exact."""
        return effective_dof(self.noise)

    def describe(self) -> str:
        """One line: σ̂_x with its error, noise model and ν."""
        nu = "∞" if self.nu >= EXACT_DOF else str(self.nu)
        return f"{self.noise.describe('m')}; ν = {nu} degrees of freedom"


def effective_dof(noise: NoiseEstimate) -> int:
    """ν = ½·(σ/se)² of a noise estimate (module docstring, eq. 1), in [1, EXACT_DOF].

    A quantised estimate is exact; one without a standard error (a record too short for
    two blocks) gets ν = 1, the most cautious reference a scale with an error can have."""
    if noise.model == "quantised":
        return EXACT_DOF
    if not (math.isfinite(noise.se) and noise.se > 0 and noise.sigma > 0):
        return 1
    return int(min(max(0.5 * (noise.sigma / noise.se) ** 2, 1.0), EXACT_DOF))


def record_noise(problem: Problem) -> Evidence:
    """:class:`Evidence` of ``problem``'s recorded displacement (its measured x, trimmed as
    the residual is; :func:`~fricjax.data.noise.estimate_noise`)."""
    x = np.asarray(problem.x, dtype=np.float64)
    src = problem.source or problem.name or None
    if x.shape[0] < 16:
        raise FricjaxError(f"{where(src, '/x')}: {x.shape[0]} samples, need 16 to measure noise")
    noise = estimate_noise(x)
    if not (math.isfinite(noise.sigma) and noise.sigma > 0):
        raise FricjaxError(
            f"{where(src, '/x')}: no displacement noise can be measured (σ̂_x = "
            f"{noise.sigma!r}); a noise-free record cannot be diagnosed against its noise"
        )
    return Evidence(noise)


def near_rest_band(problem: Problem, sigma_x: float, kappa: float = FLIP_KAPPA) -> NearRest:
    """:class:`NearRest` of ``problem`` for displacement noise ``sigma_x`` [m]: ``|v| <
    κ·g_v·σ_x``. Outside it a noise-driven sign flip of v has probability
    ``2·(1 − Φ(κ))`` per sample (6.3e-5 at κ = 4)."""
    settings = problem.preprocess
    if settings is None:
        raise FricjaxError(f"{where(problem.source or None, 'preprocess')}: missing")
    gain_v, _ = noise_gains(settings, 1.0 / problem.dt)
    speed = float(kappa * sigma_x * gain_v)
    v: Float[np.ndarray, " n"] = np.asarray(problem.v)
    return NearRest(speed, float(kappa), np.abs(v) < speed)
