"""Identification by output (simulation) error, with multiple shooting.

Equation error (seed eq. 11, :mod:`fricjax.problem`) compares forces, ``m·a_rec − F*(θ)``
at every sample; ``a_rec`` is the recorded position differentiated twice, so the noise on x
is amplified (σ_a/σ_x = 4.9e4 s⁻² with the default filter) and the filter's bias on the
upper harmonics enters θ. Output error compares the *position* the model produces when it
is simulated (:func:`fricjax.model.simulate.simulate`) with the position recorded: no
derivative of the data is taken, the noise enters once and unamplified.

Multiple shooting
-----------------
The kept samples ``k = 0..n−1`` of the problem (after the config's ``[preprocess].trim``),
uniform step ``dt`` [s], are cut into ``S`` segments of ``L`` intervals: segment ``s``
starts at sample ``k_s = s·L`` and ends at ``k_s + L``, the first sample of segment
``s + 1`` (when ``n − 1`` is not a multiple of ``L`` the last segment is shorter; it is
padded to ``L`` intervals with the time continued and the input held, and the padded
samples are left out of the residual). Segment ``s`` is simulated from its own initial
state ``(ξ_s [m], ν_s [m/s])``, extra unknowns next to the model parameters θ [d]:

    θ_aug = [θ (d) | ξ_0 … ξ_{S−1} (S) | ν_0 … ν_{S−1} (S)]                 shape [d + 2S]

    r_k   = (x_s(k)(t_k; θ, ξ_s(k), ν_s(k)) − x_k) / σ_x            k = 0..n−1       [-]
    c^x_s = w·√L·(x_s(t_{k_{s+1}}) − ξ_{s+1}) / σ_x                  s = 0..S−2       [-]
    c^v_s = w·√L·(v_s(t_{k_{s+1}}) − ν_{s+1})·T / σ_x                s = 0..S−2       [-]

    r_aug = [r (n) | c^x (S−1) | c^v (S−1)]  [n + 2(S−1)],     E_OE(θ_aug) = Σ r_aug²  [-]

with ``x_s(·), v_s(·)`` the simulated position and velocity of segment ``s``, ``s(k)`` the
segment holding sample ``k`` (a boundary sample belongs to the segment it starts; the last
sample to the last segment), ``T = L·dt`` [s] the segment length. ``S = 1`` is plain output
error (single shooting: one simulation from ``(ξ_0, ν_0)``, no defect).

Scaling and weights. ``σ_x`` [m] sets the unit of the residual so that LM's tolerances
and the Gauss–Newton algebra see numbers of order one; it does not move the optimum. By
default it is the white-noise std of x estimated from the third difference,
``std(Δ³x)/√20`` (Δ³ of white noise has variance 20σ²; a smooth motion sampled at 1 kHz
contributes ``jerk·dt³`` ≈ 1e-6 m on the twin, 3e-9 m on EMPS). A position defect is in the
same unit as the misfit of one sample. A velocity defect ``Δv`` shifts the whole next
segment by up to ``Δv·T``, so ``Δv·T`` is its position equivalent: position and velocity
defects are weighted by what they would do to the fit, not by their units. With the factor
``√L`` a defect costs ``w²`` times what the same offset of all ``L`` samples of a segment
would cost, whatever the sampling rate; with ``w`` = 10 (default) the data can pull a
defect open only by ~1 % of the misfit it would repair. When the model is right, the
segments then form one continuous trajectory to a tiny fraction of the noise (measured on
an open-loop record with 10 µm of noise: defects of 1e-9 m, and the 3-segment optimum a
stationary point of single shooting to 1e-3 σ), the limit ``w → ∞`` being single shooting,
while LM works on a problem in which no simulation runs longer than ``T``. When the model
is wrong, the defects stay open by a fraction of the misfit (EMPS: 0.30 mm against a
1.77 mm position RMS): that slack is what keeps a long record well conditioned.

Why segments. A single simulation over a long record accumulates every force error: a
constant force error ``δF`` on a free mass drifts as ``δF·t²/(2m)``, and a rig whose plant
holds a pure integrator (EMPS: motor, screw and load; it is run in closed loop for that
reason) drifts away from the record when it is simulated open loop from the recorded
drive. The single-shooting cost is then a steep, strongly nonlinear function of θ whose
basin shrinks with the record length. Restarting each segment from its own state bounds
the drift to one segment, so the cost stays close to quadratic around the optimum and the
Jacobian well conditioned; this is what makes open-loop output error well-posed even for
the EMPS closed-loop recording: the controller's output ``vir`` is replayed as the input of
each segment, and ``T`` is short against the time the open-loop drift needs to exceed the
noise by far. The stiction-aware integrator resolves stops, reversals and breakaways
inside a segment; a segment that starts in a stuck phase gets a tiny ``ν_s`` that stops in
its first sub-step.

Choice of ``T`` (``segment_s``, default 0.5 s): long against the sample step and against
the mechanical time constants θ must explain (EMPS ``m/Fv`` = 0.47 s; twin 12 ms), so every
segment carries information about them, and short against the drift time; each segment
adds two columns to the Jacobian (cost per LM step grows with ``S``). The segment count
is ``S = max(1, round((n − 1)·dt / segment_s))`` (or ``segments`` when given), then
``L = ⌈(n − 1)/S⌉``.

Input. Models with ``measured_input`` are driven by the recorded ``u`` (linear between
samples, ``hold = "linear"``, as :func:`~fricjax.model.simulate.simulate` does; or held
over each sample interval, ``hold = "zero"``, for a rig whose input is a DAC output);
models without it (the seed's harmonic drive, eq. 4) by their drive function of ``t``.
(On EMPS the two holds give estimates 0.1 % apart.)

Cost. ``substeps = 1`` by default: one RK4 step per sample was measured 4.7e-8 m off a
16-sub-step reference over the 2 s twin (500× below its noise); raise it for stiffer
dynamics. The Jacobian is assembled from d + 2 forward tangents by
:meth:`OutputError.value_and_jacobian` (the residual's custom JVP), not d + 2S.

Box. θ stays in the config's box. ``ξ_s`` is initialised at the recorded ``x_{k_s}`` and
kept within ``±(20·σ_x + 0.01·range(x))``: the record is the true position plus noise of
std σ_x, so 20σ_x always holds the truth, and 1 % of the range leaves room for a biased
model. ``ν_s`` starts at the preprocessed velocity ``v_{k_s}`` and is kept within
``±(20·σ_v + 0.1·range(v))``, ``σ_v = g_v·σ_x`` with ``g_v`` the white-noise gain of the
configured velocity filter (:func:`fricjax.data.preprocess.noise_gains`): the filtered
velocity is off by its noise and by its bias at stops and sharp reversals (the filter
smears them over a few ms), which 10 % of the range covers.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Literal, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from fricjax.data.preprocess import PreprocessSettings, noise_gains
from fricjax.errors import FricjaxError, where
from fricjax.model.simulate import simulate
from fricjax.model.system import Model
from fricjax.params import ParamSpec
from fricjax.problem import Problem, needs_input
from fricjax.refine import RefineSettings, refine, uncertainty

__all__ = [
    "OutputError",
    "OutputErrorFit",
    "OutputErrorSettings",
    "OutputErrorSetup",
    "Segmentation",
    "fit_output_error",
    "jacobian_at",
    "noise_scale",
    "output_error_residual",
    "segmentation",
]

_HOLDS = ("linear", "zero")
# Box half-widths of the segment states (module docstring, "Box").
_STATE_SIGMAS = 20.0
_X_RANGE_FRACTION = 0.01
_V_RANGE_FRACTION = 0.1


class OutputErrorSettings(NamedTuple):
    """Settings of the output-error fit (the ``[output_error]`` config table).

    segment_s: target segment length T [s] (module docstring); ``inf`` = one segment.
    segments: segment count S; 0 (default) = from ``segment_s``.
    substeps: RK4 sub-steps per sample interval of the simulator (error ∝ substeps⁻⁴).
    defect_weight: w, weight of the continuity defects [-] (multiplied by √L).
    x_scale: σ_x [m], unit of the residual; 0 = estimated (:func:`noise_scale`).
    hold: how the recorded input is interpolated between samples, ``"linear"`` or ``"zero"``.
    max_steps, rtol, atol: Levenberg–Marquardt limits (:class:`fricjax.refine.RefineSettings`).
    """

    segment_s: float = 0.5
    segments: int = 0
    substeps: int = 1
    defect_weight: float = 10.0
    x_scale: float = 0.0
    hold: Literal["linear", "zero"] = "linear"
    max_steps: int = 100
    rtol: float = 1e-6
    atol: float = 1e-6

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], source: object = None) -> OutputErrorSettings:
        """Settings from a config table; unknown keys and bad values are refused in one line
        naming ``source`` and ``[output_error].key``."""
        if not isinstance(d, Mapping):
            raise FricjaxError(f"{where(source, '[output_error]')}: must be a table")
        out: dict[str, Any] = {}
        for key, value in d.items():
            loc = where(source, f"[output_error].{key}")
            if key not in cls._fields:
                raise FricjaxError(f"{loc}: unknown key (known: {', '.join(cls._fields)})")
            if key in ("segments", "substeps", "max_steps"):
                low = 0 if key == "segments" else 1
                if isinstance(value, bool) or not isinstance(value, int | np.integer):
                    raise FricjaxError(f"{loc}: must be an integer >= {low}, got {value!r}")
                if value < low:
                    raise FricjaxError(f"{loc}: must be an integer >= {low}, got {value!r}")
                out[key] = int(value)
            elif key == "hold":
                if value not in _HOLDS:
                    raise FricjaxError(f"{loc}: must be one of {', '.join(_HOLDS)}, got {value!r}")
                out[key] = str(value)
            else:
                if isinstance(value, bool) or not isinstance(
                    value, int | float | np.integer | np.floating
                ):
                    raise FricjaxError(f"{loc}: must be a number, got {value!r}")
                f = float(value)
                zero_ok = key == "x_scale"
                inf_ok = key == "segment_s"
                if math.isnan(f) or f < 0 or (f == 0 and not zero_ok):
                    need = ">= 0" if zero_ok else "> 0"
                    raise FricjaxError(f"{loc}: must be a number {need}, got {value!r}")
                if math.isinf(f) and not inf_ok:
                    raise FricjaxError(f"{loc}: must be finite, got {value!r}")
                out[key] = f
        return cls(**out)

    def refine_settings(self) -> RefineSettings:
        """The Levenberg–Marquardt settings of the fit (sine box transform)."""
        return RefineSettings(rtol=self.rtol, atol=self.atol, max_steps=self.max_steps)


# ---------------------------------------------------------------------------- segments


class Segmentation(NamedTuple):
    """How ``n`` samples are cut: ``S`` segments of ``L`` intervals (``L + 1`` samples).

    seg, pos: [n] int, segment of sample k and its index in that segment;
    starts: [S] int, first sample of each segment; n: samples; dt: step [s].
    """

    S: int
    L: int
    n: int
    dt: float
    seg: np.ndarray
    pos: np.ndarray
    starts: np.ndarray

    @property
    def duration(self) -> float:
        """Segment length T = L·dt [s]."""
        return self.L * self.dt


def segmentation(n: int, dt: float, settings: OutputErrorSettings) -> Segmentation:
    """Segment count and length for ``n`` samples of step ``dt`` (module docstring)."""
    if n < 2:
        raise FricjaxError(f"{where('output_error', 'n')}: needs >= 2 samples, got {n}")
    intervals = n - 1
    if settings.segments > 0:
        S = settings.segments
    elif math.isinf(settings.segment_s):
        S = 1
    else:
        S = max(1, round(intervals * dt / settings.segment_s))
    S = min(S, intervals)
    L = -(-intervals // S)
    # ⌈·⌉ can leave the last segments empty (e.g. 10 intervals in 4 segments of 3): drop them.
    S = -(-intervals // L)
    k = np.arange(n)
    seg = np.minimum(k // L, S - 1)
    return Segmentation(S, L, n, float(dt), seg, k - seg * L, np.arange(S) * L)


def noise_scale(x: Float[np.ndarray, " n"]) -> float:
    """White-noise std of a sampled position [m] from its third difference,
    ``std(Δ³x)/√20``; an upper bound (the motion adds ``jerk·dt³``), floored at 1e-12 m."""
    x = np.asarray(x, dtype=np.float64)
    if x.shape[0] < 4:
        return 1e-12
    return max(float(np.std(np.diff(x, 3)) / math.sqrt(20.0)), 1e-12)


def _segment_grid(t: np.ndarray, u: np.ndarray, seg: Segmentation) -> tuple[np.ndarray, np.ndarray]:
    """[S, L + 1] time and input of every segment; beyond the record, time continues with
    step dt and the input is held at its last value (those samples are not fitted)."""
    idx = seg.starts[:, None] + np.arange(seg.L + 1)[None, :]
    inside = np.minimum(idx, seg.n - 1)
    tt = t[inside] + (idx - inside) * seg.dt
    return tt, u[inside]


# ---------------------------------------------------------------------------- residual


def _simulate_segment(
    model: Model,
    p: Mapping[str, Array],
    t: Float[Array, " L1"],
    u: Float[Array, " L1"],
    x0: Float[Array, ""],
    v0: Float[Array, ""],
    substeps: int,
    hold: str,
) -> tuple[Float[Array, " L1"], Float[Array, " L1"]]:
    """Position [m] and velocity [m/s] of one segment at its sample times."""
    if hold == "linear":
        traj = simulate(model, p, t, x0, v0, u, substeps=substeps)
        return traj.x, traj.v
    dt = t[1] - t[0]

    def step(carry: tuple[Array, Array], data: tuple[Array, Array]) -> tuple:
        tk, uk = data
        held = jnp.stack([uk, uk])
        traj = simulate(model, p, jnp.stack([tk, tk + dt]), *carry, held, substeps=substeps)
        state = (traj.x[1], traj.v[1])
        return state, state

    _, (xs, vs) = jax.lax.scan(step, (x0, v0), (t[:-1], u[:-1]))
    return jnp.concatenate([x0[None], xs]), jnp.concatenate([v0[None], vs])


class OutputError(eqx.Module):
    """Multiple-shooting output-error residual ``θ_aug [d + 2S] → r_aug [n + 2(S − 1)]``
    (module docstring), dimensionless (units of σ_x). Data are array leaves, so one
    compilation serves every record of the same shape."""

    model: Model = eqx.field(static=True)
    spec: ParamSpec = eqx.field(static=True)
    t: Float[Array, "S L1"]
    u: Float[Array, "S L1"]
    x: Float[Array, " n"]
    seg: Int[Array, " n"]
    pos: Int[Array, " n"]
    x_scale: Float[Array, ""]
    v_to_x: Float[Array, ""]
    weight: Float[Array, ""]  # w·√L
    substeps: int = eqx.field(static=True)
    hold: str = eqx.field(static=True)

    @property
    def n_segments(self) -> int:
        return int(self.t.shape[0])

    @property
    def n_params(self) -> int:
        return self.spec.n_free

    def split(
        self, theta_aug: Float[Array, " D"]
    ) -> tuple[Float[Array, " d"], Float[Array, " S"], Float[Array, " S"]]:
        """θ [d], segment start positions ξ [S] [m], start velocities ν [S] [m/s]."""
        d, S = self.n_params, self.n_segments
        return theta_aug[:d], theta_aug[d : d + S], theta_aug[d + S : d + 2 * S]

    def trajectories(
        self, theta_aug: Float[Array, " D"]
    ) -> tuple[Float[Array, "S L1"], Float[Array, "S L1"]]:
        """Simulated x [m] and v [m/s] of every segment, [S, L + 1] each."""
        theta, xi, nu = self.split(theta_aug)
        p = self.spec.unflatten(theta)

        def one(t: Array, u: Array, x0: Array, v0: Array) -> tuple[Array, Array]:
            return _simulate_segment(self.model, p, t, u, x0, v0, self.substeps, self.hold)

        return jax.vmap(one)(self.t, self.u, xi, nu)

    def parts(
        self, theta_aug: Float[Array, " D"]
    ) -> tuple[Float[Array, " n"], Float[Array, " S1"], Float[Array, " S1"]]:
        """Simulated x at the samples [n] (stitched), position defects [S − 1] [m] and
        velocity defects [S − 1] [m/s]."""
        _, xi, nu = self.split(theta_aug)
        xs, vs = self.trajectories(theta_aug)
        return xs[self.seg, self.pos], xs[:-1, -1] - xi[1:], vs[:-1, -1] - nu[1:]

    def value(self, theta_aug: Float[Array, " D"]) -> Float[Array, " m"]:
        """``r_aug`` [n + 2(S − 1)] by plain autodiff-able code (the reference for
        :meth:`value_and_jacobian`)."""
        x_sim, dx, dv = self.parts(theta_aug)
        r = (x_sim - self.x) / self.x_scale
        c = self.weight / self.x_scale * jnp.concatenate([dx, dv * self.v_to_x])
        return jnp.concatenate([r, c])

    def value_and_jacobian(
        self, theta_aug: Float[Array, " D"]
    ) -> tuple[Float[Array, " m"], Float[Array, "m D"]]:
        """``r_aug`` and its Jacobian [n + 2(S − 1), d + 2S], using its block structure.

        Segment ``s`` depends on θ and on its own ``(ξ_s, ν_s)`` only, so d + 2 forward
        tangents of the trajectories give everything: one per θ component, one with
        ``dξ = (1, …, 1)`` and one with ``dν = (1, …, 1)`` (each segment picks up its own
        start's sensitivity; the segments' rows do not overlap). The defect rows add the
        known −1 of ``ξ_{s+1}``, ``ν_{s+1}``. Plain forward mode would need d + 2S tangents
        through every segment (EMPS: 102 instead of 6).
        """
        d, S = self.n_params, self.n_segments
        theta, xi, nu = self.split(theta_aug)

        def traj(th: Array, x0: Array, v0: Array) -> tuple[Array, Array]:
            return self.trajectories(jnp.concatenate([th, x0, v0]))

        (xs, vs), lin = jax.linearize(traj, theta, xi, nu)
        eye = jnp.eye(d + 2, dtype=theta.dtype)
        dth = eye[:, :d]
        dxi = jnp.broadcast_to(eye[:, d : d + 1], (d + 2, S))
        dnu = jnp.broadcast_to(eye[:, d + 1 : d + 2], (d + 2, S))
        tx, tv = jax.vmap(lin)(dth, dxi, dnu)  # [d + 2, S, L + 1] each
        scale = 1.0 / self.x_scale
        # sample rows: θ columns, then the own segment's ξ and ν columns
        a = tx[:, self.seg, self.pos] * scale  # [d + 2, n]
        own = jax.nn.one_hot(self.seg, S, dtype=theta.dtype)  # [n, S]
        j_samples = jnp.concatenate([a[:d].T, own * a[d][:, None], own * a[d + 1][:, None]], 1)
        # defect rows: d(end of s)/d(θ, ξ_s, ν_s) minus the start of s + 1
        diag, upper = jnp.eye(S - 1, S, dtype=theta.dtype), jnp.eye(S - 1, S, 1, dtype=theta.dtype)

        def defect_rows(t_end: Array, which: int, factor: Array) -> Array:
            start_x = diag * t_end[d][:, None] - (upper if which == 0 else 0.0)
            start_v = diag * t_end[d + 1][:, None] - (upper if which == 1 else 0.0)
            return factor * jnp.concatenate([t_end[:d].T, start_x, start_v], 1)

        w = self.weight * scale
        jac = jnp.concatenate(
            [
                j_samples,
                defect_rows(tx[:, :-1, -1], 0, w),
                defect_rows(tv[:, :-1, -1], 1, w * self.v_to_x),
            ]
        )
        r = (xs[self.seg, self.pos] - self.x) * scale
        c = w * jnp.concatenate([xs[:-1, -1] - xi[1:], (vs[:-1, -1] - nu[1:]) * self.v_to_x])
        return jnp.concatenate([r, c]), jac

    def __call__(self, theta_aug: Float[Array, " D"]) -> Float[Array, " m"]:
        """``r_aug`` [n + 2(S − 1)]; forward-mode derivatives go through
        :meth:`value_and_jacobian` (a custom JVP ``J·dθ``), so the refiner's
        linearisation, its transpose and the uncertainty's Jacobian are matrix products."""
        return _structured(self, theta_aug)


