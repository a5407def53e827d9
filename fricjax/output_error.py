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
dynamics. The Jacobian is assembled from K + 2 forward tangents by
:meth:`OutputError.value_and_jacobian` (the residual's custom JVP), not P + 2S, with K
the parameters the fit moves (:func:`fit_output_error_batch`; the columns of the fixed
and masked ones are zero): a superset model's base fit moves about half of its
parameters. What that saves per LM step is measured in docs/output-error.md ("The
Jacobian along the fitted parameters only").

Compilation and batching. The residual runs over all P parameters of the model, the
fixed ones included, and a fit holds the components it does not move at their values by
a mask (:func:`fit_output_error_batch`). What is static is only the model, the parameter
names, the record's shape, the segmentation, the settings and K; the data, the start,
the fixed values, the mask and the Jacobian's directions are traced. One program (LM and
the Jacobian at its end point) is therefore compiled per (model, names, shapes, settings,
B, K) and serves every record of that shape, every start and every choice of fixed
parameters; B fits of one model (a superset model: a base and several extra terms, each
term pinned at its null where it is not tested) run as one vmapped program
(docs/output-error.md, "Speed and batching").

Tying the segments. From the record's states (``states`` not given) the fit runs in two
stages: the segments are first fitted free of each other (defect weight 0: each segment's
start is a free state, and θ is shared), then tied with the weight ``w`` from that end
point. Both stages are Levenberg–Marquardt to the Gauss–Newton decrement ``gain_tol``
(:mod:`fricjax.levenberg`), at most ``max_steps`` each. Why: the tie is a quadratic penalty
on the continuity defects, and a penalty of weight ``w²L`` (5·10³ at the judge's 50
samples) makes the cost a narrow valley along the curved set of continuous trajectories,
which damped Gauss–Newton follows in short steps (on the seed model's 1 s twin from the
equation-error estimate: 380 steps to the decrement 1e-11 at ``w`` = 10). Free segments are
a well-conditioned problem (60 steps), and from its optimum the tied one is a few steps
away (10, to the same minimum, cost 944.565 σ_x² both ways); this is the penalty method's
continuation in its weight. A start from an earlier fit's states (a further round, a
candidate from the base's optimum) is tied already and runs the tied stage twice, the
second a check that costs one Jacobian.

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

import itertools
import math
from collections import Counter
from collections.abc import Mapping
from typing import Any, Literal, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from fricjax.data.preprocess import PreprocessSettings, noise_gains
from fricjax.errors import FricjaxError, where
from fricjax.levenberg import levenberg_marquardt
from fricjax.model.simulate import simulate
from fricjax.model.system import Model
from fricjax.problem import Problem, needs_input
from fricjax.programs import stored
from fricjax.refine import Refined, RefineSettings, checked_refine_settings, uncertainty_at
from fricjax.search.fast_compile import CLASSIC_EMITTERS

__all__ = [
    "TRACES",
    "OutputError",
    "OutputErrorFit",
    "OutputErrorSettings",
    "OutputErrorSetup",
    "Segmentation",
    "fit_output_error",
    "fit_output_error_batch",
    "jacobian_at",
    "noise_scale",
    "output_error_residual",
    "sample_residual",
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
    max_steps, rtol, atol: Levenberg–Marquardt limits (:class:`fricjax.refine.RefineSettings`);
        ``max_steps`` per stage (module docstring, "Tying the segments").
    gain_tol: Gauss–Newton decrement [σ_x²] at which a stage has converged
        (:mod:`fricjax.levenberg`): the full Gauss–Newton step from there is shorter than
        ``√gain_tol`` standard errors of the estimate (r is in units of the noise), so
        0.01 leaves every parameter within 0.1 of its standard error of the optimum.
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
    gain_tol: float = 0.01

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
                zero_ok = key in ("x_scale", "gain_tol")
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
    starts: [S] int, first sample of each segment; ends: [S] int, last sample of the
    recording each segment belongs to (beyond it the segment is padding); tie: [S − 1],
    1 where segment s + 1 continues segment s, 0 where it starts a later recording of a
    joined problem (its continuity defect is not fitted); n: samples; dt: step [s].
    """

    S: int
    L: int
    n: int
    dt: float
    seg: np.ndarray
    pos: np.ndarray
    starts: np.ndarray
    ends: np.ndarray
    tie: np.ndarray

    @property
    def duration(self) -> float:
        """Segment length T = L·dt [s]."""
        return self.L * self.dt


def segmentation(
    n: int, dt: float, settings: OutputErrorSettings, joins: tuple[int, ...] = ()
) -> Segmentation:
    """Segment count and length for ``n`` samples of step ``dt`` (module docstring).

    ``joins``: the first sample of each later recording of a joined problem
    (:func:`fricjax.problem.joined`). Each recording is then cut as it would be alone, with
    the longest of their segment lengths for all (the segments form one ``[S, L + 1]``
    batch), and no segment spans a join."""
    if n < 2:
        raise FricjaxError(f"{where('output_error', 'n')}: needs >= 2 samples, got {n}")
    bounds = [0, *joins, n]
    if any(b - a < 2 for a, b in itertools.pairwise(bounds)):
        raise FricjaxError(f"{where('output_error', 'joins')}: a recording of < 2 samples")

    def length(intervals: int) -> int:
        if settings.segments > 0:
            S = settings.segments
        elif math.isinf(settings.segment_s):
            S = 1
        else:
            S = max(1, round(intervals * dt / settings.segment_s))
        S = min(S, intervals)
        return -(-intervals // S)

    parts = list(itertools.pairwise(bounds))
    L = max(length(b - a - 1) for a, b in parts)
    seg, pos, starts, ends, tie = [], [], [], [], []
    for a, b in parts:
        # ⌈·⌉ can leave the last segments empty (10 intervals in 4 segments of 3): none is made
        S_m = -(-(b - a - 1) // L)
        k = np.arange(b - a)
        j = np.minimum(k // L, S_m - 1)
        seg.append(len(starts) + j)
        pos.append(k - j * L)
        tie.extend([0.0] * bool(starts) + [1.0] * (S_m - 1))
        starts.extend(a + L * np.arange(S_m))
        ends.extend([b - 1] * S_m)
    return Segmentation(
        len(starts),
        L,
        n,
        float(dt),
        np.concatenate(seg),
        np.concatenate(pos),
        np.asarray(starts, dtype=int),
        np.asarray(ends, dtype=int),
        np.asarray(tie, dtype=np.float64),
    )


def noise_scale(x: Float[np.ndarray, " n"], joins: tuple[int, ...] = ()) -> float:
    """White-noise std of a sampled position [m] from its third difference,
    ``std(Δ³x)/√20``, taken within each recording of a joined problem (``joins``, where
    the position jumps); an upper bound (the motion adds ``jerk·dt³``), floored at 1e-12 m."""
    x = np.asarray(x, dtype=np.float64)
    parts = [d for part in np.split(x, list(joins)) if (d := np.diff(part, 3)).size]
    if not parts:
        return 1e-12
    return max(float(np.std(np.concatenate(parts))) / math.sqrt(20.0), 1e-12)


def _segment_grid(t: np.ndarray, u: np.ndarray, seg: Segmentation) -> tuple[np.ndarray, np.ndarray]:
    """[S, L + 1] time and input of every segment; beyond its recording's end, time
    continues with step dt and the input is held at its last value (those samples are not
    fitted)."""
    idx = seg.starts[:, None] + np.arange(seg.L + 1)[None, :]
    inside = np.minimum(idx, seg.ends[:, None])
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
    """Multiple-shooting output-error residual ``θ_aug [P + 2S] → r_aug [n + 2(S − 1)]``
    (module docstring), dimensionless (units of σ_x), over EVERY parameter of the model
    (``names``, fixed ones included: which of them a fit moves is the caller's mask, see
    :func:`fit_output_error_batch`). Data and parameter values are array leaves and only
    the model, the names, the shapes and the integrator settings are static, so one
    compilation serves every record of the same shape and every choice of fixed values.

    ``directions`` [K, P]: the directions of θ along which :meth:`value_and_jacobian`
    differentiates, orthonormal rows or zero rows (padding); a fit passes unit vectors of
    the parameters it moves. They are a traced leaf: only K is static, so one program
    serves every choice of K directions. Default (:func:`output_error_residual`): the
    identity, every parameter.

    ``keep`` [n]: 1 where a sample's misfit counts, 0 where it is held out (a fold of the
    cross-validation, :mod:`fricjax.diagnose.heldout`): a held-out sample's residual row is
    zero, while the segments still run through it, tied to their neighbours by the
    continuity defects, so what the fit predicts there comes from the data around it."""

    model: Model = eqx.field(static=True)
    names: tuple[str, ...] = eqx.field(static=True)
    t: Float[Array, "S L1"]
    u: Float[Array, "S L1"]
    x: Float[Array, " n"]
    seg: Int[Array, " n"]
    pos: Int[Array, " n"]
    x_scale: Float[Array, ""]
    v_to_x: Float[Array, ""]
    weight: Float[Array, ""]  # w·√L
    tie: Float[Array, " S1"]  # 1: the defect is fitted; 0: a join of recordings (none)
    directions: Float[Array, "K P"]
    keep: Float[Array, " n"]  # 1: the sample is fitted; 0: held out (cross-validation)
    substeps: int = eqx.field(static=True)
    hold: str = eqx.field(static=True)

    @property
    def n_segments(self) -> int:
        return int(self.t.shape[0])

    @property
    def n_params(self) -> int:
        return len(self.names)

    def split(
        self, theta_aug: Float[Array, " D"]
    ) -> tuple[Float[Array, " P"], Float[Array, " S"], Float[Array, " S"]]:
        """θ [P], segment start positions ξ [S] [m], start velocities ν [S] [m/s]."""
        d, S = self.n_params, self.n_segments
        return theta_aug[:d], theta_aug[d : d + S], theta_aug[d + S : d + 2 * S]

    def trajectories(
        self, theta_aug: Float[Array, " D"]
    ) -> tuple[Float[Array, "S L1"], Float[Array, "S L1"]]:
        """Simulated x [m] and v [m/s] of every segment, [S, L + 1] each."""
        theta, xi, nu = self.split(theta_aug)
        p = {name: theta[i] for i, name in enumerate(self.names)}

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
        r = (x_sim - self.x) / self.x_scale * self.keep
        c = self.weight / self.x_scale * jnp.concatenate([dx, dv * self.v_to_x]) * self._ties
        return jnp.concatenate([r, c])

    @property
    def _ties(self) -> Float[Array, " S2"]:
        """[2(S − 1)]: the tie of every defect row, position rows then velocity rows."""
        return jnp.concatenate([self.tie, self.tie])

    def value_and_jacobian(
        self, theta_aug: Float[Array, " D"]
    ) -> tuple[Float[Array, " m"], Float[Array, "m D"]]:
        """``r_aug`` and its Jacobian along the directions, using its block structure:
        ``[(∂r_aug/∂θ)·DᵀD | ∂r_aug/∂ξ | ∂r_aug/∂ν]`` [n + 2(S − 1), P + 2S], D =
        ``directions`` [K, P]. With D the identity (the default) it is the whole Jacobian;
        with D the unit rows of the parameters a fit moves, the other parameters' columns
        are exactly zero and the fitted ones are the whole Jacobian's.

        Segment ``s`` depends on θ and on its own ``(ξ_s, ν_s)`` only, so K + 2 forward
        tangents of the trajectories give everything: one per direction of θ (a zero row
        gives a zero tangent), one with ``dξ = (1, …, 1)`` and one with ``dν = (1, …, 1)``
        (each segment picks up its own start's sensitivity; the segments' rows do not
        overlap). The defect rows add the known −1 of ``ξ_{s+1}``, ``ν_{s+1}``. Plain
        forward mode would need P + 2S tangents through every segment (EMPS: 102 instead
        of 6).
        """
        K, S = self.directions.shape[0], self.n_segments
        theta, xi, nu = self.split(theta_aug)

        def traj(th: Array, x0: Array, v0: Array) -> tuple[Array, Array]:
            return self.trajectories(jnp.concatenate([th, x0, v0]))

        dirs = self.directions.astype(theta.dtype)
        dth = jnp.concatenate([dirs, jnp.zeros((2, theta.shape[0]), theta.dtype)])
        eye = jnp.eye(K + 2, dtype=theta.dtype)
        dxi = jnp.broadcast_to(eye[:, K : K + 1], (K + 2, S))
        dnu = jnp.broadcast_to(eye[:, K + 1 : K + 2], (K + 2, S))
        # vmapped JVPs rather than jax.linearize + vmap: linearize's partial evaluation of
        # the simulator's nested loops traces and compiles about 3x longer, and its
        # linear program runs about 2x slower than the batched forward pass (twin superset)
        (xs, vs), (tx, tv) = jax.vmap(lambda a, b, c: jax.jvp(traj, (theta, xi, nu), (a, b, c)))(
            dth, dxi, dnu
        )  # [K + 2, S, L + 1] each
        xs, vs = xs[0], vs[0]
        scale = 1.0 / self.x_scale
        # sample rows: θ columns, then the own segment's ξ and ν columns
        a = tx[:, self.seg, self.pos] * (scale * self.keep)  # [K + 2, n]
        own = jax.nn.one_hot(self.seg, S, dtype=theta.dtype)  # [n, S]
        j_samples = jnp.concatenate(
            [a[:K].T @ dirs, own * a[K][:, None], own * a[K + 1][:, None]], 1
        )
        # defect rows: d(end of s)/d(θ, ξ_s, ν_s) minus the start of s + 1
        diag, upper = jnp.eye(S - 1, S, dtype=theta.dtype), jnp.eye(S - 1, S, 1, dtype=theta.dtype)

        def defect_rows(t_end: Array, which: int, factor: Array) -> Array:
            start_x = diag * t_end[K][:, None] - (upper if which == 0 else 0.0)
            start_v = diag * t_end[K + 1][:, None] - (upper if which == 1 else 0.0)
            return factor * jnp.concatenate([t_end[:K].T @ dirs, start_x, start_v], 1)

        w = (self.weight * scale * self.tie)[:, None]
        jac = jnp.concatenate(
            [
                j_samples,
                defect_rows(tx[:, :-1, -1], 0, w),
                defect_rows(tv[:, :-1, -1], 1, w * self.v_to_x),
            ]
        )
        r = (xs[self.seg, self.pos] - self.x) * (scale * self.keep)
        c = (self.weight * scale * self._ties) * jnp.concatenate(
            [xs[:-1, -1] - xi[1:], (vs[:-1, -1] - nu[1:]) * self.v_to_x]
        )
        return jnp.concatenate([r, c]), jac

    def __call__(self, theta_aug: Float[Array, " D"]) -> Float[Array, " m"]:
        """``r_aug`` [n + 2(S − 1)]; forward-mode derivatives go through
        :meth:`value_and_jacobian` (a custom JVP ``J·dθ``), so the refiner's
        linearisation, its transpose and the uncertainty's Jacobian are matrix products."""
        return _structured(self, theta_aug)


@jax.jit
def _value_and_jacobian(
    residual: OutputError, theta_aug: Float[Array, " D"]
) -> tuple[Float[Array, " m"], Float[Array, "m D"]]:
    return residual.value_and_jacobian(theta_aug)


@stored
def jacobian_at(
    residual: OutputError, theta_aug: Float[Array, " D"]
) -> tuple[Float[Array, " m"], Float[Array, "m D"]]:
    """Jitted :meth:`OutputError.value_and_jacobian`: ``(r_aug, ∂r_aug/∂θ_aug)`` at
    ``theta_aug`` (one compilation per residual shape). The residual's custom JVP, the
    fit's iterations and its end point call it. Its body is a jitted function of its own,
    so that the simulation's linearisation, the costliest trace of the fit, is traced once
    per process and its jaxpr reused: inside the fit's program, and where a call on arrays
    (the candidates' screening) exports it to the program store (:mod:`fricjax.programs`)."""
    return _value_and_jacobian(residual, theta_aug)


@stored
def _value_at(residual: OutputError, theta_aug: Float[Array, " D"]) -> Float[Array, " m"]:
    return residual.value(theta_aug)


def sample_residual(
    problem: Problem, fit: OutputErrorFit, settings: OutputErrorSettings
) -> Float[np.ndarray, " n"]:
    """``(x_sim − x)/σ_x`` [n] at every sample of ``fit``'s end point (its parameters and
    segment states), the samples it held out included: what the fit predicts there."""
    setup = output_error_residual(problem, fit.params, settings, (fit.states_x, fit.states_v))
    return np.asarray(_value_at(setup.residual, jnp.asarray(setup.x0)))[: problem.n]


@jax.custom_jvp
def _structured(fn: OutputError, theta_aug: Array) -> Array:
    return fn.value(theta_aug)


@_structured.defjvp
def _structured_jvp(primals: tuple, tangents: tuple) -> tuple[Array, Array]:
    fn, theta_aug = primals
    # the data (fn's leaves) are never differentiated: only θ_aug's tangent is used
    r, jac = jacobian_at(fn, theta_aug)
    return r, jac @ tangents[1]


class OutputErrorSetup(NamedTuple):
    """The pieces of a fit over every parameter of the model: the residual, the augmented
    start x0 [P + 2S] (every parameter, then ξ and ν) inside its box [lower, upper]
    (a parameter the spec fixes sits at its value, inside its bounds), ``free`` [P + 2S] (the
    spec's free parameters and every segment state), the names of θ_aug (every parameter,
    ``x_seg<s>``, ``v_seg<s>``) and the segmentation."""

    residual: OutputError
    x0: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    free: np.ndarray
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
    (free parameters from ``start`` clipped into the config's box, missing ones at their
    init, fixed ones at their value; segment states from the record, or ``states`` =
    (ξ [S], ν [S]) of an earlier fit with the same segmentation, clipped into their box),
    the free mask and the names."""
    settings = settings or OutputErrorSettings()
    spec = problem.spec
    t = np.asarray(problem.t, dtype=np.float64)
    x = np.asarray(problem.x, dtype=np.float64)
    v = np.asarray(problem.v, dtype=np.float64)
    u = np.asarray(problem.drive_input, dtype=np.float64)
    n = t.shape[0]
    dt = problem.dt
    seg = segmentation(n, dt, settings, problem.joins)
    x_scale = settings.x_scale or noise_scale(x, problem.joins)
    known = {k: float(val) for k, val in start.items() if k in spec}
    p_lower = np.array([p.lower for p in spec.params])
    p_upper = np.array([p.upper for p in spec.params])
    p_free = np.array([p.free for p in spec.params], dtype=bool)
    values = np.array([known.get(p.name, p.init) if p.free else p.init for p in spec.params])
    theta0 = np.clip(values, p_lower, p_upper)
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
        names=spec.names,
        t=jnp.asarray(tt),
        u=jnp.asarray(uu),
        x=jnp.asarray(x),
        seg=jnp.asarray(seg.seg),
        pos=jnp.asarray(seg.pos),
        # float64, not weakly typed: the custom JVP's primals must have the avals of the
        # fit's own call of jacobian_at for the two to share one trace
        x_scale=jnp.asarray(x_scale, dtype=jnp.float64),
        v_to_x=jnp.asarray(seg.duration, dtype=jnp.float64),
        weight=jnp.asarray(settings.defect_weight * math.sqrt(seg.L), dtype=jnp.float64),
        tie=jnp.asarray(seg.tie, dtype=jnp.float64),
        directions=jnp.eye(len(spec.names), dtype=jnp.float64),
        keep=jnp.ones(n, dtype=jnp.float64),
        substeps=settings.substeps,
        hold=settings.hold,
    )
    names = [
        *spec.names,
        *(f"x_seg{s}" for s in range(seg.S)),
        *(f"v_seg{s}" for s in range(seg.S)),
    ]
    # the box of the states stays centred on the record's, so a warm start moves no bound
    xi_s = np.clip(xi_s, xi0 - dx, xi0 + dx)
    nu_s = np.clip(nu_s, nu0 - dv, nu0 + dv)
    return OutputErrorSetup(
        residual=residual,
        x0=np.concatenate([theta0, xi_s, nu_s]),
        lower=np.concatenate([p_lower, xi0 - dx, nu0 - dv]),
        upper=np.concatenate([p_upper, xi0 + dx, nu0 + dv]),
        free=np.concatenate([p_free, np.ones(2 * seg.S, dtype=bool)]),
        names=names,
        seg=seg,
    )


# ---------------------------------------------------------------------------- the fit


class OutputErrorFit(NamedTuple):
    """Result of :func:`fit_output_error` (one row of :func:`fit_output_error_batch`).

    params: every model parameter by name (fixed and pinned ones included); names, value
    [d], std [d], rel_std [d], corr [d, d], flags [d]: the fitted parameters, their values,
    Gauss–Newton σ (white-residual assumption: on real data, where the misfit is model
    error, an optimistic bound), correlations and identifiability flags (:func:`fricjax.
    refine.uncertainty_at` on the fitted components of θ_aug, restricted to θ); cond:
    condition number of the scaled JᵀJ of those components; cost: E_OE at the optimum [-]
    (units of σ_x²); cost_start: at the start; position_rms: √(mean((x_sim − x)²)) [m] over
    the n samples; x_sim [n]: the stitched simulated position [m]; x_scale: σ_x [m];
    defect_x, defect_v: max |defect| [m], [m/s]; states_x, states_v [S]: ξ [m], ν [m/s];
    n_segments: S; segment_samples: L; segment_of [n]: the segment of each sample;
    n_residual: the rows of r_aug that can be nonzero (n and the tied defects); n_steps: LM
    iterations; success: LM converged.
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
    segment_of: np.ndarray
    n_residual: int
    n_steps: int
    success: bool


def _check_problem(problem: Problem) -> None:
    src = problem.source or problem.name or "output_error"
    if problem.n < 4:
        raise FricjaxError(f"{where(src, '/x')}: output error needs >= 4 kept samples")
    if needs_input(problem.model) and not np.any(problem.drive_input):
        raise FricjaxError(f"{where(src, '/u')}: all zero; the measured_input model has no drive")


#: Traces of the batched fit program, by (model name, B, P + 2S, n, K): a numerical
#: record of when :func:`fit_output_error_batch` compiles (a warm call adds nothing here).
TRACES: Counter[tuple[str, int, int, int, int]] = Counter()


def _fit_rows(
    residual: OutputError,
    x0s: Float[Array, "B D"],
    free: Bool[Array, "B D"],
    directions: Float[Array, "B K P"],
    lower: Float[Array, "B D"],
    upper: Float[Array, "B D"],
    samples: Float[Array, "B n"],
    weights: Float[Array, " stages"],
    settings: RefineSettings,
    gain_tol: float,
    accelerate: Bool[Array, ""],
) -> tuple[Refined, Float[Array, "B m"], Float[Array, "B m D"]]:
    """LM of every row (components outside ``free[b]`` pinned at ``x0s[b]``, the Jacobian
    taken along ``directions[b]``, which span the row's free parameters; the samples with
    ``samples[b]`` = 0 held out, :attr:`OutputError.keep`), then r_aug and
    its Jacobian at each end point: one program, the rows vmapped (the batched
    ``while_loop`` runs until the last row stops; each row keeps its own end point, step
    count and convergence flag).

    The fit runs in stages, each from the end of the one before, with the defect weight
    ``w·√L`` of the residual replaced by ``weights[i]`` (module docstring, "Tying the
    segments"); a ``lax.scan`` over the stages, so that the Jacobian program has one call
    site. ``cost_before`` is the first stage's start, ``n_steps`` the sum over the stages,
    ``success`` and the rest the last stage's. ``accelerate``: geodesic or plain steps
    (:func:`fricjax.levenberg.levenberg_marquardt`), traced: one program serves both."""
    TRACES[(residual.model.name, *x0s.shape, residual.x.shape[0], directions.shape[1])] += 1

    def one(
        x0: Array, keep: Array, dirs: Array, lo: Array, hi: Array, fitted: Array
    ) -> tuple[Refined, Array, Array]:
        res = eqx.tree_at(lambda m: (m.directions, m.keep), residual, (dirs, fitted))

        def held(theta_aug: Array) -> Array:
            return jnp.where(keep, theta_aug, x0)

        def stage(carry: tuple, weight: Array) -> tuple[tuple, Refined]:
            x, _, _ = carry
            tied = eqx.tree_at(lambda m: m.weight, res, weight)
            out, r, jac = levenberg_marquardt(
                lambda th: tied.value(held(th)),
                lambda th: jacobian_at(tied, held(th)),
                x,
                lo,
                hi,
                keep,
                settings,
                gain_tol,
                accelerate,
            )
            # r and J at the end point come from the iterations' one call of the Jacobian
            # program; the held columns are exactly zero
            return (out.x, r, jac), out

        r0, jac0 = jax.eval_shape(lambda th: jacobian_at(res, th), x0)
        zeros = (jnp.zeros(r0.shape, r0.dtype), jnp.zeros(jac0.shape, jac0.dtype))
        (_, r, jac), stages = jax.lax.scan(stage, (x0, *zeros), weights)
        outs: Refined = stages
        out = Refined(
            x=outs.x[-1],
            cost_before=outs.cost_before[0],
            cost_after=outs.cost_after[-1],
            n_steps=jnp.sum(outs.n_steps),
            success=outs.success[-1],
        )
        return out, r, jac

    if x0s.shape[0] == 1:
        # vmap would turn the LM's branches into selects that evaluate both sides
        out, r, jac = one(x0s[0], free[0], directions[0], lower[0], upper[0], samples[0])
        return jax.tree.map(lambda a: a[None], (out, r, jac))
    return jax.vmap(one)(x0s, free, directions, lower, upper, samples)


# compile time is most of a cold fit's time, and the classic emitter saves a fifth of it
_fit_rows_jit = stored(_fit_rows, compiler_options=CLASSIC_EMITTERS)


def fit_output_error_batch(
    problem: Problem,
    starts: Float[np.ndarray, "B d"],
    free: Bool[np.ndarray, "B d"] | None = None,
    settings: OutputErrorSettings | None = None,
    states: tuple[np.ndarray, np.ndarray] | None = None,
    n_directions: int | None = None,
    samples: Float[np.ndarray, " n"] | None = None,
    accelerate: bool = True,
) -> list[OutputErrorFit]:
    """B output-error fits of ONE model as one compiled program (:func:`fit_output_error`
    row by row): row ``b`` starts from ``starts[b]`` (the spec's free parameters, in
    ``problem.spec.free_names`` order) and fits those with ``free[b]`` set (default: all),
    the others pinned at ``starts[b]``, together with the segment states.

    The Jacobian is taken along K directions per row (:class:`OutputError`), the unit
    vectors of the row's fitted parameters padded with zero rows: K + 2 forward tangents
    per Jacobian instead of P + 2 (P: every parameter of the model, fixed and pinned ones
    included), at the same columns for the fitted parameters.

    The program is compiled once per (model, parameter names, record shape, segmentation,
    B, K, settings): which parameters are pinned, at what values, and the data are traced.
    So a superset model (a base and several extra terms, each term's amplitude pinned at
    its null 0 where it is not tested) fits every candidate × start in one program, and a
    row equals the fit of the model whose spec fixes its pinned parameters (same LM steps:
    a pinned component has a zero Jacobian column, so the damped step leaves it at rest).

    Args:
        problem: as for :func:`fit_output_error`.
        starts: [B, d] start values (clipped into the config's box), d = spec.n_free.
        free: [B, d] bool, the parameters each row fits; None: all of them.
        settings: :class:`OutputErrorSettings`.
        states: segment states to start from, (ξ, ν) of shape [S] (every row) or [B, S].
        n_directions: K, at least the largest count of fitted parameters over the rows
            (the default) and at most P; a caller that fits several models of one superset
            passes one K (e.g. the largest model's count) so that they share one program.
        samples: [n] or [B, n]: 1 where a sample's misfit counts, 0 where it is held out
            (:attr:`OutputError.keep`; a row each, e.g. the folds of a cross-validation);
            default: every sample. Traced: the same program. The returned ``x_sim`` and
            ``position_rms`` then hold on the fitted samples only (the held-out ones read as
            the record).
        accelerate: geodesic acceleration (a first fit) or plain damped steps (a restart
            from a converged end point; :mod:`fricjax.levenberg`, "Two kinds of step").

    Returns:
        B :class:`OutputErrorFit`, in row order.
    """
    settings = settings or OutputErrorSettings()
    _check_problem(problem)
    spec = problem.spec
    src = problem.source or problem.name or "output_error"
    x0 = np.asarray(starts, dtype=np.float64)
    d = spec.n_free
    if x0.ndim != 2 or x0.shape[1] != d or x0.shape[0] < 1:
        raise FricjaxError(
            f"{where(src, 'starts')}: shape {x0.shape}, expected (B >= 1, {d}) for the free "
            f"parameters {', '.join(spec.free_names)}"
        )
    B = x0.shape[0]
    mask = np.ones((B, d), dtype=bool) if free is None else np.asarray(free)
    if mask.shape != x0.shape or mask.dtype != np.bool_:
        raise FricjaxError(f"{where(src, 'free')}: must be a bool array of shape {x0.shape}")
    if not np.all(np.isfinite(x0)):
        raise FricjaxError(f"{where(src, 'starts')}: not all finite")
    setup = output_error_residual(problem, {}, settings, None)
    held = np.ones((B, problem.n)) if samples is None else np.asarray(samples, np.float64)
    if held.ndim == 1:
        held = np.broadcast_to(held, (B, held.shape[0]))
    if held.shape != (B, problem.n):
        raise FricjaxError(
            f"{where(src, 'samples')}: shape {held.shape}, expected ({problem.n},) or "
            f"({B}, {problem.n})"
        )
    P, S = len(spec.names), setup.seg.S
    spec_free = setup.free[:P]
    x0s = np.repeat(setup.x0[None], B, axis=0)
    x0s[:, :P][:, spec_free] = np.clip(x0, spec.lower, spec.upper)
    keep = np.repeat(setup.free[None], B, axis=0)
    keep[:, :P][:, spec_free] = mask
    directions = _directions(keep[:, :P], n_directions, src)
    if states is not None:
        xi, nu = (np.asarray(a, dtype=np.float64) for a in states)
        if xi.shape[-1:] != (S,) or nu.shape[-1:] != (S,) or xi.ndim > 2 or nu.ndim > 2:
            raise FricjaxError(
                f"output error: {xi.shape[-1] if xi.ndim else 0} segment states given for "
                f"{S} segments"
            )
        xi, nu = np.broadcast_to(xi, (B, S)), np.broadcast_to(nu, (B, S))
        lo_s, hi_s = setup.lower[P:], setup.upper[P:]
        x0s[:, P:] = np.clip(np.concatenate([xi, nu], axis=1), lo_s, hi_s)
    # A pinned component never moves, but the box transform of the LM needs lower < upper
    # there: any finite interval around its value will do.
    lower = np.where(keep, setup.lower, x0s - 1.0)
    upper = np.where(keep, setup.upper, x0s + 1.0)
    tied = setup.residual.weight
    # from the record's states the segments are first fitted free of each other (module
    # docstring, "Tying the segments"); a start from an earlier fit's states is tied already
    weights = jnp.stack([jnp.zeros_like(tied) if states is None else tied, tied])
    out, r_opt, jac = _fit_rows_jit(
        setup.residual,
        x0s,
        keep,
        directions,
        lower,
        upper,
        held,
        weights,
        checked_refine_settings(settings.refine_settings()),
        settings.gain_tol,
        jnp.asarray(accelerate),
    )
    out, r_opt, jac = jax.device_get((out, r_opt, jac))
    return [
        _row_fit(problem, setup, keep[b], lower[b], upper[b], out, b, r_opt[b], jac[b])
        for b in range(B)
    ]


def _directions(
    keep: Bool[np.ndarray, "B P"], n_directions: int | None, source: object
) -> Float[np.ndarray, "B K P"]:
    """Row b: the unit vectors of the parameters with ``keep[b]`` set, in order, then zero
    rows up to K (default: the largest count over the rows)."""
    B, P = keep.shape
    counts = keep.sum(axis=1)
    need = int(counts.max())
    K = need if n_directions is None else n_directions
    if isinstance(K, bool) or not isinstance(K, int | np.integer) or not need <= K <= P:
        raise FricjaxError(
            f"{where(source, 'n_directions')}: must be an integer from {need} (the most "
            f"parameters a row fits) to {P} (every parameter), got {n_directions!r}"
        )
    directions = np.zeros((B, int(K), P))
    for b in range(B):
        idx = np.flatnonzero(keep[b])
        directions[b, np.arange(idx.size), idx] = 1.0
    return directions


def _row_fit(
    problem: Problem,
    setup: OutputErrorSetup,
    keep: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    out: Refined,
    b: int,
    r: np.ndarray,
    jac: np.ndarray,
) -> OutputErrorFit:
    """Row ``b`` of the batched program as an :class:`OutputErrorFit`; the uncertainty is
    that of the row's fitted components of θ_aug (parameters and states), from r and J at
    its end point."""
    spec, seg, res = problem.spec, setup.seg, setup.residual
    P, S, n = len(spec.names), seg.S, problem.n
    x_aug = np.asarray(out.x[b], dtype=np.float64)
    idx = np.flatnonzero(keep)
    names = [setup.names[i] for i in idx]
    unc = uncertainty_at(r, jac[:, idx], x_aug[idx], lower[idx], upper[idx], names=names)
    d = int(np.count_nonzero(keep[:P]))
    # x_sim and the defects from the residual: r = (x_sim − x)/σ_x, c^x = w√L·Δx/σ_x,
    # c^v = w√L·Δv·T/σ_x.
    sx, wt = float(res.x_scale), float(res.weight)
    rec_x = np.asarray(problem.x)
    x_sim = rec_x + sx * r[:n]
    dx = r[n : n + S - 1] * sx / wt
    dv = r[n + S - 1 :] * sx / (wt * seg.duration)
    return OutputErrorFit(
        params={name: float(x_aug[i]) for i, name in enumerate(spec.names)},
        names=names[:d],
        value=x_aug[idx[:d]],
        std=np.asarray(unc.std[:d]),
        rel_std=np.asarray(unc.rel_std[:d]),
        corr=np.asarray(unc.corr[:d, :d]),
        flags=[list(f) for f in unc.flags[:d]],
        cond=float(unc.cond),
        cost=float(out.cost_after[b]),
        cost_start=float(out.cost_before[b]),
        position_rms=float(np.sqrt(np.mean((x_sim - rec_x) ** 2))),
        x_sim=x_sim,
        x_scale=sx,
        defect_x=float(np.max(np.abs(dx))) if dx.size else 0.0,
        defect_v=float(np.max(np.abs(dv))) if dv.size else 0.0,
        states_x=x_aug[P : P + S],
        states_v=x_aug[P + S : P + 2 * S],
        n_segments=S,
        segment_samples=seg.L,
        segment_of=seg.seg,
        n_residual=n + 2 * int(np.sum(seg.tie)),
        n_steps=int(out.n_steps[b]),
        success=bool(out.success[b]),
    )


def fit_output_error(
    problem: Problem,
    start: Mapping[str, float],
    settings: OutputErrorSettings | None = None,
    states: tuple[np.ndarray, np.ndarray] | None = None,
    n_directions: int | None = None,
) -> OutputErrorFit:
    """Minimise E_OE (module docstring) over θ and the segment states by Levenberg–Marquardt
    (:func:`fricjax.levenberg.levenberg_marquardt`, sine box transform) from ``start``
    (named values, e.g. the equation-error estimate; missing free names take the config's
    init), inside the
    config's box for θ and the state box of the module docstring. The batched program of
    :func:`fit_output_error_batch` with one row: it is compiled once per model, record
    shape and segmentation, whatever the start, the data and the fixed values.

    Args:
        problem: the preprocessed recording and model (x, the preprocessed v for the state
            starts, u for a measured-input model; the config's trim already applied).
        start: named parameter values.
        settings: :class:`OutputErrorSettings`.
        states: segment states (ξ [S] m, ν [S] m/s) to start from, e.g. those of an
            earlier fit of the same record (``states_x``, ``states_v``); default: the
            record's.
        n_directions: K tangent directions of the Jacobian (:func:`fit_output_error_batch`);
            default: the spec's free parameter count.
    """
    spec = problem.spec
    known = {k: float(v) for k, v in start.items() if k in spec}
    starts = spec.flatten(known)[None]
    return fit_output_error_batch(problem, starts, None, settings, states, n_directions)[0]
