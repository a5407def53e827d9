"""The seed model's equation-error cost written out by hand, for numpy and for JAX at any
float dtype: the baseline that peer optimisers (scipy, pycma) and the throughput benchmark
evaluate, checked against :attr:`fricjax.problem.Problem.cost_fn`.

Per sample k (seed eq. 4, 1, 5, 11)::

    F_p = F0 + Σ_{i=1..N} A_i·sin(iωt) + B_i·cos(iωt),   A_i = Fp_i cos φ_i, B_i = Fp_i sin φ_i
    F_f = [Fc + (Fs − Fc)·exp(−(|v|/vs)^δ)]·sgn v + Fv·v
    r_k = m·a − (F_p − F_f)                                                       [N]
    E(θ) = Σ_k r_k²                                                               [N²]

with sin/cos(iωt) by the Chebyshev recurrence ``s_{i+1} = 2cos(ωt)·s_i − s_{i−1}`` (one sine
and one cosine per sample, as :class:`fricjax.model.drive.HarmonicDrive` does without a time
grid; fricjax's own cost gets them by angle addition on the recording's uniform grid,
:func:`fricjax.model.drive.phasor`, so this transcription is the per-sample baseline).
``θ`` is the problem's free vector (``[d]`` or a batch ``[P, d]``); fixed parameters (δ,
mass) take their spec values.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import ModuleType
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from fricjax.errors import FricjaxError, where
from fricjax.model.drive import HarmonicDrive
from fricjax.problem import Problem

_FRICTION = ("Fc", "Fs", "vs", "delta", "Fv")


@dataclass(frozen=True, eq=False)
class SeedCost:
    """The seed cost over one preprocessed recording (module docstring).

    Attributes:
        t, v, a: float64 [n]: time [s], velocity [m/s], acceleration [m/s²].
        harmonics: N of eq. 4.
        index: parameter name → position in θ (free parameters).
        fixed: parameter name → value (fixed parameters).
    """

    t: np.ndarray
    v: np.ndarray
    a: np.ndarray
    harmonics: int
    index: dict[str, int]
    fixed: dict[str, float]

    @classmethod
    def from_problem(cls, problem: Problem) -> SeedCost:
        """Bind to a problem whose model is exactly ``harmonic_drive`` + ``stribeck_friction``."""
        names = tuple(term.name for term in problem.model.terms)
        if names != ("harmonic_drive", "stribeck_friction"):
            raise FricjaxError(
                f"{where(problem.spec.source or 'config', '[model].terms')}: the benchmark "
                f"cost needs harmonic_drive + stribeck_friction, got {', '.join(names)}"
            )
        drive = problem.model.terms[0]
        assert isinstance(drive, HarmonicDrive)  # the names were checked above
        harmonics = int(drive.harmonics)
        spec = problem.spec
        index = {name: i for i, name in enumerate(spec.free_names)}
        fixed = {p.name: float(p.init) for p in spec.params if not p.free}
        return cls(
            t=np.asarray(problem.t, dtype=np.float64),
            v=np.asarray(problem.v, dtype=np.float64),
            a=np.asarray(problem.a, dtype=np.float64),
            harmonics=harmonics,
            index=index,
            fixed=fixed,
        )

    @property
    def n(self) -> int:
        return int(self.t.shape[0])

    @property
    def d(self) -> int:
        return len(self.index)

    def numpy(self, theta: Float[np.ndarray, "*P d"]) -> Float[np.ndarray, "*P"]:
        """E(θ) [N²] in numpy float64, vectorised over any leading batch axes of θ."""
        theta = np.asarray(theta, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            return _cost(np, self, theta, (self.t, self.v, self.a))

    def jax_fn(self, dtype: Any = jnp.float64) -> Any:
        """``θ [d] -> E(θ) []`` in JAX with the data and θ cast to ``dtype`` (jit/vmap-able).

        With ``float32`` every operation runs in float32 (the data are cast once here, θ
        on entry), although ``jax_enable_x64`` stays on.
        """
        dt = jnp.dtype(dtype)
        data = tuple(jnp.asarray(x, dtype=dt) for x in (self.t, self.v, self.a))

        def cost(theta: Float[Array, " d"]) -> Float[Array, ""]:
            return _cost(jnp, self, jnp.asarray(theta).astype(dt), data)

        return cost


def _cost(xp: ModuleType, sc: SeedCost, theta: Any, data: tuple[Any, Any, Any]) -> Any:
    """Eq. 4/1/5/11 with array module ``xp``; θ [..., d] → [...] (dtype of θ and data)."""
    t, v, a = data
    dtype = theta.dtype

    def param(name: str) -> Any:
        # [..., 1], broadcasting against the samples [n]
        if name in sc.index:
            i = sc.index[name]
            return theta[..., i : i + 1]
        return xp.full((*theta.shape[:-1], 1), sc.fixed[name], dtype=dtype)

    wt = param("omega") * t
    c1, s1 = xp.cos(wt), xp.sin(wt)
    two_c = 2.0 * c1
    sin_prev, cos_prev = xp.zeros_like(s1), xp.ones_like(c1)
    sin_i, cos_i = s1, c1
    drive = param("F0") + xp.zeros_like(wt)
    for i in range(1, sc.harmonics + 1):
        amp, phase = param(f"Fp_{i}"), param(f"phi_{i}")
        drive = drive + (amp * xp.cos(phase)) * sin_i + (amp * xp.sin(phase)) * cos_i
        sin_prev, sin_i = sin_i, two_c * sin_i - sin_prev
        cos_prev, cos_i = cos_i, two_c * cos_i - cos_prev
    fc, fs, vs, delta, fv = (param(n) for n in _FRICTION)
    r = xp.abs(v) / vs
    safe = xp.where(r > 0, r, 1.0)
    power = xp.where(r > 0, xp.exp(delta * xp.log(safe)), 0.0)
    friction = (fc + (fs - fc) * xp.exp(-power)) * xp.sign(v) + fv * v
    resid = param("mass") * a - (drive - friction)
    return xp.sum(resid * resid, axis=-1)


def batch_fn(sc: SeedCost, dtype: Any = jnp.float64) -> Any:
    """Jitted ``θ [P, d] -> E [P]`` (vmap of :meth:`SeedCost.jax_fn`)."""
    return jax.jit(jax.vmap(sc.jax_fn(dtype)))
