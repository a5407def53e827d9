"""A :class:`Problem` bundles what the equation-error cost needs, as arrays.

``residual(theta) = m·a − (F_p − F_f)`` over the preprocessed recording (seed eq. 5/11) and
``cost(theta) = Σ residual²`` are pure, jit- and vmap-able functions of the free-parameter
vector ``theta`` [d]. They are built once per problem and cached, so every search and
refinement stage reuses the same compiled function.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from fricjax.config import Config
from fricjax.data.decimate import antialias_kernel, decimate, decimated_length
from fricjax.data.preprocess import PreprocessSettings, derivatives
from fricjax.data.recording import Recording, require_mass
from fricjax.errors import FricjaxError, where
from fricjax.model.system import MASS, Model, cost
from fricjax.model.term import Signals
from fricjax.params import ParamSpec


class EquationError(eqx.Module):
    """Equation-error residual ``m·a − (F_p − F_f)`` [N] over a recording (seed eq. 5/11)."""

    model: Model = eqx.field(static=True)
    spec: ParamSpec = eqx.field(static=True)
    t: Float[Array, " n"]
    x: Float[Array, " n"]
    v: Float[Array, " n"]
    u: Float[Array, " n"]
    a: Float[Array, " n"]

    kernel: Float[Array, " L"] | None = None
    q: int = eqx.field(static=True, default=1)

    def __call__(self, theta: Float[Array, " d"]) -> Float[Array, " m"]:
        sig = Signals(self.t, self.x, self.v, self.u)
        r = self.model.residual(self.spec.unflatten(theta), sig, self.a)
        # IDIM-LS: anti-alias filter + keep every q-th sample of the residual (= of every
        # regressor column and the force), fricjax.data.decimate
        return r if self.q == 1 else decimate(r, self.kernel, self.q)


class Cost(eqx.Module):
    """Seed eq. (11): ``Σ r²`` [N²] of an :class:`EquationError`."""

    residual: EquationError

    def __call__(self, theta: Float[Array, " d"]) -> Float[Array, ""]:
        return cost(self.residual(theta))


@eqx.filter_jit
def _call(fn: eqx.Module, theta: Float[Array, " d"]) -> Array:
    return fn(theta)


@dataclass(frozen=True, eq=False)
class Problem:
    """Preprocessed signals + model + parameter specification.

    Attributes:
        model: the force model (terms).
        spec: parameters, ``mass`` included (fixed from the recording unless free).
        t, x, v, a, u: float64 arrays [n]: time [s], position [m], velocity [m/s],
            acceleration [m/s²], drive input [u_unit] (zeros when the rig records none).
        name: recording name; checksum: recording sha256; source: recording path.
    """

    model: Model
    spec: ParamSpec
    t: np.ndarray
    x: np.ndarray
    v: np.ndarray
    a: np.ndarray
    u: np.ndarray
    name: str = ""
    checksum: str = ""
    source: str = ""
    preprocess: PreprocessSettings | None = None

    @property
    def n(self) -> int:
        return int(self.t.shape[0])

    @property
    def signals(self) -> Signals:
        return Signals(
            jnp.asarray(self.t), jnp.asarray(self.x), jnp.asarray(self.v), jnp.asarray(self.u)
        )

    def named(self, theta: Float[Array, " d"]) -> dict[str, Any]:
        return self.spec.unflatten(theta)

    @cached_property
    def residual_fn(self) -> EquationError:
        """``theta [d] -> residual [n]`` in newtons.

        An equinox Module holding the data as array leaves: jitted callers (search, refiner)
        reuse one compilation for every problem with the same model, spec and length.
        """
        return EquationError(
            self.model,
            self.spec.structural(),
            *(jnp.asarray(a) for a in (self.t, self.x, self.v, self.u, self.a)),
            kernel=None if self.q == 1 else jnp.asarray(antialias_kernel(self.q)),
            q=self.q,
        )

    @property
    def q(self) -> int:
        """Decimation factor of the residual (``[preprocess].decimate``; 1 = none)."""
        return self.preprocess.decimate if self.preprocess is not None else 1

    @property
    def n_residual(self) -> int:
        """Length of the residual vector (``n``, or ``⌈n/q⌉`` when decimated)."""
        return decimated_length(self.n, self.q)

    @cached_property
    def cost_fn(self) -> Cost:
        """``theta [d] -> Σ r²`` [N²] (seed eq. 11)."""
        return Cost(self.residual_fn)

    def cost(self, theta: Float[Array, " d"]) -> float:
        return float(_call(self.cost_fn, jnp.asarray(theta, dtype=jnp.float64)))

    def residual(self, theta: Float[Array, " d"]) -> np.ndarray:
        """Residual [n] in newtons, as numpy (jitted evaluation)."""
        return np.asarray(_call(self.residual_fn, jnp.asarray(theta, dtype=jnp.float64)))

    def ems(self, theta: Float[Array, " d"]) -> float:
        """Error mean square ``cost/n`` [N²] (seed Table 4)."""
        return float(np.mean(self.residual(theta) ** 2))

    def theta(self, named: dict[str, float]) -> np.ndarray:
        """Named values (e.g. a twin's truth) -> free vector; absent names take init."""
        known = {k: v for k, v in named.items() if k in self.spec}
        return self.spec.flatten(known)


def needs_input(model: Model) -> bool:
    return any(term.name == "measured_input" for term in model.terms)


def build_problem(
    rec: Recording, config: Config, *, preprocess: PreprocessSettings | None = None
) -> Problem:
    """Preprocess ``rec`` (seed section 4.1) and bind it to the config's model."""
    settings = preprocess or PreprocessSettings.from_dict(
        config.table("preprocess"), source=config.source or "config"
    )
    spec: ParamSpec = config.spec
    if not config.mass_in_spec:
        m = require_mass(rec)
        spec = spec.extended([MASS.fixed_at(m)])
    if needs_input(config.model) and rec.u is None:
        raise FricjaxError(
            f"{where(rec.path or rec.name, '/u')}: missing (model term measured_input needs "
            "the recorded drive input)"
        )
    d = derivatives(rec.t, rec.x, settings, u=rec.u, F=rec.F)
    u = d.u if d.u is not None else np.zeros_like(d.t)
    return Problem(
        model=config.model,
        spec=spec,
        t=d.t,
        x=d.x,
        v=d.v,
        a=d.a,
        u=u,
        name=rec.name,
        checksum=rec.sha256(),
        source=rec.path,
        preprocess=settings,
    )