@jax.custom_jvp
def _structured(fn: OutputError, theta_aug: Array) -> Array:
    return fn.value(theta_aug)


@_structured.defjvp
def _structured_jvp(primals: tuple, tangents: tuple) -> tuple[Array, Array]:
    fn, theta_aug = primals
    # the data (fn's leaves) are never differentiated: only θ_aug's tangent is used
    r, jac = fn.value_and_jacobian(theta_aug)
    return r, jac @ tangents[1]


@jax.jit
def _call(fn: eqx.Module, theta: Array) -> Array:
    return fn(theta)


class _Jitted(eqx.Module):
    """The residual behind one jit boundary (the refiner and the uncertainty trace it
    several times; each trace then reuses one jaxpr instead of re-running the Python)."""

    fn: eqx.Module

    def __call__(self, theta: Array) -> Array:
        return _call(self.fn, theta)


@eqx.filter_jit
def jacobian_at(
    residual: OutputError, theta_aug: Float[Array, " D"]
) -> tuple[Float[Array, " m"], Float[Array, "m D"]]:
    """Jitted :meth:`OutputError.value_and_jacobian`: ``(r_aug, ∂r_aug/∂θ_aug)`` at
    ``theta_aug`` (one compilation per residual shape)."""
    return residual.value_and_jacobian(theta_aug)


