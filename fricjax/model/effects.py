"""The force terms of the diagnosis' catalogue: physics a base friction model may leave out.

Each is a :class:`~fricjax.model.term.Term` like the base library's, so a config can name it
(``terms = ["coulomb_viscous", "quadratic_drag"]`` with ``drag_Cd`` in ``[params]``) and every
simulator and fit runs it. Forces (``v``, ``x``, ``t`` from the
:class:`~fricjax.model.term.Signals`, ``sgn(0) = 0``; "friction" terms give the resisting force
``F_f``, subtracted, "drive" terms a force on the body; seed eq. 3/5: ``m·a = F_p − F_f``):

=====================  ========  =====================================================
effect                 role      force [N]
=====================  ========  =====================================================
stribeck               friction  ``A·exp(−(|v|/vst)²)·sgn(v)``
stribeck_shape         friction  ``(Fs−Fc)·[exp(−(|v|/vs)^(δ+dδ)) − exp(−(|v|/vs)^δ)]·sgn(v)``
asymmetric_friction    friction  ``dFc·|sgn(v)| + dFv·|v|``
quadratic_drag         friction  ``Cd·v·|v|``
presliding_hysteresis  friction  ``A·(z − sgn(v))``, ``z`` the Dahl bristle state (stateful)
position_bump          friction  ``A·exp(−((x − x0)/w)²/2)·sgn(v)``
position_periodic      drive     ``A·sin(2πx/λ) + B·cos(2πx/λ)``
impact                 drive     ``A·exp(−((t − t0)/w)²/2)``
extra_harmonic         drive     ``A·sin(2πf·t) + B·cos(2πf·t)``
friction_drift         friction  ``β·(t − t_mid)/T·sgn(v)``
mass_error             drive     ``−ε·F*_base`` (the base model's force scaled)
=====================  ========  =====================================================

Which of them the diagnosis tries, on which grids and bounds, is
:mod:`fricjax.diagnose.catalogue`'s business; here are only the equations.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from fricjax.errors import FricjaxError, where
from fricjax.model.system import Model
from fricjax.model.term import Signals, Term, sgn
from fricjax.params import Named, Param

__all__ = [
    "EFFECTS",
    "MASS_FRACTION",
    "AsymmetricFriction",
    "ExtraHarmonic",
    "FrictionDrift",
    "GaussianStribeck",
    "Impact",
    "MassError",
    "PositionBump",
    "PositionPeriodic",
    "PreslidingHysteresis",
    "QuadraticDrag",
    "StribeckShape",
    "bristle_state",
    "is_stateful",
]

# mass_error frees the mass within ± this fraction of the given value.
MASS_FRACTION = 0.3


def _safe_power(r: Float[Array, "..."], k: Float[Array, ""]) -> Float[Array, "..."]:
    """``r^k`` for ``r ≥ 0`` with the ``r = 0`` branch kept out of the log, so derivatives in
    ``k`` stay finite (and zero) at rest."""
    safe = jnp.where(r > 0, r, 1.0)
    return jnp.where(r > 0, jnp.exp(k * jnp.log(safe)), 0.0)


def is_stateful(term: Term) -> bool:
    """Whether ``term`` needs the whole recorded signal (a scan) rather than one sample.

    Stateful terms work in the equation error over a recording ([n] signals) but not in the
    pointwise simulator; base-library terms lack the flag and are pointwise.
    """
    return bool(getattr(term, "stateful", False))


@dataclass(frozen=True)
class GaussianStribeck(Term):
    """``F_f = A·exp(−(|v|/vst)²)·sgn(v)`` [N]: a Stribeck drop of Gaussian shape (δ = 2),
    the common alternative to the exponential of seed eq. 2.

    Parameters: stribeck_A [N] friction excess at rest over sliding (linear, null 0),
    stribeck_vst [m/s] Stribeck velocity (nonlinear).
    """

    name: ClassVar[str] = "stribeck"
    role: ClassVar = "friction"
    stateful: ClassVar[bool] = False

    def parameters(self) -> tuple[Param, ...]:
        return (
            Param("stribeck_A", "N", -1e4, 1e4, 0.0, null=0.0),
            Param("stribeck_vst", "m/s", 1e-6, 10.0, 0.05),
        )

    def force(self, p: Named, s: Signals) -> Float[Array, "..."]:
        r = s.v / p["stribeck_vst"]
        return p["stribeck_A"] * jnp.exp(-(r * r)) * sgn(s.v)

    def static(self, p: Named, s: Signals, direction: Float[Array, "..."]) -> Float[Array, "..."]:
        return p["stribeck_A"] * direction + jnp.zeros_like(s.t)


@dataclass(frozen=True)
class StribeckShape(Term):
    """``F_f = (Fs − Fc)·[exp(−(|v|/vs)^(δ+dδ)) − exp(−(|v|/vs)^δ)]·sgn(v)`` [N].

    Correction of the base Stribeck exponent δ (seed eq. 1) to ``δ + dδ``: base + this term
    is exactly the Stribeck law with exponent ``δ + dδ``. It reads the base's ``Fs, Fc, vs,
    delta`` from ``p``. Parameter: shape_ddelta [-] (null 0). It is not linear: the score
    uses the local column ``∂F/∂dδ|₀ = −(Fs−Fc)·ρ^δ·ln ρ·exp(−ρ^δ)·sgn(v)``, ``ρ = |v|/vs``.
    """

    name: ClassVar[str] = "stribeck_shape"
    role: ClassVar = "friction"
    stateful: ClassVar[bool] = False

    def parameters(self) -> tuple[Param, ...]:
        return (Param("shape_ddelta", "1", -0.8, 2.0, 0.0, null=0.0),)

    def force(self, p: Named, s: Signals) -> Float[Array, "..."]:
        rho = jnp.abs(s.v) / p["vs"]
        new = jnp.exp(-_safe_power(rho, p["delta"] + p["shape_ddelta"]))
        old = jnp.exp(-_safe_power(rho, p["delta"]))
        return (p["Fs"] - p["Fc"]) * (new - old) * sgn(s.v)

    def static(self, p: Named, s: Signals, direction: Float[Array, "..."]) -> Float[Array, "..."]:
        return jnp.zeros_like(s.t * direction)  # both curves start at Fs


@dataclass(frozen=True)
class AsymmetricFriction(Term):
    """``F_f = dFc·|sgn(v)| + dFv·|v|`` [N]: friction levels that depend on the direction.

    Derivation: with Coulomb and viscous levels ``Fc± = Fc ± dFc``, ``Fv± = Fv ± dFv`` for
    ``v ≷ 0``, the friction is ``F_f = Fc±·sgn(v) + Fv±·v``. For ``v > 0``:
    ``(Fc + dFc) + (Fv + dFv)·v = Fc·sgn v + Fv·v + dFc + dFv·|v|``; for ``v < 0``:
    ``−(Fc − dFc) + (Fv − dFv)·v = Fc·sgn v + Fv·v + dFc + dFv·|v|``. The excess over the
    symmetric law is therefore the even function ``dFc·|sgn v| + dFv·|v|``.
    Parameters: asym_dFc [N], asym_dFv [N·s/m] (both linear, null 0).
    """

    name: ClassVar[str] = "asymmetric_friction"
    role: ClassVar = "friction"
    stateful: ClassVar[bool] = False

    def parameters(self) -> tuple[Param, ...]:
        return (
            Param("asym_dFc", "N", -1e4, 1e4, 0.0, null=0.0),
            Param("asym_dFv", "N*s/m", -1e5, 1e5, 0.0, null=0.0),
        )

    def force(self, p: Named, s: Signals) -> Float[Array, "..."]:
        return p["asym_dFc"] * jnp.abs(sgn(s.v)) + p["asym_dFv"] * jnp.abs(s.v)

    def static(self, p: Named, s: Signals, direction: Float[Array, "..."]) -> Float[Array, "..."]:
        return p["asym_dFc"] * jnp.abs(direction) + jnp.zeros_like(s.t)


@dataclass(frozen=True)
class QuadraticDrag(Term):
    """``F_f = Cd·v·|v|`` [N]: fluid or air drag. Parameter: drag_Cd [N·s²/m²] (linear)."""

    name: ClassVar[str] = "quadratic_drag"
    role: ClassVar = "friction"
    stateful: ClassVar[bool] = False

    def parameters(self) -> tuple[Param, ...]:
        return (Param("drag_Cd", "N*s^2/m^2", -1e6, 1e6, 0.0, null=0.0),)

    def force(self, p: Named, s: Signals) -> Float[Array, "..."]:
        return p["drag_Cd"] * s.v * jnp.abs(s.v)


def bristle_state(
    x: Float[Array, " n"], v: Float[Array, " n"], eps: Float[Array, ""]
) -> Float[Array, " n"]:
    """Normalised Dahl/LuGre bristle deflection ``z`` ∈ [−1, 1] along a recorded motion.

    ``dz/dx = (sgn(ẋ) − z)/ε`` per unit of travel, integrated exactly between samples:
    ``z_{k+1} = s_k + (z_k − s_k)·exp(−|x_{k+1} − x_k|/ε)``, ``s_k = sgn(v_k)``,
    ``z_0 = sgn(v_0)``. Shapes: x [m], v [m/s] both [n]; ε [m] scalar; returns [n].
    """
    s = sgn(v)
    travel = jnp.abs(jnp.diff(x, append=x[-1:]))  # the last sample has no successor
    decay = jnp.exp(-travel / eps)

    def step(z: Float[Array, ""], inp: tuple[Float[Array, ""], Float[Array, ""]]):
        s_k, d_k = inp
        return s_k + (z - s_k) * d_k, z

    _, z = jax.lax.scan(step, s[0], (s, decay))
    return z


@dataclass(frozen=True)
class PreslidingHysteresis(Term):
    """``F_f = A·(z − sgn(v))`` [N] with ``z`` = :func:`bristle_state` (Dahl/LuGre memory).

    A Dahl friction ``A·z`` lags behind the Coulomb law ``A·sgn(v)`` for a presliding travel
    of a few ε after each reversal; this term is that lag, zero once ``z`` has settled
    (steady sliding). Parameters: presl_A [N] (linear; ≈ the Coulomb level for pure Dahl
    behaviour), presl_eps [m] presliding distance (nonlinear).

    ``stateful = True``: ``z`` is integrated with ``lax.scan`` over the whole record, so the
    term works in the equation error (signals [n]) but not in the pointwise simulator.
    """

    name: ClassVar[str] = "presliding_hysteresis"
    role: ClassVar = "friction"
    stateful: ClassVar[bool] = True

    def parameters(self) -> tuple[Param, ...]:
        return (
            Param("presl_A", "N", -1e4, 1e4, 0.0, null=0.0),
            Param("presl_eps", "m", 1e-8, 1.0, 1e-3),
        )

    def force(self, p: Named, s: Signals) -> Float[Array, "..."]:
        x, v = jnp.asarray(s.x), jnp.asarray(s.v)
        if x.ndim != 1:
            raise FricjaxError(
                f"{where('model', self.name)}: stateful term needs the whole recorded signal; "
                "it cannot be used in the pointwise simulator"
            )
        return p["presl_A"] * (bristle_state(x, v, p["presl_eps"]) - sgn(v))

    def static(self, p: Named, s: Signals, direction: Float[Array, "..."]) -> Float[Array, "..."]:
        raise FricjaxError(
            f"{where('model', self.name)}: stateful term has no pointwise static friction; "
            "it cannot be used in the simulator"
        )


@dataclass(frozen=True)
class PositionBump(Term):
    """``F_f = A·exp(−((x − x0)/w)²/2)·sgn(v)`` [N]: extra resistance over a band of
    positions (an engraving, a burr, a seal). Parameters: bump_A [N] (linear), bump_x0 [m]
    centre, bump_w [m] standard width (nonlinear).
    """

    name: ClassVar[str] = "position_bump"
    role: ClassVar = "friction"
    stateful: ClassVar[bool] = False

    def parameters(self) -> tuple[Param, ...]:
        return (
            Param("bump_A", "N", -1e4, 1e4, 0.0, null=0.0),
            Param("bump_x0", "m", -1e3, 1e3, 0.0),
            Param("bump_w", "m", 1e-9, 1e3, 1e-3),
        )

    def _profile(self, p: Named, x: Float[Array, "..."]) -> Float[Array, "..."]:
        z = (x - p["bump_x0"]) / p["bump_w"]
        return p["bump_A"] * jnp.exp(-0.5 * z * z)

    def force(self, p: Named, s: Signals) -> Float[Array, "..."]:
        return self._profile(p, s.x) * sgn(s.v)

    def static(self, p: Named, s: Signals, direction: Float[Array, "..."]) -> Float[Array, "..."]:
        return self._profile(p, s.x) * direction + jnp.zeros_like(s.t)


@dataclass(frozen=True)
class PositionPeriodic(Term):
    """``F_p = A·sin(2πx/λ) + B·cos(2πx/λ)`` [N]: a force periodic in position (cogging,
    screw pitch, rollers). Parameters: per_A, per_B [N] (linear), per_lambda [m] (nonlinear).
    """

    name: ClassVar[str] = "position_periodic"
    role: ClassVar = "drive"
    stateful: ClassVar[bool] = False

    def parameters(self) -> tuple[Param, ...]:
        return (
            Param("per_A", "N", -1e4, 1e4, 0.0, null=0.0),
            Param("per_B", "N", -1e4, 1e4, 0.0, null=0.0),
            Param("per_lambda", "m", 1e-9, 1e3, 1e-2),
        )

    def force(self, p: Named, s: Signals) -> Float[Array, "..."]:
        phase = (2.0 * math.pi / p["per_lambda"]) * s.x
        return p["per_A"] * jnp.sin(phase) + p["per_B"] * jnp.cos(phase)


@dataclass(frozen=True)
class Impact(Term):
    """``F_p = A·exp(−((t − t0)/w)²/2)`` [N]: a short impulsive force (collision, shock).
    Parameters: impact_A [N] (linear), impact_t0 [s] instant, impact_w [s] standard width
    (nonlinear).
    """

    name: ClassVar[str] = "impact"
    role: ClassVar = "drive"
    stateful: ClassVar[bool] = False

    def parameters(self) -> tuple[Param, ...]:
        return (
            Param("impact_A", "N", -1e5, 1e5, 0.0, null=0.0),
            Param("impact_t0", "s", -1e9, 1e9, 0.0),
            Param("impact_w", "s", 1e-9, 1e6, 1e-3),
        )

    def force(self, p: Named, s: Signals) -> Float[Array, "..."]:
        z = (s.t - p["impact_t0"]) / p["impact_w"]
        return p["impact_A"] * jnp.exp(-0.5 * z * z)


@dataclass(frozen=True)
class ExtraHarmonic(Term):
    """``F_p = A·sin(2πf·t) + B·cos(2πf·t)`` [N]: a vibration at a frequency the drive model
    lacks. Parameters: harm_A, harm_B [N] (linear), harm_f [Hz] (nonlinear).
    """

    name: ClassVar[str] = "extra_harmonic"
    role: ClassVar = "drive"
    stateful: ClassVar[bool] = False

    def parameters(self) -> tuple[Param, ...]:
        return (
            Param("harm_A", "N", -1e4, 1e4, 0.0, null=0.0),
            Param("harm_B", "N", -1e4, 1e4, 0.0, null=0.0),
            Param("harm_f", "Hz", 1e-6, 1e6, 1.0),
        )

    def force(self, p: Named, s: Signals) -> Float[Array, "..."]:
        phase = (2.0 * math.pi * p["harm_f"]) * s.t
        return p["harm_A"] * jnp.sin(phase) + p["harm_B"] * jnp.cos(phase)


@dataclass(frozen=True)
class FrictionDrift(Term):
    """``F_f = β·(t − t_mid)/T·sgn(v)`` [N]: the Coulomb level drifting linearly over the run
    (heating, lubricant, wear), by ``β`` from start to end, zero on average.

    Structure (options): ``t_mid`` [s] the middle of the run, ``duration`` T [s]; the
    catalogue sets them from the recording, a config may give them in
    ``[model.friction_drift]`` (defaults 0 s and 1 s: β is then the drift per second from
    t = 0). Parameter: drift_beta [N] (linear).
    """

    t_mid: float = 0.0
    duration: float = 1.0
    name: ClassVar[str] = "friction_drift"
    role: ClassVar = "friction"
    stateful: ClassVar[bool] = False

    def __post_init__(self) -> None:
        if not (math.isfinite(self.duration) and self.duration > 0):
            raise FricjaxError(
                f"{where('model', 'friction_drift.duration')}: must be a positive number of "
                f"seconds, got {self.duration!r}"
            )

    def parameters(self) -> tuple[Param, ...]:
        return (Param("drift_beta", "N", -1e4, 1e4, 0.0, null=0.0),)

    def _level(self, p: Named, t: Float[Array, "..."]) -> Float[Array, "..."]:
        return p["drift_beta"] * (t - self.t_mid) / self.duration

    def force(self, p: Named, s: Signals) -> Float[Array, "..."]:
        return self._level(p, s.t) * sgn(s.v)

    def static(self, p: Named, s: Signals, direction: Float[Array, "..."]) -> Float[Array, "..."]:
        return self._level(p, s.t) * direction


EFFECTS: tuple[type[Term], ...] = (
    GaussianStribeck,
    StribeckShape,
    AsymmetricFriction,
    QuadraticDrag,
    PreslidingHysteresis,
    PositionBump,
    PositionPeriodic,
    Impact,
    ExtraHarmonic,
    FrictionDrift,
)


@dataclass(frozen=True)
class MassError(Term):
    """``mass_error`` as a force scale: ``F_me = −ε·F*_base(t, x, v, u)`` [N], so that the
    residual becomes ``m·a − (1 − ε)·F*_base`` and the true mass is ``m/(1 − ε)``.

    Why not free the mass: the regressor of m is the *measured* acceleration, whose noise
    (the derivative of x-noise) is the very noise of the residual. Least squares then shrinks
    m to shrink the noise (errors in variables) and a null recording "gains" tens of BIC
    units. Scaling the noise-free model force instead keeps the regressor clean. Parameter:
    ``mass_eps`` [1], null 0. ``base`` is the model the term was added to.
    """

    base: Model = field(default_factory=lambda: Model(()))
    name: ClassVar[str] = "mass_error"
    role: ClassVar = "drive"
    stateful: ClassVar[bool] = False

    def parameters(self) -> tuple[Param, ...]:
        return (Param("mass_eps", "1", -MASS_FRACTION, MASS_FRACTION, 0.0, null=0.0),)

    def force(self, p: Named, s: Signals) -> Float[Array, "..."]:
        return -p["mass_eps"] * self.base.force(p, s)
