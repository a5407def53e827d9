"""Annealing control shared by every search algorithm (seed paper section 3.2).

The search minimises a scalar cost ``f(θ)`` over a box ``a ≤ θ ≤ b`` (``θ`` of shape
``[d]``, in the parameters' own SI units; the cost in its own units, N² for the seed
paper's eq. 11). Temperatures are in cost units.

What lives here:

* :class:`AnnealSettings`: every knob of the annealing control and of the moves, with
  validation that names the offending field.
* :func:`initial_temperature`: ``t0 = K·δ``, ``δ = max f − min f`` over a random sample of
  the box (eq. 15).
* :func:`temperature`: the temperature of level ``k`` as a pure function of ``k``
  (geometric eq. 16 and three further schedules).
* :func:`metropolis_accept`: the acceptance rule of STEP2.
* :func:`commit`, :func:`run_level`: the bookkeeping common to all chains and one level
  (``steps_per_level`` steps in ``lax.scan`` at a fixed temperature).
* :class:`Algorithm`: the ``prepare / init / step / end_level`` quadruple that
  :mod:`fricjax.search.csaa`, :mod:`~fricjax.search.dsaa` and :mod:`~fricjax.search.rdsa`
  provide and :mod:`fricjax.search.chains` runs.

Every chain is one :class:`ChainState` (built by :func:`start`); what an algorithm carries
of its own (a step scale, a code, a failure count) is its ``adapt`` field.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.special import ndtri
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from fricjax.errors import FricjaxError, where

CostFn = Callable[[Float[Array, " d"]], Float[Array, ""]]

#: Names accepted for ``AnnealSettings.schedule``.
SCHEDULES: tuple[str, ...] = ("geometric", "boltzmann", "cauchy", "reheat")


@dataclasses.dataclass(frozen=True)
class AnnealSettings:
    """Annealing control and move settings (hashable, so it can be a static jit argument).

    Annealing control (seed paper section 3.2.3 (3)):

    * ``K``: factor of eq. 15, ``t0 = K·δ`` (paper: 10).
    * ``alpha``: cooling factor of eq. 16, ``t_{k+1} = α·t_k`` (paper: 0.95).
    * ``schedule``: one of :data:`SCHEDULES`, see :func:`temperature`.
    * ``steps_per_level``: Metropolis steps per chain at each temperature.
    * ``max_levels``: hard limit on the number of temperature levels.
    * ``t_min_rel``: the run may stop once ``t_k ≤ t_min_rel·t0`` (geometric with the
      defaults: after ln(1e-7)/ln(0.95) ≈ 315 levels) ...
    * ``patience``, ``rel_tol``, ``abs_tol``: ... and the best cost over all chains has not
      dropped by more than ``rel_tol·|best| + abs_tol`` for ``patience`` levels ("the
      cost function doesn't change").
    * ``n_temperature_samples``: points of the box sampled for δ in eq. 15.
    * ``reheat_every``, ``reheat_fraction``: the ``"reheat"`` schedule.

    Moves (``k`` values larger than the number of parameters or bits are clipped to it):

    * ``csaa_k``: parameters redrawn uniformly by a CSAA move (eq. 12; the paper's "k
      parameters", value not given). Default 1: late in a run a redraw is accepted only
      if it lowers the cost, which is far likelier for one coordinate than for several at
      once. Measured with 8 chains: on a 5-D shifted quadratic (6·10³ steps per chain)
      k = 1 ends ~10× closer to the minimum than k = 3; on a rotated, ill-conditioned
      26-D quadratic (3·10⁴ steps, default schedule) at about a third of the cost.
    * ``gauss_k``: parameters moved by a Gaussian CSAA move; 0 moves all of them.
    * ``gauss_scale0``: initial Gaussian step, as a fraction of each parameter's range.
    * ``gauss_target``, ``gauss_gamma``: after each level the step scale is multiplied by
      ``exp(γ·(acceptance − target))``, clipped to [1e-12, 1]. Under geometric cooling the
      acceptance settles slightly below the target, near ``target + ln(α)/(2γ)`` (the
      step has to shrink like √t).
    * ``dsaa_k``: a DSAA neighbour differs in 1..k bits (eq. 14). Default 2: half of the
      proposals are single-bit flips (the finest moves, needed to set the last bits at low
      temperature), half two-bit flips, which step over small Hamming barriers. Measured
      with Gray code: on the 26-D problem above k = 2 gave the lowest median chain cost
      of k = 1, 2, 3, 5; on 2-D Rastrigin k = 1 left most chains in a wrong well, k = 2
      and 3 none.
    * ``n_bits``: bits per parameter (eq. 13; paper: 10); the grid step is
      ``(b − a)/(2^n − 1)``.
    * ``rdsa_alpha0``: initial RDSA step α of eq. 6, as a fraction of the ranges.
    * ``rdsa_grow``, ``rdsa_shrink``, ``rdsa_patience``: α ×grow after a success, ×shrink
      after ``patience`` consecutive failures (α kept in [1e-12, 1]). The defaults (1.5,
      0.5, 5) balance at a success rate of ≈ 0.25, close to the classical 1/5 rule.
    """

    K: float = 10.0
    alpha: float = 0.95
    schedule: str = "geometric"
    steps_per_level: int = 100
    max_levels: int = 500
    t_min_rel: float = 1e-7
    patience: int = 20
    rel_tol: float = 1e-8
    abs_tol: float = 0.0
    n_temperature_samples: int = 512
    reheat_every: int = 50
    reheat_fraction: float = 0.5
    csaa_k: int = 1
    gauss_k: int = 0
    gauss_scale0: float = 0.1
    gauss_target: float = 0.4
    gauss_gamma: float = 1.0
    dsaa_k: int = 2
    n_bits: int = 10
    rdsa_alpha0: float = 0.1
    rdsa_grow: float = 1.5
    rdsa_shrink: float = 0.5
    rdsa_patience: int = 5

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], source: object = None) -> AnnealSettings:
        """Build settings from a mapping (e.g. a TOML table), refusing unknown keys and
        wrong types with a one-line :class:`FricjaxError` naming ``source`` and the key."""
        if not isinstance(d, Mapping):
            raise FricjaxError(f"{where(source)}: search settings must be a table")
        types = {f.name: f.type for f in dataclasses.fields(cls)}
        values: dict[str, Any] = {}
        for name, value in d.items():
            if name not in types:
                valid = ", ".join(types)
                raise FricjaxError(f"{where(source, name)}: unknown setting (valid: {valid})")
            values[name] = _coerce(value, types[name], source, name)
        return cls(**values).validate(source)

    def validate(self, source: object = None) -> AnnealSettings:
        """Return ``self`` if every field is in range, else raise :class:`FricjaxError`."""
        for name, kind in ((f.name, f.type) for f in dataclasses.fields(self)):
            _coerce(getattr(self, name), kind, source, name)
        checks: list[tuple[str, bool, str]] = [
            ("K", 0.0 < self.K < math.inf, "must be > 0 and finite"),
            ("alpha", 0.0 < self.alpha < 1.0, "must be in (0, 1)"),
            ("schedule", self.schedule in SCHEDULES, f"must be one of {', '.join(SCHEDULES)}"),
            ("steps_per_level", self.steps_per_level >= 1, "must be ≥ 1"),
            ("max_levels", self.max_levels >= 1, "must be ≥ 1"),
            ("t_min_rel", 0.0 <= self.t_min_rel < math.inf, "must be ≥ 0 and finite"),
            ("patience", self.patience >= 0, "must be ≥ 0"),
            ("rel_tol", 0.0 <= self.rel_tol < math.inf, "must be ≥ 0 and finite"),
            ("abs_tol", 0.0 <= self.abs_tol < math.inf, "must be ≥ 0 and finite"),
            ("n_temperature_samples", self.n_temperature_samples >= 2, "must be ≥ 2"),
            ("reheat_every", self.reheat_every >= 1, "must be ≥ 1"),
            ("reheat_fraction", 0.0 < self.reheat_fraction <= 1.0, "must be in (0, 1]"),
            ("csaa_k", self.csaa_k >= 1, "must be ≥ 1"),
            ("gauss_k", self.gauss_k >= 0, "must be ≥ 0 (0 = all parameters)"),
            ("gauss_scale0", 0.0 < self.gauss_scale0 <= 1.0, "must be in (0, 1]"),
            ("gauss_target", 0.0 < self.gauss_target < 1.0, "must be in (0, 1)"),
            ("gauss_gamma", 0.0 <= self.gauss_gamma < math.inf, "must be ≥ 0 and finite"),
            ("dsaa_k", self.dsaa_k >= 1, "must be ≥ 1"),
            ("n_bits", 1 <= self.n_bits <= 52, "must be in 1..52"),
            ("rdsa_alpha0", 0.0 < self.rdsa_alpha0 <= 1.0, "must be in (0, 1]"),
            ("rdsa_grow", 1.0 <= self.rdsa_grow < math.inf, "must be ≥ 1 and finite"),
            ("rdsa_shrink", 0.0 < self.rdsa_shrink < 1.0, "must be in (0, 1)"),
            ("rdsa_patience", self.rdsa_patience >= 1, "must be ≥ 1"),
        ]
        for name, ok, what in checks:
            if not ok:
                raise FricjaxError(f"{where(source, name)}: {what}, got {getattr(self, name)!r}")
        return self


def _coerce(value: Any, kind: str, source: object, name: str) -> Any:
    """Check one setting's type (TOML integers are accepted for float fields)."""
    if kind == "str":
        if isinstance(value, str):
            return value
        raise FricjaxError(f"{where(source, name)}: must be a string, got {value!r}")
    # bool is an int subclass, but `patience = true` is a mistake, not 1.
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise FricjaxError(f"{where(source, name)}: must be a number, got {value!r}")
    if kind == "int":
        if isinstance(value, int | np.integer):
            return int(value)
        raise FricjaxError(f"{where(source, name)}: must be an integer, got {value!r}")
    value = float(value)
    if math.isnan(value):
        raise FricjaxError(f"{where(source, name)}: must not be NaN")
    return value


def finite_range(costs: Float[Array, " n"]) -> Float[Array, ""]:
    """``δ = max − min`` of the finite entries of ``costs`` (eq. 15); NaN if none is
    finite. Cost units."""
    finite = jnp.isfinite(costs)
    high = jnp.max(jnp.where(finite, costs, -jnp.inf))
    low = jnp.min(jnp.where(finite, costs, jnp.inf))
    return jnp.where(jnp.any(finite), high - low, jnp.nan)


def initial_temperature(
    key: Array,
    cost_fn: CostFn,
    lower: Float[ArrayLike, " d"],
    upper: Float[ArrayLike, " d"],
    K: float,
    n_samples: int,
) -> Float[Array, ""]:
    """Initial temperature, eq. 15: ``t0 = K·δ``, ``δ = max f − min f`` over the box.

    ``δ`` is estimated from ``n_samples`` points drawn uniformly in ``[lower, upper]``
    (shape ``[d]`` each), the cost vmapped over them (:func:`finite_range`). Non-finite
    costs are ignored; if none is finite the result is NaN (the caller reports it).
    Units: cost units.
    """
    lower = jnp.asarray(lower)
    upper = jnp.asarray(upper)
    d = lower.shape[0]
    # A flat draw compiles in less than half the time of a 2-D one.
    u = jax.random.uniform(key, (n_samples * d,), dtype=lower.dtype).reshape(n_samples, d)
    return K * finite_range(jax.vmap(cost_fn)(lower + u * (upper - lower)))


def temperature(
    schedule: str, t0: Float[ArrayLike, ""], level: Int[ArrayLike, "*L"], settings: AnnealSettings
) -> Float[Array, "*L"]:
    """Temperature of level ``k`` (0-based; ``t(0) = t0``), a pure function of ``k``.

    * ``"geometric"``: ``t0·α^k`` — eq. 16 unrolled.
    * ``"boltzmann"`` (logarithmic): ``t0·ln 2 / ln(k + 2)``.
    * ``"cauchy"`` (fast): ``t0/(k + 1)``.
    * ``"reheat"``: geometric restarted every ``R = reheat_every`` levels, each restart at
      ``reheat_fraction`` (f) times the previous restart's temperature:
      ``t0·f^⌊k/R⌋·α^(k mod R)``.

    ``level`` may be an integer array; the result has its shape.
    """
    k = jnp.asarray(level, dtype=jnp.result_type(float))
    t0 = jnp.asarray(t0, dtype=k.dtype)
    if schedule == "geometric":
        return t0 * settings.alpha**k
    if schedule == "boltzmann":
        return t0 * math.log(2.0) / jnp.log(k + 2.0)
    if schedule == "cauchy":
        return t0 / (k + 1.0)
    if schedule == "reheat":
        cycle = jnp.floor(k / settings.reheat_every)
        within = k - cycle * settings.reheat_every
        return t0 * settings.reheat_fraction**cycle * settings.alpha**within
    raise FricjaxError(f"{where(None, 'schedule')}: must be one of {', '.join(SCHEDULES)}")


def draw(key: Array, n: int, dtype: Any = float) -> tuple[Array, Float[Array, " n"]]:
    """Advance a chain's key and draw ``n`` uniforms in [0, 1) for one step.

    Every step takes all its randomness from this one split and one flat draw: random-bit
    generation dominates XLA's CPU compile time of the scanned, vmapped level (~1 s), and
    every further call site adds to it.
    """
    key, sub = jax.random.split(key)
    return key, jax.random.uniform(sub, (n,), dtype=jnp.dtype(dtype))


def normal_from_uniform(u: Float[ArrayLike, "*s"]) -> Float[Array, "*s"]:
    """Standard normals from uniforms in [0, 1) by the inverse CDF.

    Uniforms are multiples of the machine epsilon; shifting them by half of it gives a
    grid symmetric about 1/2 that excludes 0 and 1, so the result is always finite.
    """
    u = jnp.asarray(u)
    return ndtri(u + jnp.finfo(u.dtype).eps / 2)


def metropolis_rule(
    u: Float[ArrayLike, ""],
    cost: Float[ArrayLike, ""],
    cost_new: Float[ArrayLike, ""],
    temperature: Float[ArrayLike, ""],
) -> Bool[Array, ""]:
    """Metropolis rule of STEP2 with a given uniform ``u ∈ [0, 1)``: accept if
    ``Δf = f(x_j) − f(x_i) ≤ 0``, else if ``exp(−Δf/t) > u`` — so a worse point is taken
    with probability ``exp(−Δf/t)``.

    A non-finite candidate cost is never accepted (NaN must not enter a chain); a
    non-finite current cost counts as +∞, so any finite candidate replaces it.
    """
    current = finite_or_inf(cost)
    cost_new = jnp.asarray(cost_new)
    delta = cost_new - current
    # At t = 0 the ratio is -inf for Δ > 0 (never accepted); the NaN of 0/0 at Δ = 0 is
    # masked by the Δ ≤ 0 branch.
    uphill = jnp.exp(-delta / temperature) > u
    return jnp.isfinite(cost_new) & ((delta <= 0) | uphill)


def metropolis_accept(
    key: Array,
    cost: Float[ArrayLike, ""],
    cost_new: Float[ArrayLike, ""],
    temperature: Float[ArrayLike, ""],
) -> Bool[Array, ""]:
    """:func:`metropolis_rule` with ``u ~ U[0, 1)`` drawn from ``key``."""
    dtype = jnp.result_type(jnp.asarray(cost).dtype, float)
    return metropolis_rule(jax.random.uniform(key, (), dtype=dtype), cost, cost_new, temperature)


def greedy_accept(cost: Float[ArrayLike, ""], cost_new: Float[ArrayLike, ""]) -> Bool[Array, ""]:
    """RDSA rule: accept only a finite, strictly better candidate (non-finite current = +∞)."""
    return jnp.isfinite(cost_new) & (cost_new < finite_or_inf(cost))


class ChainState(NamedTuple):
    """State of one chain of any algorithm (shapes without the chain axis).

    ``x [d]``/``cost []``: current point and its cost (+∞ if it was not finite);
    ``best_x [d]``/``best_cost []``: best point visited; ``key``: PRNG key;
    ``n_accepted``, ``n_proposed``, ``n_evals``: cumulative counters; ``adapt``: what the
    algorithm itself carries (CSAA's Gaussian scale ``[]``, DSAA's code ``[d, n]``,
    RDSA's :class:`fricjax.search.rdsa.Step`).
    """

    x: Float[Array, " d"]
    cost: Float[Array, ""]
    best_x: Float[Array, " d"]
    best_cost: Float[Array, ""]
    key: Array
    n_accepted: Int[Array, ""]
    n_proposed: Int[Array, ""]
    n_evals: Int[Array, ""]
    adapt: Any


def start(
    key: Array, x0: Float[ArrayLike, " d"], cost0: Float[ArrayLike, ""], adapt: Any
) -> ChainState:
    """A chain at ``x0`` whose cost ``cost0 = f(x0)`` the caller evaluated (counted as one
    evaluation)."""
    x0 = jnp.asarray(x0)
    cost0 = finite_or_inf(cost0)
    zero = jnp.zeros((), dtype=int)
    return ChainState(x0, cost0, x0, cost0, key, zero, zero, zero + 1, adapt)


def commit(
    state: ChainState, accepted: Bool[Array, ""], x_new: Float[Array, " d"], cost_new: Any
) -> ChainState:
    """Move a chain state to the candidate if ``accepted``; update the best point and the
    counters (one proposal, one cost evaluation)."""
    better = accepted & (cost_new < state.best_cost)
    return state._replace(
        x=jnp.where(accepted, x_new, state.x),
        cost=jnp.where(accepted, cost_new, state.cost),
        best_x=jnp.where(better, x_new, state.best_x),
        best_cost=jnp.where(better, cost_new, state.best_cost),
        n_accepted=state.n_accepted + accepted.astype(state.n_accepted.dtype),
        n_proposed=state.n_proposed + 1,
        n_evals=state.n_evals + 1,
    )


def finite_or_inf(cost: Float[ArrayLike, ""]) -> Float[Array, ""]:
    """A chain stores a non-finite cost as +∞ so that NaN never appears in its state."""
    cost = jnp.asarray(cost)
    return jnp.where(jnp.isfinite(cost), cost, jnp.inf)


def reflect(
    x: Float[ArrayLike, " d"], lower: Float[ArrayLike, " d"], upper: Float[ArrayLike, " d"]
) -> Float[Array, " d"]:
    """Fold ``x`` back into ``[lower, upper]`` by mirror reflection at the bounds.

    The fold is periodic (period ``2(b − a)``), so a step of any length lands inside; the
    final clip only removes last-ulp rounding.
    """
    x = jnp.asarray(x)
    width = jnp.asarray(upper) - jnp.asarray(lower)
    y = jnp.mod(x - lower, 2.0 * width)
    y = jnp.where(y > width, 2.0 * width - y, y)
    return jnp.clip(lower + y, lower, upper)


def random_subset(
    u: Float[ArrayLike, " k"], n: int, count: Int[ArrayLike, ""] | int
) -> Int[Array, " k"]:
    """A uniformly random ``count``-subset of ``0..n−1`` (Floyd's algorithm), from ``k``
    uniforms in [0, 1), ``count ≤ k ≤ n`` (``count`` may be traced).

    Returns ``k`` indices: the subset in the first ``count`` entries, then ``n`` (an
    out-of-range filler for ``.at[].set(mode="drop")``). Costs O(k²), independent of
    ``n``: a top-k over the 260 DSAA bits of the seed problem took ~75 µs per step on CPU,
    this ~1 µs.
    """
    u = jnp.asarray(u)
    k = u.shape[0]

    def pick(i: Int[Array, ""], chosen: Int[Array, " k"]) -> Int[Array, " k"]:
        j = n - count + i
        t = jnp.minimum(jnp.floor(u[i] * (j + 1)).astype(chosen.dtype), j)
        new = jnp.where(jnp.any(chosen == t), j, t)
        return chosen.at[i].set(jnp.where(i < count, new, n))

    return jax.lax.fori_loop(0, k, pick, jnp.full((k,), n, dtype=int))


def random_mask(u: Float[ArrayLike, " k"], n: int, k: int) -> Bool[Array, " n"]:
    """Boolean ``[n]`` mask with exactly ``min(k, n)`` True entries at random positions,
    from ``k`` i.i.d. uniforms in [0, 1) (unused when ``k ≥ n``)."""
    if k >= n:
        return jnp.ones((n,), dtype=bool)
    idx = random_subset(u, n, k)
    return jnp.zeros((n,), dtype=bool).at[idx].set(True, mode="drop")


class Algorithm(NamedTuple):
    """A search algorithm as pure functions (module-level constants, so it is hashable).

    * ``prepare(x [d], lower, upper, settings) -> x [d]``: map a start point into the
      algorithm's search space (the DSAA grid); the identity for the others.
    * ``init(key, x0, cost0, lower, upper, settings) -> State``.
    * ``step(state, cost_fn, temperature, lower, upper, settings) -> State``: one proposal.
    * ``end_level(state, acceptance, settings) -> State``: adaptation between levels.
    """

    name: str
    prepare: Callable[..., Any]
    init: Callable[..., Any]
    step: Callable[..., Any]
    end_level: Callable[..., Any]


def keep_point(
    x: Float[Array, " d"], lower: Float[Array, " d"], upper: Float[Array, " d"], settings: Any
) -> Float[Array, " d"]:
    """``prepare`` for continuous algorithms: start points are used as given."""
    return x


def no_adaptation(state: Any, acceptance: Float[Array, ""], settings: Any) -> Any:
    """``end_level`` for algorithms without between-level adaptation."""
    return state


class LevelStats(NamedTuple):
    """Per-chain summary of one level (a leading chain axis after vmap)."""

    best_cost: Float[Array, ""]
    current_cost: Float[Array, ""]
    acceptance: Float[Array, ""]
    n_evals: Int[Array, ""]


def run_level(
    algorithm: Algorithm,
    state: Any,
    cost_fn: CostFn,
    temperature: Float[ArrayLike, ""],
    lower: Float[Array, " d"],
    upper: Float[Array, " d"],
    settings: AnnealSettings,
) -> tuple[Any, LevelStats]:
    """One temperature level of ONE chain: ``steps_per_level`` steps of
    ``algorithm.step`` in ``lax.scan`` at ``temperature``, then ``algorithm.end_level``
    with the level's acceptance rate (accepted / proposed in this level)."""
    accepted_before = state.n_accepted

    def body(carry: Any, _: None) -> tuple[Any, None]:
        return algorithm.step(carry, cost_fn, temperature, lower, upper, settings), None

    state, _ = jax.lax.scan(body, state, None, length=settings.steps_per_level)
    acceptance = (state.n_accepted - accepted_before) / settings.steps_per_level
    state = algorithm.end_level(state, acceptance, settings)
    stats = LevelStats(state.best_cost, state.cost, acceptance, state.n_evals)
    return state, stats


def propose(
    algorithm: Algorithm,
    state: Any,
    temperature: Float[ArrayLike, ""],
    lower: Float[Array, " d"],
    upper: Float[Array, " d"],
    settings: AnnealSettings,
) -> Float[Array, " d"]:
    """The point ``[d]`` that the next ``algorithm.step`` of ``state`` evaluates.

    With :func:`step_with_cost` this splits a step around its one cost evaluation, so a
    caller can evaluate the proposals of all chains (and other points) at ONE call site of
    the cost: the step is traced with a cost function that records its argument and the
    rest of that trace is dead code (XLA removes it). Relies on the :class:`Algorithm`
    contract: a step draws its randomness from the state's key and calls the cost exactly
    once, at the top level of its trace.
    """
    seen: list[Array] = []

    def record(x: Float[Array, " d"]) -> Float[Array, ""]:
        seen.append(x)
        return jnp.zeros((), dtype=state.cost.dtype)

    algorithm.step(state, record, temperature, lower, upper, settings)
    if len(seen) != 1:
        raise TypeError(
            f"{algorithm.name}: step evaluated the cost {len(seen)} times; exactly one "
            "evaluation per step is the Algorithm contract"
        )
    return seen[0]


def step_with_cost(
    algorithm: Algorithm,
    state: Any,
    cost_new: Float[ArrayLike, ""],
    temperature: Float[ArrayLike, ""],
    lower: Float[Array, " d"],
    upper: Float[Array, " d"],
    settings: AnnealSettings,
) -> Any:
    """``algorithm.step`` given the cost ``cost_new`` of its proposal (:func:`propose`):
    the same step (same draw, same proposal), the evaluation replaced by the value."""
    return algorithm.step(state, lambda x: cost_new, temperature, lower, upper, settings)


def improved(new_best: float, reference: float, settings: AnnealSettings) -> bool:
    """True if ``new_best`` beats ``reference`` by more than ``rel_tol·|ref| + abs_tol``
    (host-side part of the stopping rule; a first finite value always counts)."""
    if not math.isfinite(new_best):
        return False
    if not math.isfinite(reference):
        return True
    return new_best < reference - (settings.rel_tol * abs(reference) + settings.abs_tol)


def should_stop(
    temperature: float, t0: float, levels_without_improvement: int, settings: AnnealSettings
) -> bool:
    """Stopping rule (section 3.2.3 (3)): the temperature is at or below ``t_min_rel·t0``
    and the best cost has not improved for ``patience`` levels."""
    cold = temperature <= settings.t_min_rel * t0
    return bool(cold and levels_without_improvement >= settings.patience)