class _Affine(eqx.Module):
    """``θ ↦ r0 + J·(θ − θ0)``: value and Jacobian of a residual at θ0, nothing else."""

    r0: Float[Array, " m"]
    jac: Float[Array, "m D"]
    theta0: Float[Array, " D"]

    def __call__(self, theta: Float[Array, " D"]) -> Float[Array, " m"]:
        return self.r0 + self.jac @ (theta - self.theta0)


class OutputErrorSetup(NamedTuple):
    """The pieces of a fit: the residual, the augmented start x0 [d + 2S] inside its box
    [lower, upper], the names of θ_aug (free parameters, ``x_seg<s>``, ``v_seg<s>``) and
    the segmentation."""

    residual: OutputError
    x0: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    names: list[str]
    seg: Segmentation


def _state_sigma_v(preprocess: PreprocessSettings | None, dt: float, x_scale: float) -> float:
    try:
        gain_v, _ = noise_gains(preprocess or PreprocessSettings(), 1.0 / dt)
    except FricjaxError:  # settings that cannot run on an impulse: fall back to differencing
        gain_v = math.sqrt(2.0) / dt
    return gain_v * x_scale


def output_error_residual(
    problem: Problem,
    start: Mapping[str, float],
    settings: OutputErrorSettings | None = None,
    states: tuple[np.ndarray, np.ndarray] | None = None,
) -> OutputErrorSetup:
    """The :class:`OutputError` residual of ``problem``, the augmented start vector and box
    (θ clipped into the config's box; segment states from the record, or ``states`` =
    (ξ [S], ν [S]) of an earlier fit with the same segmentation, clipped into their box),
    and names."""
    settings = settings or OutputErrorSettings()
    spec = problem.spec
    t = np.asarray(problem.t, dtype=np.float64)
    x = np.asarray(problem.x, dtype=np.float64)
    v = np.asarray(problem.v, dtype=np.float64)
    u = np.asarray(problem.u, dtype=np.float64)
    n = t.shape[0]
    dt = float((t[-1] - t[0]) / (n - 1)) if n > 1 else math.nan
    seg = segmentation(n, dt, settings)
    x_scale = settings.x_scale or noise_scale(x)
    known = {k: float(val) for k, val in start.items() if k in spec}
    theta0 = np.clip(spec.flatten(known), spec.lower, spec.upper)
    dx = _STATE_SIGMAS * x_scale + _X_RANGE_FRACTION * float(np.ptp(x))
    sigma_v = _state_sigma_v(problem.preprocess, dt, x_scale)
    dv = _STATE_SIGMAS * sigma_v + _V_RANGE_FRACTION * float(np.ptp(v))
    xi0, nu0 = x[seg.starts], v[seg.starts]
    xi_s, nu_s = (xi0, nu0) if states is None else (np.asarray(states[0]), np.asarray(states[1]))
    if xi_s.shape != xi0.shape or nu_s.shape != nu0.shape:
        raise FricjaxError(
            f"output error: {xi_s.shape[0]} segment states given for {seg.S} segments"
        )
    tt, uu = _segment_grid(t, u, seg)
    residual = OutputError(
        model=problem.model,
        spec=spec.structural(),
        t=jnp.asarray(tt),
        u=jnp.asarray(uu),
        x=jnp.asarray(x),
        seg=jnp.asarray(seg.seg),
        pos=jnp.asarray(seg.pos),
        x_scale=jnp.asarray(x_scale),
        v_to_x=jnp.asarray(seg.duration),
        weight=jnp.asarray(settings.defect_weight * math.sqrt(seg.L)),
        substeps=settings.substeps,
        hold=settings.hold,
    )
    names = [
        *spec.free_names,
        *(f"x_seg{s}" for s in range(seg.S)),
        *(f"v_seg{s}" for s in range(seg.S)),
    ]
    # the box of the states stays centred on the record's, so a warm start moves no bound
    xi_s = np.clip(xi_s, xi0 - dx, xi0 + dx)
    nu_s = np.clip(nu_s, nu0 - dv, nu0 + dv)
    return OutputErrorSetup(
        residual=residual,
        x0=np.concatenate([theta0, xi_s, nu_s]),
        lower=np.concatenate([spec.lower, xi0 - dx, nu0 - dv]),
        upper=np.concatenate([spec.upper, xi0 + dx, nu0 + dv]),
        names=names,
        seg=seg,
    )


