"""Variable projection (Golub–Pereyra) for separable models: search the nonlinear
parameters only, solve the linear ones exactly.

For fixed nonlinear parameters ``p_nl`` (ω, vs, δ, ...) the equation-error residual of a
model whose terms all declare a linear basis is linear in the coefficients ``c``
(:mod:`fricjax.model.system`, seed eq. 5/11)::

    r(θ) = m·a − F*(θ) = Ψ(p_nl) · c(θ),        Ψ [n, k] = [a | −Φ_F],   c = [m, c_F]

(for the seed model: ``c_F = [F0, A_1, B_1, …, A_10, B_10, Fc, Fs, Fv]`` with
``A_i = Fp_i cos φ_i``, ``B_i = Fp_i sin φ_i`` — seed eq. 4 as ``A_i sin iωt + B_i cos iωt``;
and Stribeck columns ``sgn v·(1 − e)``, ``sgn v·e``, ``v`` with ``e = exp(−(|v|/vs)^δ)``,
seed eq. 1). The coefficients split into

* *solved* groups — every parameter of the group is free: found by least squares here;
* *known* groups — every parameter fixed (e.g. the mass of the recording, or a fixed
  ``gain``): their contribution ``y`` is a known part of the residual;
* *mixed* groups (some free, some fixed, e.g. ``Fp_3`` fixed and ``φ_3`` free): their free
  parameters are searched with the nonlinear ones and the group is known for given θ_nl.

With ``Ψ_S`` the solved columns and ``y = −Ψ_O c_O`` the rest, the projected cost is

    E_P(θ_nl) = min_{c_S ∈ box} ‖Ψ_S(θ_nl)·c_S − y(θ_nl)‖²                      [N²]

(seed eq. 11 minimised over the linear parameters), a function of the few nonlinear
parameters only (2 for the seed model: ω and vs, δ fixed), which the annealing chains of
:mod:`fricjax.search.chains` minimise instead of the 26-D cost.

Linear solve. ``Ψ_S`` is scaled to unit column norms (``D = diag‖Ψ_S,j‖``, zero columns kept
at scale 1) and the normal equations ``G z = b`` (``G = D⁻¹Ψ_SᵀΨ_S D⁻¹``, ``b = D⁻¹Ψ_Sᵀy``,
``c = D⁻¹z``) are solved by Cholesky with a 1e-13 ridge (scaled units; it only matters for a
zero or duplicated column). The coefficients' relative error is ≲ cond(Ψ_S D⁻¹)²·ε; on the
paper twin cond(Ψ_S D⁻¹) ≤ 1.7e3 over the whole (ω, vs) box (measured), so ≲ 1e-9, and the
cost's excess over the exact minimum is second order in it. Normal equations rather than a
QR of ``Ψ_S``: the Gram matrix is formed once and every active-set pass below is then a
``k × k`` factorisation (24 × 24: ~3 µs), while XLA's CPU QR under ``vmap`` was far slower
than everything else in the cost (measured).

Bounds (the config's box applies to the *original* parameters: ``Fp_i ∈ [a, b]``,
``φ_i ∈ [−π, π]``, ``Fc, Fs, Fv, F0`` in theirs). The choice: a small active-set method on
the *groups*, inside the same jitted function (at most ``passes + 1`` least-squares solves,
a ``while_loop`` that stops once the active set has settled):

1. solve with the fixed groups held (none at first); map the coefficients back to the
   named parameters (``Fp_i = √(A_i² + B_i²)``, ``φ_i = atan2(B_i, A_i)``, the others are
   their own coefficients) and clip each into its box — an amplitude outside ``[a, b]`` is
   moved onto the bound *keeping its phase*, a phase outside a narrower box is clipped
   keeping its amplitude; the clipped point is feasible and its exact cost is computed;
2. if free groups left the box, they are all fixed at their clipped values and the rest
   is re-solved; otherwise the fixed group whose bound holds it back most (its
   Lagrange multiplier ∂E/∂parameter has the wrong sign at its bound, one reverse pass
   through the coefficient map) is released, one per pass (Lawson–Hanson's rule);
3. the result is the best feasible point visited (never worse than the clipped
   unconstrained solution), and ``E_P(θ_nl) = E(full_theta(θ_nl))`` (seed eq. 11) holds
   exactly, bounds active or not.

Limits: with no bound active it is the exact minimum. Otherwise the method is a heuristic
(no step-to-the-boundary interpolation, so no monotonicity guarantee; capped passes): the
default ``passes = 3`` gave the same search results on the paper twin as 12 passes (median
and worst end-point cost over 10 seeds) at half the cost (measured). An amplitude held on
its bound keeps the unconstrained phase (the constrained optimum may have another phase:
the amplitude annulus is not convex), and a phase is clipped without regard to
wrap-around. So ``E_P`` is the cost of a *feasible* point: the box-constrained minimum
whenever the active set is found, an upper bound of it otherwise. Measured on the paper
twin against L-BFGS-B over the 24 linear parameters started from that point: 0.02-0.2 %
above near the optimum (ω within 0.1 rad/s), up to 30 % above far from it (ω = 25 rad/s,
where many amplitudes sit on their lower bounds). The search only needs the landscape
near the basin right; the Levenberg–Marquardt polish of all parameters
(:func:`fricjax.refine.refine` on :meth:`Separable.full_theta`) removes the difference.

Cost (2 CPU cores): ~100-150 µs per evaluation against ~5-8 µs for the 26-D cost at 32-64
chains (which takes sin/cos by angle addition on the recording's time grid,
:func:`fricjax.model.drive.phasor`; the projection passes plain signals, one sine/cosine
pair per sample, a small part of its solve), but the 2-D search needs ~750 evaluations
instead of ~1e5; the solve compiles into every program that evaluates it (XLA inlines
it), so :func:`fricjax.identify.identify` runs the whole search as one program with one
call site of :class:`CostAndTheta` (:func:`fricjax.search.chains.run_chains_fused`, with
the compile-bound options of :mod:`fricjax.search.fast_compile`: ~1 s of compilation), and
the persistent compilation cache of the CLI (:func:`fricjax.api.enable_compilation_cache`)
removes it from later runs.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.linalg import cho_solve
from jaxtyping import Array, Float

from fricjax.errors import FricjaxError, where
from fricjax.model.system import Model
from fricjax.model.term import Signals
from fricjax.params import ParamSpec
from fricjax.problem import Problem

#: Ridge added to the scaled Gram matrix (unit diagonal) so that a zero or duplicated
#: column still factorises (a relative perturbation of 1e-13 elsewhere).
_RIDGE = 1e-13
#: Most active-set passes after the first solve (the loop stops earlier once the active
#: set has settled).
PASSES = 3


@dataclass(frozen=True)
class Layout:
    """Static partition of a problem's parameters (hashable: a jit static argument).

    Structure only — the numbers (box, initial and fixed values) are arrays of the
    :class:`Projection`, so problems that differ only in those share one compilation.
    ``names``/``free``: every parameter in spec order and whether it is free;
    ``nl_index [d_nl]``: positions of the searched parameters in the free vector θ;
    ``solved [k_S]`` / ``other [k_O]``: columns of the residual basis Ψ solved here / known;
    ``coef_group [k_S]``: solved group (0..G−1) of each solved column; ``lin_names``,
    ``lin_index``, ``lin_group`` [L]: the solved parameters, their positions in θ and their
    group; ``passes``: most active-set passes after the first solve.
    """

    model: Model
    names: tuple[str, ...]
    free: tuple[bool, ...]
    nl_index: tuple[int, ...]
    solved: tuple[int, ...]
    other: tuple[int, ...]
    coef_group: tuple[int, ...]
    n_groups: int
    lin_names: tuple[str, ...]
    lin_index: tuple[int, ...]
    lin_group: tuple[int, ...]
    passes: int

    def unflatten(
        self, theta: Float[Array, " d"], fixed: Float[Array, " f"]
    ) -> dict[str, Float[Array, ""]]:
        """``{name: value}`` from the free vector θ [d] and the fixed values [f] (spec order)."""
        out, i, j = {}, 0, 0
        for name, free in zip(self.names, self.free, strict=True):
            if free:
                out[name], i = theta[i], i + 1
            else:
                out[name], j = fixed[j], j + 1
        return out


def layout(model: Model, spec: ParamSpec, *, passes: int = PASSES) -> Layout:
    """Split ``spec`` into searched (nonlinear) and solved (linear) parameters.

    Raises the one-line :class:`FricjaxError` of :meth:`Model.require_basis` when a term
    declares no basis, and one when ``spec`` lacks the moving mass.
    """
    model.require_basis()
    if "mass" not in spec:
        raise FricjaxError(f"{where(spec.source, '[params].mass')}: missing (needed by the fit)")
    if passes < 0:
        raise FricjaxError(f"{where('separable', 'passes')}: must be ≥ 0, got {passes}")
    free_pos = {p.name: i for i, p in enumerate(spec.free)}
    solved_names: set[str] = set()
    solved: list[int] = []
    other: list[int] = []
    coef_group: list[int] = []
    lin_names: list[str] = []
    lin_group: list[int] = []
    col = n_groups = 0
    for group in model.linear_groups():
        cols = list(range(col, col + len(group)))
        col += len(group)
        if all(n in free_pos for n in group):
            solved += cols
            coef_group += [n_groups] * len(cols)
            lin_names += list(group)
            lin_group += [n_groups] * len(group)
            solved_names.update(group)
            n_groups += 1
        else:
            other += cols
    return Layout(
        model=model,
        names=spec.names,
        free=tuple(p.free for p in spec.params),
        nl_index=tuple(i for i, p in enumerate(spec.free) if p.name not in solved_names),
        solved=tuple(solved),
        other=tuple(other),
        coef_group=tuple(coef_group),
        n_groups=n_groups,
        lin_names=tuple(lin_names),
        lin_index=tuple(free_pos[n] for n in lin_names),
        lin_group=tuple(lin_group),
        passes=int(passes),
    )


class Projection(eqx.Module):
    """``θ_nl [d_nl] -> (θ [d], E_P [])``: the variable-projection solve (module docstring).

    An equinox Module: the recording's arrays and the numbers of the parameter spec are
    leaves (traced under jit), the :class:`Layout` is static, so the compiled code is
    shared by every problem of the same model, free/fixed structure and sample count.

    ``base [d]``: θ at the spec's initial values (the solved entries are placeholders);
    ``fixed [f]``: the fixed parameters' values (spec order); ``lower``/``upper`` [L]: the
    solved parameters' box; ``t, x, v, u, a`` [n]: the preprocessed recording.
    """

    layout: Layout = eqx.field(static=True)
    base: Float[Array, " d"]
    fixed: Float[Array, " f"]
    lower: Float[Array, " L"]
    upper: Float[Array, " L"]
    t: Float[Array, " n"]
    x: Float[Array, " n"]
    v: Float[Array, " n"]
    u: Float[Array, " n"]
    a: Float[Array, " n"]

    def solve(self, theta_nl: Float[Array, " d_nl"]) -> tuple[Float[Array, " d"], Float[Array, ""]]:
        """Full free vector θ [d] (inside the box) and its cost E(θ) = E_P(θ_nl) [N²]."""
        lay = self.layout
        model = lay.model
        theta = _place(self.base, theta_nl, lay.nl_index)
        p = lay.unflatten(theta, self.fixed)
        sig = Signals(self.t, self.x, self.v, self.u)
        psi = model.residual_basis(p, sig, self.a).columns  # [n, k]
        c0 = model.to_linear(p)
        if not lay.solved:
            r = psi @ c0
            return theta, jnp.sum(r * r)
        s_cols = _columns(psi, lay.solved)  # [n, k_S]
        if lay.other:
            y = -(_columns(psi, lay.other) @ _columns(c0, lay.other))
        else:
            y = jnp.zeros(psi.shape[0])
        # Normal equations of the column-scaled problem, scaled after forming SᵀS (the same
        # numbers as scaling S first, one pass over the [n, k] matrix fewer).
        gram_raw = s_cols.T @ s_cols
        norm = jnp.sqrt(jnp.diagonal(gram_raw))
        scale = jnp.where(norm > 0.0, norm, 1.0)
        gram = gram_raw / jnp.outer(scale, scale)
        rhs = (s_cols.T @ y) / scale
        k, n_lin, n_groups = len(lay.solved), len(lay.lin_names), lay.n_groups
        eye = jnp.eye(k, dtype=jnp.float64)
        lower, upper = self.lower, self.upper
        # static 0/1 incidence matrices (tiny matmuls; XLA's CPU scatter/gather are slow)
        lin_of_group = jnp.asarray(np.equal.outer(lay.lin_group, np.arange(n_groups)), float)
        coef_of_group = jnp.asarray(np.equal.outer(lay.coef_group, np.arange(n_groups)), float)

        def least_squares(free: Float[Array, " k"], z_fixed: Float[Array, " k"]) -> Array:
            # min ‖S D⁻¹ z − y‖ over the free entries of z, the others held at z_fixed: the
            # fixed rows/columns of G become the identity with a zero right-hand side.
            g = gram * jnp.outer(free, free) + jnp.diag(1.0 - free) + _RIDGE * eye
            z_hold = (1.0 - free) * z_fixed
            factor = (jnp.linalg.cholesky(g), True)
            return cho_solve(factor, free * (rhs - gram @ z_hold)) + z_hold

        # The solved parameters' values are the solved entries of the model's value vector
        # (one value per coefficient, same order), mapped as vectors in one pass each.
        v0 = model.linear_values(c0, p)

        def named(z: Array) -> Array:
            return _columns(model.linear_values(_place(c0, z / scale, lay.solved), p), lay.solved)

        def coefficients(values: Array) -> Array:
            c = model.linear_coefficients(_place(v0, values, lay.solved), p)
            return _columns(c, lay.solved) * scale

        def step(state: _ActiveSet) -> _ActiveSet:
            free = 1.0 - coef_of_group @ state.fixed
            z = least_squares(free, state.z_fixed)
            values = named(z)
            box = jnp.clip(values, lower, upper)
            z_box = coefficients(box)
            # every iterate, clipped into the box, is a feasible candidate: keep the best
            r = s_cols @ (z_box / scale) - y
            cost = jnp.sum(r * r)
            better = cost < state.best_cost
            best = jnp.where(better, box, state.best)
            best_cost = jnp.where(better, cost, state.best_cost)
            # 1. free groups that left the box: fixed where they were clipped (all at once)
            moved = jnp.where(box != values, 1.0, 0.0) @ lin_of_group
            out = jnp.where((moved > 0.0) & (state.fixed == 0.0), 1.0, 0.0)
            # 2. else the fixed group whose bound holds it back most is released (one at a
            #    time): ∂E/∂parameter (one reverse pass through to_linear) of the wrong sign
            #    at its bound, times its box width: the cost it could still gain.
            slope = jax.vjp(coefficients, box)[1](gram @ z - rhs)[0]
            pull = state.side * slope * (upper - lower)
            pull = jnp.max(jnp.where(lin_of_group > 0.0, pull[:, None], -jnp.inf), axis=0)
            pull = jnp.where(state.fixed > 0.0, pull, -jnp.inf)
            worst = jnp.argmax(pull)
            tol = 1e-9 * jnp.linalg.norm(rhs) * (jnp.max(jnp.abs(z)) + 1e-300)
            release = (jnp.max(out) == 0.0) & (pull[worst] > tol)
            gone = jnp.where(release, jax.nn.one_hot(worst, n_groups), 0.0)
            fixed = state.fixed + out - gone
            side = jnp.where(lin_of_group @ out > 0.0, jnp.sign(values - box), state.side)
            side = jnp.where(lin_of_group @ gone > 0.0, 0.0, side)
            z_fixed = jnp.where(coef_of_group @ out > 0.0, z_box, state.z_fixed)
            done = (jnp.max(out) == 0.0) & ~release
            return _ActiveSet(fixed, z_fixed, side, best, best_cost, state.count + 1, done)

        def going(state: _ActiveSet) -> Array:
            return ~state.done & (state.count <= lay.passes)

        start = _ActiveSet(
            fixed=jnp.zeros(n_groups),
            z_fixed=jnp.zeros(k),
            side=jnp.zeros(n_lin),
            best=jnp.zeros(n_lin),
            best_cost=jnp.asarray(jnp.inf),
            count=jnp.asarray(0),
            done=jnp.asarray(False),
        )
        # under vmap the loop runs until every chain's active set has settled (or `passes`)
        end = jax.lax.while_loop(going, step, start)
        # E_P is the exact cost of this feasible θ (not the normal equations' estimate of it)
        return _place(theta, end.best, lay.lin_index), end.best_cost


class _ActiveSet(NamedTuple):
    """Loop state of the bounded solve: ``fixed [G]`` (1.0: group held on a bound), their
    scaled coefficients ``z_fixed [k]``, ``side [L]`` (−1 lower, +1 upper, 0 not on a bound)
    per solved parameter, the best feasible parameter values so far ``best [L]`` and their
    cost ``best_cost`` [N²], ``count`` (least-squares solves), ``done``."""

    fixed: Array
    z_fixed: Array
    side: Array
    best: Array
    best_cost: Array
    count: Array
    done: Array


def _runs(index: tuple[int, ...]) -> list[tuple[int, int]]:
    """Contiguous runs ``[(start, stop), ...]`` of a static index tuple."""
    runs: list[tuple[int, int]] = []
    for i in index:
        if runs and runs[-1][1] == i:
            runs[-1] = (runs[-1][0], i + 1)
        else:
            runs.append((i, i + 1))
    return runs


def _columns(m: Array, index: tuple[int, ...]) -> Array:
    """``m[..., index]`` for a static ``index``, as contiguous slices (XLA's gather is slow)."""
    parts = [m[..., a:b] for a, b in _runs(index)]
    return parts[0] if len(parts) == 1 else jnp.concatenate(parts, axis=-1)


def _place(base: Array, values: Array, index: tuple[int, ...]) -> Array:
    """``base.at[index].set(values)`` for a static ``index``, as slice updates."""
    i = 0
    for a, b in _runs(index):
        base = base.at[a:b].set(values[i : i + b - a])
        i += b - a
    return base


@jax.jit
def _solve(
    projection: Projection, theta_nl: Float[Array, " d_nl"]
) -> tuple[Float[Array, " d"], Float[Array, ""]]:
    # A jit boundary inside every caller: the solve is traced to a jaxpr once per layout
    # and shape, and the search's sample/init/level programs (and their vmaps) reuse it
    # instead of re-running the Python above (measured: ~1 s of tracing saved per run).
    return projection.solve(theta_nl)


class ProjectedCost(eqx.Module):
    """``θ_nl [d_nl] -> E_P(θ_nl)`` [N²] (pure, jit/vmap-able): a search cost function."""

    projection: Projection

    def __call__(self, theta_nl: Float[Array, " d_nl"]) -> Float[Array, ""]:
        return _solve(self.projection, theta_nl)[1]


class CostAndTheta(eqx.Module):
    """``θ_nl [d_nl] -> (E_P(θ_nl) [N²], θ [d])``: the search cost with the full vector as
    auxiliary output (:func:`fricjax.search.chains.run_chains_fused` with ``has_aux``)."""

    projection: Projection

    def __call__(
        self, theta_nl: Float[Array, " d_nl"]
    ) -> tuple[Float[Array, ""], Float[Array, " d"]]:
        theta, cost = _solve(self.projection, theta_nl)
        return cost, theta


class FullTheta(eqx.Module):
    """``θ_nl [d_nl] -> θ [d]``: the original free vector at the projected optimum."""

    projection: Projection

    def __call__(self, theta_nl: Float[Array, " d_nl"]) -> Float[Array, " d"]:
        return _solve(self.projection, theta_nl)[0]


def projected(
    projection: Projection, theta_nl: Float[Array, " d_nl"]
) -> tuple[Float[Array, " d"], Float[Array, ""]]:
    """θ [d] and E_P [N²] at ``θ_nl`` (traceable: vmap it over chains, or over stacked
    projections of several recordings)."""
    return _solve(projection, theta_nl)


@eqx.filter_jit
def _project_batch(
    projection: Projection, theta_nl: Float[Array, "C d_nl"]
) -> tuple[Float[Array, "C d"], Float[Array, " C"]]:
    return jax.vmap(lambda x: _solve(projection, x))(theta_nl)


@dataclass(frozen=True, eq=False)
class Separable:
    """A problem in variable-projection form.

    Attributes:
        problem: the original :class:`Problem` (its free vector θ [d] is the target).
        nonlinear_spec: the searched parameters only (free, with their bounds) [d_nl].
        linear_names: the free parameters solved exactly, in coefficient-group order.
        projected_cost: ``θ_nl -> E_P`` [N²], jittable, vmappable over chains.
        full_theta: ``θ_nl -> θ [d]``; ``problem.cost(full_theta(θ_nl)) == E_P(θ_nl)``.
        layout: the static partition.
    """

    problem: Problem
    nonlinear_spec: ParamSpec
    linear_names: tuple[str, ...]
    projected_cost: ProjectedCost
    full_theta: FullTheta
    layout: Layout

    @property
    def n_nonlinear(self) -> int:
        return self.nonlinear_spec.n_free

    def project(self, theta_nl: Float[Array, "C d_nl"]) -> tuple[np.ndarray, np.ndarray]:
        """Over a batch: full vectors θ [C, d] and their costs E_P [C] [N²] (one compiled
        call per batch size)."""
        x = jnp.atleast_2d(jnp.asarray(theta_nl, dtype=jnp.float64))
        theta, cost = _project_batch(self.full_theta.projection, x)
        return np.asarray(theta), np.asarray(cost)

    @property
    def cost_and_theta(self) -> CostAndTheta:
        """``θ_nl -> (E_P, θ)`` (:class:`CostAndTheta`)."""
        return CostAndTheta(self.full_theta.projection)

    def describe(self) -> str:
        """E.g. ``"omega, vs over 2-D; 24 linear parameters solved exactly"``."""
        solved = f"{len(self.linear_names)} linear parameters solved exactly"
        if not self.n_nonlinear:
            return f"no nonlinear parameter; {solved}"
        return f"{', '.join(self.nonlinear_spec.free_names)} over {self.n_nonlinear}-D; {solved}"


_CACHE: weakref.WeakKeyDictionary[Problem, dict[int, Separable]] = weakref.WeakKeyDictionary()


def separate(problem: Problem, *, passes: int = PASSES) -> Separable:
    """The variable-projection form of ``problem`` (cached per problem and ``passes``, so
    every call hands the search the same cost object and reuses its compilation).

    ``passes``: active-set re-solves after the unconstrained one (module docstring).
    Raises :class:`FricjaxError` when a model term declares no linear basis.
    """
    per_problem = _CACHE.setdefault(problem, {})
    if passes in per_problem:
        return per_problem[passes]
    lay = layout(problem.model, problem.spec, passes=passes)
    spec = problem.spec
    # device_put, not jnp.asarray: the latter compiles a small copy program per shape
    arrays = {
        k: np.asarray(getattr(problem, k), dtype=np.float64) for k in ("t", "x", "v", "u", "a")
    }
    arrays["base"] = np.asarray(spec.init, dtype=np.float64)
    arrays["fixed"] = np.asarray([p.init for p in spec.params if not p.free], dtype=np.float64)
    arrays["lower"] = np.asarray([spec[n].lower for n in lay.lin_names], dtype=np.float64)
    arrays["upper"] = np.asarray([spec[n].upper for n in lay.lin_names], dtype=np.float64)
    arrays = jax.device_put(arrays)
    projection = Projection(layout=lay, **arrays)
    free = problem.spec.free
    nonlinear = ParamSpec(tuple(free[i] for i in lay.nl_index), source=problem.spec.source)
    sep = Separable(
        problem=problem,
        nonlinear_spec=nonlinear,
        linear_names=lay.lin_names,
        projected_cost=ProjectedCost(projection),
        full_theta=FullTheta(projection),
        layout=lay,
    )
    per_problem[passes] = sep
    return sep
