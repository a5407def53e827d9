"""Local least-squares polish of search end points, and what the data say about the result.

Generic over a residual function ``residual_fn(theta: Float[Array, "d"]) -> Float[Array, "n"]``
(for the friction model: the force residual m·a − F(θ) at every sample, newtons); the cost
is the sum of squared residuals, eq. (11) of the seed paper,

    E(θ) = Σ_k r_k(θ)²                                                     [N²]

Three tools:

* :func:`refine` / :func:`refine_many` — Levenberg–Marquardt (``optimistix``) from one or
  K starting points inside the box ``lower ≤ θ ≤ upper``. The box is kept by a smooth
  change of variables θ = a + (b − a)·(1 + sin z)/2 (default) or a + (b − a)·sigmoid(z);
  LM works on z, unconstrained.
* :func:`uncertainty` — covariance at an optimum: Gauss–Newton σ²(JᵀJ)⁻¹ for a white
  residual, or the sandwich (JᵀJ)⁺ JᵀΣJ (JᵀJ)⁺ when the residual's noise covariance Σ is
  known (:class:`ResidualNoise`); correlations, condition number and plain-word flags for
  parameters the data do not pin down.
* :func:`cluster_minima` — census of distinct end points, so that a user sees when two
  different parameter sets fit equally well.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from fricjax.errors import FricjaxError, where
from fricjax.programs import stored
from fricjax.search.fast_compile import FAST_COMPILE

ResidualFn = Callable[[Float[Array, " d"]], Float[Array, " n"]]

_TRANSFORMS = ("sine", "sigmoid", "none")


# --------------------------------------------------------------------------------------
# Settings and results
# --------------------------------------------------------------------------------------


class RefineSettings(NamedTuple):
    """Settings of the Levenberg–Marquardt polish.

    rtol, atol: relative / absolute tolerances of LM's Cauchy termination, applied to both
        the step in the optimisation variable and the change of the residual vector.
    max_steps: LM iterations at most; hitting it gives ``success = False``.
    transform: how θ is kept inside [a, b]:
        ``"sine"`` (default; the MINUIT transform) θ = a + (b − a)·(1 + sin z)/2 reaches a
        bound at finite z, where the cost is quadratic in z, so an optimum on a bound is
        reached in a few tens of LM steps (it lands exactly on the bound);
        ``"sigmoid"`` θ = a + (b − a)·sigmoid(z) reaches a bound only as z → ∓∞: the
        Jacobian column shrinks like the distance to the bound and LM's damping slows the
        approach to ~1/steps (measured: 1e-5 of the range after 200 steps, 1000 steps to
        converge), so an optimum on a bound ends slightly inside with ``success = False``;
        ``"none"`` runs LM on θ itself and clips the end point to the box afterwards (use it
        only when the optimum is known to be interior: clipping is not a constrained solve).
    eps_bound: a start on a bound is moved the fraction ``eps_bound`` of the range inside
        it, because the transform's slope vanishes on the bound (sine: slope ≈ √eps_bound,
        sigmoid: ≈ eps_bound there) and LM could not leave it otherwise.
    """

    rtol: float = 1e-10
    atol: float = 1e-10
    max_steps: int = 200
    transform: Literal["sine", "sigmoid", "none"] = "sine"
    eps_bound: float = 1e-6

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], source: object = None) -> RefineSettings:
        """Build settings from a config table, refusing unknown keys and bad values.

        ``source`` names the file (or table) in error messages.
        """
        if not isinstance(d, Mapping):
            raise FricjaxError(f"{where(source)}: expected a table of refine settings")
        unknown = sorted(set(d) - set(cls._fields))
        if unknown:
            raise FricjaxError(
                f"{where(source, unknown[0])}: unknown key; expected one of "
                f"{', '.join(cls._fields)}"
            )
        out: dict[str, Any] = {}
        for key in ("rtol", "atol"):
            if key in d:
                out[key] = _positive_float(d[key], source, key)
        if "max_steps" in d:
            v = d["max_steps"]
            if isinstance(v, bool) or not isinstance(v, int | np.integer) or v < 1:
                raise FricjaxError(
                    f"{where(source, 'max_steps')}: must be an integer ≥ 1, got {v!r}"
                )
            out["max_steps"] = int(v)
        if "transform" in d:
            v = d["transform"]
            if v not in _TRANSFORMS:
                raise FricjaxError(
                    f"{where(source, 'transform')}: must be one of {', '.join(_TRANSFORMS)}, "
                    f"got {v!r}"
                )
            out["transform"] = str(v)
        if "eps_bound" in d:
            v = _positive_float(d["eps_bound"], source, "eps_bound")
            if not v < 0.5:
                raise FricjaxError(f"{where(source, 'eps_bound')}: must be < 0.5, got {v!r}")
            out["eps_bound"] = v
        return cls(**out)


_DEFAULT_SETTINGS = RefineSettings()


def _positive_float(v: object, source: object, key: str) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float | np.integer | np.floating):
        raise FricjaxError(f"{where(source, key)}: must be a number, got {v!r}")
    f = float(v)
    if not (math.isfinite(f) and f > 0.0):
        raise FricjaxError(f"{where(source, key)}: must be a finite number > 0, got {v!r}")
    return f


class Refined(NamedTuple):
    """Result of :func:`refine` (shapes shown) or :func:`refine_many` (leading axis K added).

    x: [d] refined parameters, inside [lower, upper]; never worse than the start.
    cost_before: [] E(x0), eq. (11), residual units squared.
    cost_after: [] E(x) ≤ cost_before.
    n_steps: [] LM iterations taken.
    success: [] LM converged within max_steps to a finite point no worse than x0. When
        False, ``x`` is still the better of x0 and LM's end point.
    """

    x: Float[Array, " d"]
    cost_before: Float[Array, ""]
    cost_after: Float[Array, ""]
    n_steps: Int[Array, ""]
    success: Bool[Array, ""]


# --------------------------------------------------------------------------------------
# Levenberg–Marquardt in the box
# --------------------------------------------------------------------------------------


def to_box(
    z: Float[Array, " d"], lower: Float[Array, " d"], upper: Float[Array, " d"], transform: str
) -> Float[Array, " d"]:
    if transform == "sine":
        return lower + (upper - lower) * (0.5 + 0.5 * jnp.sin(z))
    if transform == "sigmoid":
        return lower + (upper - lower) * jax.nn.sigmoid(z)
    return z


def from_box(
    x: Float[Array, " d"],
    lower: Float[Array, " d"],
    upper: Float[Array, " d"],
    transform: str,
    eps: float,
) -> Float[Array, " d"]:
    if transform == "none":
        return x
    u = jnp.clip((x - lower) / (upper - lower), eps, 1.0 - eps)
    if transform == "sine":
        return jnp.arcsin(2.0 * u - 1.0)
    return jnp.log(u) - jnp.log1p(-u)


def _residual(residual_fn: ResidualFn, x: Float[Array, " d"]) -> Float[Array, " n"]:
    r = residual_fn(x)
    if jnp.ndim(r) != 1:
        raise FricjaxError(
            f"{where('refine', 'residual_fn')}: must return a 1-D residual vector, "
            f"got shape {jnp.shape(r)}"
        )
    return r


def _cost(residual_fn: ResidualFn, x: Float[Array, " d"]) -> Float[Array, ""]:
    r = _residual(residual_fn, x)
    return jnp.sum(r * r)


def _refine_one(
    residual_fn: ResidualFn,
    x0: Float[Array, " d"],
    lower: Float[Array, " d"],
    upper: Float[Array, " d"],
    settings: RefineSettings,
) -> Refined:
    t = settings.transform

    def fn(z: Float[Array, " d"], args: None) -> Float[Array, " n"]:
        return _residual(residual_fn, to_box(z, lower, upper, t))

    z0 = from_box(x0, lower, upper, t, settings.eps_bound)
    solver = optx.LevenbergMarquardt(rtol=settings.rtol, atol=settings.atol)
    sol = optx.least_squares(fn, solver, z0, max_steps=settings.max_steps, throw=False)
    x_new = to_box(sol.value, lower, upper, t)
    if t == "none":
        x_new = jnp.clip(x_new, lower, upper)
    # both costs at one call site of the residual: it compiles once, not twice
    cost_before, cost_new = jax.vmap(lambda x: _cost(residual_fn, x))(jnp.stack([x0, x_new]))
    # A non-finite or worse end point (LM failure, or the transform's round trip of a start
    # on a bound) must not replace a start the search already scored.
    better = (
        jnp.isfinite(cost_new)
        & jnp.all(jnp.isfinite(x_new))
        & ((cost_new <= cost_before) | ~jnp.isfinite(cost_before))
    )
    x = jnp.where(better, x_new, x0)
    cost_after = jnp.where(better, cost_new, cost_before)
    converged = sol.result == optx.RESULTS.successful
    return Refined(
        x=x,
        cost_before=cost_before,
        cost_after=cost_after,
        n_steps=jnp.asarray(sol.stats["num_steps"]),
        success=converged & better,
    )


def refine_batch(
    residual_fn: ResidualFn,
    x0s: Float[Array, "K d"],
    lower: Float[Array, " d"],
    upper: Float[Array, " d"],
    settings: RefineSettings,
) -> Refined:
    return jax.vmap(lambda x0: _refine_one(residual_fn, x0, lower, upper, settings))(x0s)


# filter_jit treats the residual function and the (hashable) settings as static and any
# array leaves of the residual function (an eqx.Module / jax.tree_util.Partial holding the
# data) as traced, so repeated calls with the same function object or new data of the same
# shape reuse one compilation.
_refine_one_jit = stored(_refine_one)
_refine_batch_jit = stored(refine_batch)
# For a polish that runs once per process (a cold CLI run), where compiling the LM loop
# costs seconds and running it tens of milliseconds (fricjax.search.fast_compile).
_refine_one_fast = stored(_refine_one, compiler_options=FAST_COMPILE)
_refine_batch_fast = stored(refine_batch, compiler_options=FAST_COMPILE)


def _check_box(
    x0: Any, lower: Any, upper: Any, batched: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    lo = np.asarray(lower, dtype=np.float64)
    hi = np.asarray(upper, dtype=np.float64)
    x = np.asarray(x0, dtype=np.float64)
    if lo.ndim != 1 or hi.shape != lo.shape:
        raise FricjaxError(
            f"{where('refine', 'lower/upper')}: must be 1-D and of equal shape, got "
            f"{lo.shape} and {hi.shape}"
        )
    bad = np.flatnonzero(~(np.isfinite(lo) & np.isfinite(hi) & (lo < hi)))
    if bad.size:
        i = int(bad[0])
        raise FricjaxError(
            f"{where('refine', 'lower/upper')}: need finite lower < upper, "
            f"index {i} has [{lo[i]}, {hi[i]}]"
        )
    want = ("K", lo.shape[0]) if batched else (lo.shape[0],)
    if x.ndim != len(want) or x.shape[-1] != lo.shape[0]:
        raise FricjaxError(
            f"{where('refine', 'x0s' if batched else 'x0')}: shape {x.shape} does not match "
            f"{want} (bounds have d = {lo.shape[0]})"
        )
    outside = ~(np.isfinite(x) & (x >= lo) & (x <= hi))
    if outside.any():
        idx = np.argwhere(outside)[0]
        j = int(idx[-1])
        raise FricjaxError(
            f"{where('refine', 'x0s' if batched else 'x0')}: value {x[tuple(idx)]} at index "
            f"{tuple(int(i) for i in idx) if batched else j} is not inside [{lo[j]}, {hi[j]}]"
        )
    return x, lo, hi


def checked_refine_settings(settings: RefineSettings) -> RefineSettings:
    # Re-validated and rebuilt from Python scalars: filter_jit would trace array-valued
    # settings, and max_steps / transform must be static.
    if not isinstance(settings, RefineSettings):
        raise FricjaxError(
            f"{where('refine', 'settings')}: expected RefineSettings, got {type(settings).__name__}"
        )
    return RefineSettings.from_dict(
        {
            k: v.item() if isinstance(v, np.generic | np.ndarray) else v
            for k, v in settings._asdict().items()
        },
        "refine: settings",
    )


def refine(
    residual_fn: ResidualFn,
    x0: Float[Array, " d"],
    lower: Float[Array, " d"],
    upper: Float[Array, " d"],
    settings: RefineSettings = _DEFAULT_SETTINGS,
    *,
    fast_compile: bool = False,
    program: Callable[..., Refined] | None = None,
) -> Refined:
    """Levenberg–Marquardt polish of one point inside the box [lower, upper].

    Minimises E(θ) = Σ r(θ)², eq. (11), over z with θ = a + (b − a)·(1 + sin z)/2
    (``transform = "sine"``; ``"sigmoid"``: θ = a + (b − a)·sigmoid(z)), starting from
    z0 = arcsin(2u0 − 1) (or logit u0), u0 = clip((x0 − a)/(b − a), ε, 1 − ε). Never returns
    a point worse than ``x0``: ``cost_after ≤ cost_before`` always.

    Args:
        residual_fn: θ [d] → r [n], pure and jax-traceable. Pass the same function object
            (or an equinox Module / ``jax.tree_util.Partial`` carrying the data as array
            leaves) to reuse the compilation; a new lambda per call recompiles.
        x0: [d] start, inside [lower, upper] (a bound itself is allowed).
        lower, upper: [d] box, finite, lower < upper.
        settings: :class:`RefineSettings`.
        fast_compile: compile with :data:`fricjax.search.fast_compile.FAST_COMPILE`: on
            the paper twin (26 parameters, 200 LM steps, 2 CPU cores) ~0.75 s to compile
            instead of ~3.2 s, ~145 ms to run instead of ~45 ms (measured). For a polish
            compiled once and run once; a program reused many times is better optimised.
        program: the compiled program from :func:`compile_refine` for these arguments'
            shapes and settings (``fast_compile`` is then the one it was compiled with).

    Returns:
        :class:`Refined` of jax arrays (x [d], scalars).
    """
    x, lo, hi = _check_box(x0, lower, upper, batched=False)
    settings = checked_refine_settings(settings)
    # numpy arguments: the call transfers them (jnp.asarray would compile a copy per shape)
    run = program or (_refine_one_fast if fast_compile else _refine_one_jit)
    return run(residual_fn, x, lo, hi, settings)


def compile_refine(
    residual_fn: ResidualFn,
    x0: Float[Array, " d"],
    lower: Float[Array, " d"],
    upper: Float[Array, " d"],
    settings: RefineSettings = _DEFAULT_SETTINGS,
    *,
    fast_compile: bool = False,
) -> Callable[..., Refined]:
    """:func:`refine`'s program compiled ahead of time, for ``program=`` of :func:`refine`
    (same arguments; ``x0`` only gives the shape). Tracing and XLA compilation happen
    here, so a caller can run them in a thread while it does other work: XLA compiles
    without Python's lock, on the second core (a cold ``fricjax identify`` overlaps the
    polish's compilation with the search's)."""
    x, lo, hi = _check_box(x0, lower, upper, batched=False)
    settings = checked_refine_settings(settings)
    jitted = _refine_one_fast if fast_compile else _refine_one_jit
    return jitted.compiled(residual_fn, x, lo, hi, settings)


def refine_many(
    residual_fn: ResidualFn,
    x0s: Float[Array, "K d"],
    lower: Float[Array, " d"],
    upper: Float[Array, " d"],
    settings: RefineSettings = _DEFAULT_SETTINGS,
    *,
    fast_compile: bool = False,
) -> Refined:
    """:func:`refine` vmapped over K starting points (e.g. the best K chain end points).

    Each start is polished independently (same result as :func:`refine` one by one, up to
    floating-point reassociation); the batch runs until its slowest member stops.
    ``fast_compile``: as for :func:`refine`.

    Returns:
        :class:`Refined` with a leading axis K on every field (x [K, d], others [K]).
    """
    x, lo, hi = _check_box(x0s, lower, upper, batched=True)
    settings = checked_refine_settings(settings)
    run = _refine_batch_fast if fast_compile else _refine_batch_jit
    return run(residual_fn, x, lo, hi, settings)


# --------------------------------------------------------------------------------------
# Uncertainty and identifiability
# --------------------------------------------------------------------------------------


class ResidualNoise(NamedTuple):
    """What the residual's noise ``δr`` [n] (covariance Σ [n, n]) does to a least-squares fit
    with Jacobian J [n, d], in the residual's units squared.

    jsj: [d, d] ``JᵀΣJ``, the covariance of the gradient's noise ``Jᵀδr``.
    trace: ``tr Σ = E‖δr‖²``.
    trace_sq: ``tr Σ²`` (for Gaussian noise ``Var‖δr‖² = 2 tr Σ²``).
    label: one line naming the noise source, for the result (e.g. "x noise 2e-06 m, white").
    """

    jsj: np.ndarray
    trace: float
    trace_sq: float
    label: str


#: :attr:`Uncertainty.method` of the two covariances.
SANDWICH = "sandwich"
SANDWICH_EXCESS = "sandwich + white excess"
GAUSS_NEWTON = "gauss-newton"
#: The residual holds more than the noise when E(x) exceeds E[E | noise only] by more than
#: this many of its noise-only standard deviations √(2 tr Σ²) (2: one fit in 44 of pure
#: noise counts its chance excess, which then adds a small white part).
EXCESS_SIGMAS = 2.0


class Uncertainty(NamedTuple):
    """Uncertainty of a least-squares optimum (numpy / Python values).

    std: [d] standard deviations √diag(C), units of the parameters, C the sandwich or the
        Gauss–Newton covariance (``method``, :func:`uncertainty_at`); ``inf
        for a parameter with a component along a direction the data do not determine
        (JᵀJ singular there).
    rel_std: [d] std / |x| (``inf`` where x = 0 and std > 0).
    corr: [d, d] correlation matrix of C. Along undetermined directions it is the limit of
        the correlation as their curvature goes to 0 (so two duplicated parameters show
        ρ = −1); between a determined and an undetermined parameter it is 0.
    sigma2: residual variance σ² = E(x)/(n − d), residual units squared.
    on_bound: [d] x within ``rel_tol_bound·(b − a)`` of a bound (the covariance assumes an
        interior optimum and is not valid for these).
    flags: per parameter, plain-word reasons for distrust (empty list = none).
    cond: condition number of the column-scaled JᵀJ (``inf`` if singular to working
        precision, i.e. a singular value of J_s below 1e-10 of the largest).
    names: [d] parameter names used in the flags.
    method: ``"sandwich"`` (the residual noise's covariance was known), ``"sandwich + white
        excess"`` (and the residual held significantly more than that noise) or
        ``"gauss-newton"`` (white residual assumed).
    dispersion: sandwich only, ``φ = E(x) / E[E(x) | noise only]`` (≈ 1 when the residual
        is the noise); nan for Gauss–Newton.
    noise: sandwich only, :attr:`ResidualNoise.label`; "" for Gauss–Newton.
    """

    std: np.ndarray
    rel_std: np.ndarray
    corr: np.ndarray
    sigma2: float
    on_bound: np.ndarray
    flags: list[list[str]]
    cond: float
    names: list[str]
    method: str = GAUSS_NEWTON
    dispersion: float = math.nan
    noise: str = ""


# A singular value of the column-scaled Jacobian below this fraction of the largest is a
# direction the data do not determine (cond(JᵀJ) > 1e20 cannot be resolved in float64).
_SV_RCOND = 1e-10
# Components of such a direction smaller than this are SVD round-off, not participation.
_NULL_COMPONENT = 1e-6


def uncertainty(
    residual_fn: ResidualFn,
    x: Float[Array, " d"],
    lower: Float[Array, " d"],
    upper: Float[Array, " d"],
    *,
    names: Sequence[str] | None = None,
    rel_tol_bound: float = 1e-6,
    rel_std_limit: float = 1.0,
    corr_limit: float = 0.99,
) -> Uncertainty:
    """Gauss–Newton covariance, correlations and identifiability flags at an optimum x.

    With J = ∂r/∂θ [n, d] (forward-mode) and σ² = E(x)/(n − d), eq. (11) for E:

        C = σ² (JᵀJ)⁻¹ = σ² D⁻¹ (J_sᵀ J_s)⁻¹ D⁻¹,   J_s = J D⁻¹,  D = diag(‖J_:,j‖)

    computed from the SVD of the column-scaled J_s = U S Vᵀ: C = σ² D⁻¹ V S⁻² Vᵀ D⁻¹ over the
    singular values above 1e-10·S_max; parameters with a component > 1e-6 along a dropped
    direction get std = inf. cond = (S_max / S_min)².

    Flags (per parameter): "not determined (...)", "weakly determined (rel. σ = 1.3 > 1)",
    "correlated with NAME (ρ = 0.995)" for |ρ| > ``corr_limit``, "on bound (lower|upper)".

    Args:
        residual_fn: θ [d] → r [n]; requires n > d.
        x: [d] the optimum (e.g. ``refine(...).x``).
        lower, upper: [d] the box (for the on-bound test).
        names: d parameter names for the flags (default p0, p1, ...).
        rel_tol_bound: on-bound tolerance as a fraction of the range b − a.
        rel_std_limit: flag "weakly determined" when std/|x| exceeds it.
        corr_limit: flag "correlated" when |ρ| exceeds it.
    """
    xv, lo, hi, names = _uncertainty_args(x, lower, upper, names)
    xj = jnp.asarray(xv)
    r = np.asarray(residual_fn(xj), dtype=np.float64)
    _check_residual(r, xv.shape[0])
    jac = np.asarray(jax.jacfwd(residual_fn)(xj), dtype=np.float64)
    return uncertainty_at(
        r,
        jac,
        xv,
        lo,
        hi,
        names=names,
        rel_tol_bound=rel_tol_bound,
        rel_std_limit=rel_std_limit,
        corr_limit=corr_limit,
    )


def _uncertainty_args(
    x: Any, lower: Any, upper: Any, names: Sequence[str] | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[str]]:
    xv = np.asarray(x, dtype=np.float64)
    lo = np.asarray(lower, dtype=np.float64)
    hi = np.asarray(upper, dtype=np.float64)
    if xv.ndim != 1 or lo.shape != xv.shape or hi.shape != xv.shape:
        raise FricjaxError(
            f"{where('uncertainty', 'x/lower/upper')}: must be 1-D of equal shape, got "
            f"{xv.shape}, {lo.shape}, {hi.shape}"
        )
    d = xv.shape[0]
    if names is None:
        names = [f"p{j}" for j in range(d)]
    names = [str(s) for s in names]
    if len(names) != d:
        raise FricjaxError(
            f"{where('uncertainty', 'names')}: {len(names)} names for {d} parameters"
        )
    return xv, lo, hi, names


def _check_residual(r: np.ndarray, d: int) -> None:
    if r.ndim != 1:
        raise FricjaxError(
            f"{where('uncertainty', 'residual_fn')}: must return a 1-D residual vector, "
            f"got shape {r.shape}"
        )
    if r.shape[0] <= d:
        raise FricjaxError(
            f"{where('uncertainty', 'residual_fn')}: {r.shape[0]} residuals for {d} "
            f"parameters; σ² = E/(n − d) needs n > d"
        )


def _value_and_jacobian_program(
    residual_fn: ResidualFn, x: Float[Array, " d"]
) -> tuple[Float[Array, " n"], Float[Array, "n d"]]:
    return residual_fn(x), jax.jacfwd(residual_fn)(x)


_value_and_jacobian = stored(_value_and_jacobian_program)
_value_and_jacobian_fast = stored(_value_and_jacobian_program, compiler_options=FAST_COMPILE)


def value_and_jacobian(
    residual_fn: ResidualFn, x: Float[Array, " d"], *, fast_compile: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """``r(x) [n]`` and ``J = ∂r/∂θ (x) [n, d]`` (forward mode) as ONE compiled program
    (numpy results), the inputs of :func:`uncertainty_at`.

    Compiled once per residual function (an equinox Module or ``jax.tree_util.Partial``
    carrying its data as array leaves is reused for new data of the same shape; a new
    lambda per call recompiles, where :func:`uncertainty` would not). ``fast_compile``:
    as for :func:`refine`.
    """
    run = _value_and_jacobian_fast if fast_compile else _value_and_jacobian
    r, jac = run(residual_fn, np.asarray(x, dtype=np.float64))
    return np.asarray(r, dtype=np.float64), np.asarray(jac, dtype=np.float64)


def covariance(std: Float[np.ndarray, " k"], corr: Float[np.ndarray, "k k"]) -> np.ndarray:
    """[k, k] covariance (units of the parameters²) from σ and the correlation matrix; a
    parameter the record does not determine (σ = inf or NaN) keeps an inf variance and no
    covariance with the others."""
    std = np.asarray(std, dtype=np.float64)
    finite = np.isfinite(std)
    s = np.where(finite, std, 0.0)
    rho = np.where(np.isfinite(corr), np.asarray(corr, dtype=np.float64), 0.0)
    cov = rho * np.outer(s, s)
    cov[np.diag_indices_from(cov)] = np.where(finite, std**2, np.inf)
    return cov


def uncertainty_at(
    r: Float[Array, " n"],
    jac: Float[Array, "n d"],
    x: Float[Array, " d"],
    lower: Float[Array, " d"],
    upper: Float[Array, " d"],
    *,
    names: Sequence[str] | None = None,
    rel_tol_bound: float = 1e-6,
    rel_std_limit: float = 1.0,
    corr_limit: float = 0.99,
    noise: ResidualNoise | None = None,
) -> Uncertainty:
    """:func:`uncertainty` from the residual ``r [n]`` and its Jacobian ``jac [n, d]`` at
    ``x`` (e.g. from :func:`value_and_jacobian`); same equations, flags and arguments.

    With ``noise`` (the residual's noise covariance Σ through ``JᵀΣJ``, ``tr Σ``, ``tr Σ²``)
    the covariance is the least-squares estimator's own (the sandwich) instead of
    σ²(JᵀJ)⁻¹, which holds only for a white residual:

        C = A⁺ (JᵀΣJ) A⁺ + s_e²·A⁺,   A = JᵀJ,
        E_0 = E[E | noise only] = tr Σ − tr(A⁺ JᵀΣJ),   φ = E(x) / E_0,
        s_e² = (E(x) − E_0)/(n − d)  if  E(x) − E_0 > 2·√(2 tr Σ²),  else 0

    (E_0 the expected residual sum of squares of the linearised fit, tr((I − J A⁺ Jᵀ)Σ),
    units of r²). A residual significantly above its noise (φ > 1, a model that misses
    physics) holds an excess that the noise's covariance does not describe; it is counted
    as white, Gauss–Newton's assumption, so σ is never smaller than the data support and
    becomes Gauss–Newton's when the excess dominates. Why not scale Σ by φ
    (quasi-likelihood): that gives the excess the noise's colour, twice differentiated and
    nearly empty at the motion's frequencies, where a model error lives; on the EMPS
    recording (φ = 1.6e4) it gave σ 7-11× below the published IDIM-LS σ (measured).
    A⁺ is the same pseudo-inverse over the determined directions as Gauss–Newton's."""
    xv, lo, hi, names = _uncertainty_args(x, lower, upper, names)
    d = xv.shape[0]
    r = np.asarray(r, dtype=np.float64)
    _check_residual(r, d)
    n = r.shape[0]
    jac = np.asarray(jac, dtype=np.float64)
    if jac.shape != (n, d):
        raise FricjaxError(f"{where('uncertainty', 'jac')}: shape {jac.shape}, expected ({n}, {d})")
    cost = float(r @ r)
    sigma2 = cost / (n - d)

    scale = np.linalg.norm(jac, axis=0)
    # A parameter with no effect keeps a zero column: it becomes a null direction below.
    scale_safe = np.where(scale > 0.0, scale, 1.0)
    _, s, vt = np.linalg.svd(jac / scale_safe, full_matrices=False)
    keep = s > _SV_RCOND * s[0] if s[0] > 0.0 else np.zeros_like(s, dtype=bool)
    # Dropped directions are singular to working precision: their S is round-off.
    cond = float((s[0] / s[-1]) ** 2) if keep.all() else math.inf

    v_keep = vt[keep].T  # [d, k]
    cov_s = (v_keep / s[keep] ** 2) @ v_keep.T
    a_pinv = cov_s / np.outer(scale_safe, scale_safe)
    method = GAUSS_NEWTON
    if noise is None:
        cov, dispersion = sigma2 * a_pinv, math.nan
    else:
        jsj = np.asarray(noise.jsj, dtype=np.float64)
        if jsj.shape != (d, d):
            raise FricjaxError(
                f"{where('uncertainty', 'noise')}: JᵀΣJ has shape {jsj.shape}, expected ({d}, {d})"
            )
        cov, method = a_pinv @ jsj @ a_pinv, SANDWICH
        expected = float(noise.trace) - float(np.sum(a_pinv * jsj))
        dispersion = cost / expected if expected > 0.0 else math.inf
        excess = cost - max(expected, 0.0)
        if excess > EXCESS_SIGMAS * math.sqrt(2.0 * float(noise.trace_sq)):
            cov, method = cov + excess / (n - d) * a_pinv, SANDWICH_EXCESS
    v_null = vt[~keep].T  # [d, d - k]
    undetermined = np.any(np.abs(v_null) > _NULL_COMPONENT, axis=1)

    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    std = np.where(undetermined, np.inf, std)
    corr = _correlation(cov, v_null, undetermined)

    absx = np.abs(xv)
    with np.errstate(divide="ignore", invalid="ignore"):
        rel_std = np.where(absx > 0.0, std / np.where(absx > 0.0, absx, 1.0), np.inf)
    rel_std = np.where((absx == 0.0) & (std == 0.0), 0.0, rel_std)

    tol = rel_tol_bound * (hi - lo)
    at_lower = xv <= lo + tol
    at_upper = xv >= hi - tol
    on_bound = at_lower | at_upper

    flags: list[list[str]] = []
    for j in range(d):
        fj: list[str] = []
        if undetermined[j]:
            fj.append("not determined (JᵀJ singular along this parameter)")
        elif rel_std[j] > rel_std_limit:
            fj.append(f"weakly determined (rel. σ = {rel_std[j]:.3g} > {rel_std_limit:g})")
        for k in np.flatnonzero(np.abs(corr[j]) > corr_limit):
            if k != j:
                fj.append(f"correlated with {names[k]} (ρ = {corr[j, k]:.3f})")
        if at_lower[j]:
            fj.append("on bound (lower)")
        elif at_upper[j]:
            fj.append("on bound (upper)")
        flags.append(fj)

    return Uncertainty(
        std=std,
        rel_std=rel_std,
        corr=corr,
        sigma2=float(sigma2),
        on_bound=on_bound,
        flags=flags,
        cond=cond,
        names=names,
        method=method,
        dispersion=float(dispersion),
        noise="" if noise is None else noise.label,
    )


def _correlation(cov: np.ndarray, v_null: np.ndarray, undetermined: np.ndarray) -> np.ndarray:
    """Correlation of C; along null directions the limit Σ_k v_kj v_kl as curvature → 0."""
    d = cov.shape[0]
    corr = np.zeros((d, d))
    det = ~undetermined
    sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    idx = np.flatnonzero(det)
    if idx.size:
        denom = np.outer(sd[idx], sd[idx])
        with np.errstate(divide="ignore", invalid="ignore"):
            block = np.where(denom > 0.0, cov[np.ix_(idx, idx)] / denom, 0.0)
        corr[np.ix_(idx, idx)] = block
    und = np.flatnonzero(undetermined)
    if und.size:
        g = v_null[und] @ v_null[und].T
        dg = np.sqrt(np.diag(g))
        corr[np.ix_(und, und)] = g / np.outer(dg, dg)
    np.fill_diagonal(corr, 1.0)
    return np.clip(corr, -1.0, 1.0)


# --------------------------------------------------------------------------------------
# Census of minima
# --------------------------------------------------------------------------------------


class Minimum(NamedTuple):
    """One distinct end point of the search chains.

    x: [d] representative (the member of lowest cost).
    cost: its cost E, eq. (11).
    count: number of end points in the cluster.
    members: indices into the input, in increasing cost.
    """

    x: np.ndarray
    cost: float
    count: int
    members: np.ndarray


def cluster_minima(
    xs: Float[Array, "C d"],
    costs: Float[Array, " C"],
    lower: Float[Array, " d"],
    upper: Float[Array, " d"],
    *,
    tol: float = 0.02,
) -> list[Minimum]:
    """Group chain end points into distinct minima (greedy, by cost).

    Points are mapped to the unit box u = (x − a)/(b − a) and visited in increasing cost; a
    point joins the first existing cluster whose representative is within ``tol`` in the
    max-norm ‖u − u_rep‖_∞ (every parameter within ``tol`` of its range), else it starts a
    new cluster. The max-norm keeps the rule independent of d: two fits differing by 30 % of
    the range in a single parameter are distinct minima however many parameters agree.
    End points with a non-finite cost or position are left out.

    Returns:
        list of :class:`Minimum`, in increasing cost (the first is the best fit).
    """
    xv = np.asarray(xs, dtype=np.float64)
    cv = np.asarray(costs, dtype=np.float64)
    lo = np.asarray(lower, dtype=np.float64)
    hi = np.asarray(upper, dtype=np.float64)
    if xv.ndim != 2 or cv.shape != xv.shape[:1] or lo.shape != xv.shape[1:] or hi.shape != lo.shape:
        raise FricjaxError(
            f"{where('cluster_minima', 'xs/costs/lower/upper')}: expected shapes [C, d], [C], "
            f"[d], [d], got {xv.shape}, {cv.shape}, {lo.shape}, {hi.shape}"
        )
    if not (np.all(hi > lo) and tol > 0.0):
        raise FricjaxError(
            f"{where('cluster_minima', 'lower/upper/tol')}: need lower < upper and tol > 0"
        )
    u = (xv - lo) / (hi - lo)
    ok = np.isfinite(cv) & np.all(np.isfinite(u), axis=1)
    order = [int(i) for i in np.flatnonzero(ok)[np.argsort(cv[ok], kind="stable")]]
    reps: list[int] = []
    members: list[list[int]] = []
    for i in order:
        for c, rep in enumerate(reps):
            if np.max(np.abs(u[i] - u[rep])) <= tol:
                members[c].append(i)
                break
        else:
            reps.append(i)
            members.append([i])
    return [
        Minimum(x=xv[rep].copy(), cost=float(cv[rep]), count=len(m), members=np.asarray(m))
        for rep, m in zip(reps, members, strict=True)
    ]