# ---------------------------------------------------------------------------- the fit


class OutputErrorFit(NamedTuple):
    """Result of :func:`fit_output_error`.

    params: every model parameter by name (fixed ones included); names, value [d], std [d],
    rel_std [d], corr [d, d], flags [d]: the free parameters, their values, Gauss–Newton σ
    (white-residual assumption: on real data, where the misfit is model error, an
    optimistic bound), correlations and identifiability flags (:func:`fricjax.refine.
    uncertainty` on θ_aug, restricted to θ); cond: condition number of the scaled JᵀJ of
    θ_aug; cost: E_OE at the optimum [-] (units of σ_x²); cost_start: at the start;
    position_rms: √(mean((x_sim − x)²)) [m] over the n samples; x_sim [n]: the stitched
    simulated position [m]; x_scale: σ_x [m]; defect_x, defect_v: max |defect| [m], [m/s];
    states_x, states_v [S]: ξ [m], ν [m/s]; n_segments: S; segment_samples: L;
    n_residual: length of r_aug; n_steps: LM iterations; success: LM converged.
    """

    params: dict[str, float]
    names: list[str]
    value: np.ndarray
    std: np.ndarray
    rel_std: np.ndarray
    corr: np.ndarray
    flags: list[list[str]]
    cond: float
    cost: float
    cost_start: float
    position_rms: float
    x_sim: np.ndarray
    x_scale: float
    defect_x: float
    defect_v: float
    states_x: np.ndarray
    states_v: np.ndarray
    n_segments: int
    segment_samples: int
    n_residual: int
    n_steps: int
    success: bool


def _check_problem(problem: Problem) -> None:
    src = problem.source or problem.name or "output_error"
    if problem.n < 4:
        raise FricjaxError(f"{where(src, '/x')}: output error needs >= 4 kept samples")
    if needs_input(problem.model) and not np.any(problem.u):
        raise FricjaxError(f"{where(src, '/u')}: all zero; the measured_input model has no drive")


def fit_output_error(
    problem: Problem,
    start: Mapping[str, float],
    settings: OutputErrorSettings | None = None,
    states: tuple[np.ndarray, np.ndarray] | None = None,
) -> OutputErrorFit:
    """Minimise E_OE (module docstring) over θ and the segment states by Levenberg–Marquardt
    (:func:`fricjax.refine.refine`, sine box transform) from ``start`` (named values, e.g.
    the equation-error estimate; missing free names take the config's init), inside the
    config's box for θ and the state box of the module docstring.

    Args:
        problem: the preprocessed recording and model (x, the preprocessed v for the state
            starts, u for a measured-input model; the config's trim already applied).
        start: named parameter values.
        settings: :class:`OutputErrorSettings`.
        states: segment states (ξ [S] m, ν [S] m/s) to start from, e.g. those of an
            earlier fit of the same record (``states_x``, ``states_v``); default: the
            record's.
    """
    settings = settings or OutputErrorSettings()
    _check_problem(problem)
    setup = output_error_residual(problem, start, settings, states)
    fn = _Jitted(setup.residual)
    out = refine(fn, setup.x0, setup.lower, setup.upper, settings.refine_settings())
    x_aug = np.asarray(out.x)
    r_opt, jac = jacobian_at(setup.residual, jnp.asarray(x_aug))
    # The uncertainty needs r and J at the optimum only: hand it the affine model
    # r + J·(θ − θ*), which has exactly those, instead of compiling the simulation again.
    unc = uncertainty(
        _Affine(r_opt, jac, jnp.asarray(x_aug)),
        jnp.asarray(x_aug),
        setup.lower,
        setup.upper,
        names=setup.names,
    )
    d, S, n = problem.spec.n_free, setup.seg.S, problem.n
    # x_sim and the defects from the residual: r = (x_sim − x)/σ_x, c^x = w√L·Δx/σ_x,
    # c^v = w√L·Δv·T/σ_x.
    r = np.asarray(r_opt)
    res = setup.residual
    sx, wt = float(res.x_scale), float(res.weight)
    x_sim = np.asarray(problem.x) + sx * r[:n]
    dx = r[n : n + S - 1] * sx / wt
    dv = r[n + S - 1 :] * sx / (wt * setup.seg.duration)
    theta = x_aug[:d]
    rec_x = np.asarray(problem.x)
    return OutputErrorFit(
        params=problem.spec.as_dict(theta),
        names=list(problem.spec.free_names),
        value=theta,
        std=np.asarray(unc.std[:d]),
        rel_std=np.asarray(unc.rel_std[:d]),
        corr=np.asarray(unc.corr[:d, :d]),
        flags=[list(f) for f in unc.flags[:d]],
        cond=float(unc.cond),
        cost=float(out.cost_after),
        cost_start=float(out.cost_before),
        position_rms=float(np.sqrt(np.mean((x_sim - rec_x) ** 2))),
        x_sim=x_sim,
        x_scale=float(setup.residual.x_scale),
        defect_x=float(np.max(np.abs(dx))) if dx.size else 0.0,
        defect_v=float(np.max(np.abs(dv))) if dv.size else 0.0,
        states_x=x_aug[d : d + S],
        states_v=x_aug[d + S : d + 2 * S],
        n_segments=S,
        segment_samples=setup.seg.L,
        n_residual=int(problem.n + 2 * (S - 1)),
        n_steps=int(out.n_steps),
        success=bool(out.success),
    )
