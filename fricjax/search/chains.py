"""Independent search chains, vmapped, sharded over devices, one jitted call per level.

:func:`run_chains` runs ``n_chains`` chains of one algorithm (``"csaa"``, ``"csaa-gauss"``,
``"dsaa"``, ``"dsaa-gray"``, ``"rdsa"``) on a cost ``f(θ) -> scalar`` over the box
``lower ≤ θ ≤ upper`` (shape ``[d]``):

1. one key is split into a key for the box sample (temperature and start points) and one
   key per chain, so the same key and settings give bit-identical results;
2. ``t0 = K·δ`` (eq. 15) from a uniform sample of the box; start points uniform over the
   part of the box where the cost is finite, unless ``x0 [n_chains, d]`` is given (DSAA
   snaps them to its grid);
3. levels ``k = 0, 1, …`` run at ``t_k = temperature(schedule, t0, k)`` (eq. 16 for the
   geometric schedule); each level is ONE jitted call of the vmapped
   :func:`fricjax.search.annealing.run_level`, so the Python loop between levels can report
   progress (``on_level``), apply the stopping rule and honour Ctrl-C;
4. the chain axis is sharded over the devices (a 1-D mesh; chains padded with copies of
   chain 0 to a multiple of the device count and dropped afterwards). Each chain's
   arithmetic does not depend on the other chains, so on one platform the result does not
   depend on the number of devices (checked bit for bit with two host CPU devices,
   ``XLA_FLAGS=--xla_force_host_platform_device_count=2``); a GPU runs the same code but
   its floating point differs from the CPU's.

Compilation is cached by ``equinox.filter_jit`` on (algorithm, cost function, move
settings, shapes): pass the same ``cost_fn`` object to reuse it (a new lambda per call
recompiles). The schedule and stopping fields of the settings live on the host only, so
changing them does not recompile.
A ``cost_fn`` that is an ``equinox.Module`` has its arrays traced, so new data of the same
shape reuses the compiled code too.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import Array, ArrayLike, Float

from fricjax.errors import FricjaxError, where
from fricjax.search import csaa, dsaa, rdsa
from fricjax.search.annealing import (
    Algorithm,
    AnnealSettings,
    CostFn,
    LevelStats,
    finite_range,
    improved,
    run_level,
    should_stop,
    temperature,
)

# Fields used only by the host loop. Jitted functions get them reset to their defaults, so
# that changing the schedule or the stopping rule reuses the compiled code.
_HOST_ONLY = (
    "K",
    "alpha",
    "schedule",
    "max_levels",
    "t_min_rel",
    "patience",
    "rel_tol",
    "abs_tol",
    "reheat_every",
    "reheat_fraction",
)
_DEFAULTS = AnnealSettings()


def _device_settings(settings: AnnealSettings) -> AnnealSettings:
    return dataclasses.replace(settings, **{f: getattr(_DEFAULTS, f) for f in _HOST_ONLY})


#: Method name → algorithm.
METHODS: dict[str, Algorithm] = {
    "csaa": csaa.REDRAW,
    "csaa-gauss": csaa.GAUSS,
    "dsaa": dsaa.BINARY,
    "dsaa-gray": dsaa.GRAY,
    "rdsa": rdsa.ALGORITHM,
}


class Traces(NamedTuple):
    """Per-level history, ``L`` levels run, ``C`` chains (numpy arrays).

    ``best_cost [L, C]``: best cost of each chain so far; ``current_cost [L, C]``: cost of
    each chain's current point; ``acceptance [L, C]``: accepted/proposed in the level;
    ``temperature [L]`` (cost units); ``n_evals [L]``: cumulative cost evaluations of all
    chains, the box sample (``n_temperature_samples + C``) and the start points included;
    ``wall_time [L]``: seconds since the call started (compilation included).
    """

    best_cost: np.ndarray
    current_cost: np.ndarray
    acceptance: np.ndarray
    temperature: np.ndarray
    n_evals: np.ndarray
    wall_time: np.ndarray


class SearchResult(NamedTuple):
    """Outcome of :func:`run_chains` (numpy arrays and Python scalars).

    ``best_x [d]``/``best_cost``: best point of all chains; ``chain_x [C, d]``/
    ``chain_cost [C]``: best point of each chain; ``traces``: :class:`Traces`;
    ``levels_run``; ``interrupted``: stopped by Ctrl-C; ``method``; ``t0``: initial
    temperature (eq. 15, cost units); ``n_devices``: devices the chains were sharded over.
    """

    best_x: np.ndarray
    best_cost: float
    chain_x: np.ndarray
    chain_cost: np.ndarray
    traces: Traces
    levels_run: int
    interrupted: bool
    method: str
    t0: float
    n_devices: int


class LevelInfo(NamedTuple):
    """What ``on_level`` receives after each level (host scalars)."""

    level: int
    temperature: float
    best_cost: float
    mean_acceptance: float
    n_evals: int
    wall_time: float


@eqx.filter_jit
def _start(
    algorithm: Algorithm,
    key: Array,
    cost_fn: CostFn,
    x0: Float[Array, "C d"] | None,
    lower: Float[Array, " d"],
    upper: Float[Array, " d"],
    settings: AnnealSettings,
    n_samples: int,
    n_chains: int,
    n_pad: int,
) -> tuple[Float[Array, ""], Any]:
    """δ of eq. 15 and the initial states of ``n_pad ≥ C`` chains.

    ``n_chains + n_samples`` uniform points are drawn and mapped by the algorithm's
    ``prepare`` (DSAA: onto its grid); δ is the cost range over the last ``n_samples``.
    Without ``x0``, chain i starts at point i unless its cost is not finite: start points
    are the first ``n_chains`` points with a finite cost (uniform over the finite part of
    the box), so no chain begins stranded in a forbidden region; ``x0`` [C, d] replaces
    them when given. Padding copies chain 0, so the real chains do not depend on the
    device count.

    One program, one batched cost call: every program that contains the cost traces and
    compiles it again (with the separable path's linear solve inlined, ~1-1.6 s of XLA
    compilation each on 2 cores), and ``fricjax identify`` runs exactly one of these.
    """
    key_box, key_chains = jax.random.split(key)
    # One flat draw serves the start points and the temperature sample: each random call
    # site adds compile time, a 2-D draw more than twice that of a 1-D one.
    n_box = n_chains + n_samples
    u = jax.random.uniform(key_box, (n_box * lower.shape[0],), dtype=lower.dtype)
    points = jnp.clip(lower + u.reshape(n_box, -1) * (upper - lower), lower, upper)
    if x0 is not None:
        points = jnp.concatenate([points, x0])
    points = jax.vmap(lambda x: algorithm.prepare(x, lower, upper, settings))(points)
    costs = jax.vmap(cost_fn)(points)
    delta = finite_range(costs[n_chains:n_box])
    if x0 is None:
        order = jnp.argsort(~jnp.isfinite(costs), stable=True)[:n_chains]
        xs, cs = points[order], costs[order]
    else:
        xs, cs = points[n_box:], costs[n_box:]
    keys = jax.random.split(key_chains, n_chains)
    extra = n_pad - n_chains
    xs, cs, keys = (jnp.concatenate([a, jnp.repeat(a[:1], extra, axis=0)]) for a in (xs, cs, keys))
    states = jax.vmap(lambda k, x, c: algorithm.init(k, x, c, lower, upper, settings))(keys, xs, cs)
    return delta, states


@eqx.filter_jit
def _level(
    algorithm: Algorithm,
    states: Any,
    cost_fn: CostFn,
    temp: Float[Array, ""],
    lower: Float[Array, " d"],
    upper: Float[Array, " d"],
    settings: AnnealSettings,
) -> tuple[Any, LevelStats]:
    """One level of all chains (vmap of :func:`run_level` over the leading chain axis)."""
    return jax.vmap(lambda s: run_level(algorithm, s, cost_fn, temp, lower, upper, settings))(
        states
    )


def _bounds(lower: ArrayLike, upper: ArrayLike, source: object) -> tuple[np.ndarray, np.ndarray]:
    lo = np.asarray(lower, dtype=np.float64)
    hi = np.asarray(upper, dtype=np.float64)
    for name, arr in (("lower", lo), ("upper", hi)):
        if arr.ndim != 1 or arr.size == 0:
            raise FricjaxError(f"{where(source, name)}: must be a 1-D array, got shape {arr.shape}")
        bad = np.flatnonzero(~np.isfinite(arr))
        if bad.size:
            raise FricjaxError(f"{where(source, name)}: not finite at index {bad[0]}")
    if lo.shape != hi.shape:
        raise FricjaxError(
            f"{where(source, 'upper')}: shape {hi.shape} differs from lower's {lo.shape}"
        )
    bad = np.flatnonzero(~(hi > lo))
    if bad.size:
        i = bad[0]
        raise FricjaxError(
            f"{where(source, 'upper')}: must exceed lower at index {i} ({hi[i]} ≤ {lo[i]})"
        )
    return lo, hi


def _start_points(
    x0: ArrayLike, n_chains: int, lo: np.ndarray, hi: np.ndarray, source: object
) -> np.ndarray:
    x = np.asarray(x0, dtype=np.float64)
    if x.shape != (n_chains, lo.shape[0]):
        raise FricjaxError(
            f"{where(source, 'x0')}: must have shape ({n_chains}, {lo.shape[0]}), got {x.shape}"
        )
    outside = np.argwhere(~((x >= lo) & (x <= hi)))
    if outside.size:
        c, j = outside[0]
        raise FricjaxError(
            f"{where(source, 'x0')}: chain {c} parameter {j} = {x[c, j]} is outside "
            f"[{lo[j]}, {hi[j]}]"
        )
    return x


def run_chains(
    key: Array | int,
    cost_fn: CostFn,
    lower: Float[ArrayLike, " d"],
    upper: Float[ArrayLike, " d"],
    method: str = "csaa",
    settings: AnnealSettings | None = None,
    n_chains: int = 8,
    x0: Float[ArrayLike, "C d"] | None = None,
    on_level: Callable[[LevelInfo], None] | None = None,
    *,
    devices: Sequence[jax.Device] | None = None,
    source: object = None,
) -> SearchResult:
    """Minimise ``cost_fn`` over the box with ``n_chains`` independent chains.

    ``key``: a JAX PRNG key (or an int seed); ``cost_fn(θ [d]) -> []``, pure and
    jit/vmap-able, non-finite values are treated as forbidden points; ``lower``/``upper``
    ``[d]``: the box, ``lower < upper``; ``method``: a key of :data:`METHODS`;
    ``x0``: optional start points ``[n_chains, d]`` inside the box; ``on_level``: called
    with a :class:`LevelInfo` after every level; ``devices``: devices to shard the chains
    over (default: all of ``jax.devices()``); ``source``: prefix for error messages (e.g.
    the config file).

    Stops when the rule of :func:`fricjax.search.annealing.should_stop` holds, after
    ``settings.max_levels`` levels, or on Ctrl-C (``interrupted=True``, the last complete
    level kept). Costs are in the cost's units, temperatures too.
    """
    settings = (AnnealSettings() if settings is None else settings).validate(source)
    if method not in METHODS:
        raise FricjaxError(
            f"{where(source, 'method')}: unknown method {method!r} (valid: {', '.join(METHODS)})"
        )
    algorithm = METHODS[method]
    lo, hi = _bounds(lower, upper, source)
    if isinstance(n_chains, bool) or not isinstance(n_chains, int | np.integer) or n_chains < 1:
        raise FricjaxError(f"{where(source, 'n_chains')}: must be an integer ≥ 1, got {n_chains!r}")
    n_chains = int(n_chains)
    x_start = None if x0 is None else jnp.asarray(_start_points(x0, n_chains, lo, hi, source))
    if isinstance(key, int | np.integer):
        key = jax.random.key(int(key))

    devices = list(jax.devices() if devices is None else devices)
    n_dev = len(devices)
    n_pad = -(-n_chains // n_dev) * n_dev
    mesh = Mesh(np.asarray(devices), ("chains",))
    by_chain = NamedSharding(mesh, PartitionSpec("chains"))
    replicated = NamedSharding(mesh, PartitionSpec())

    start = time.perf_counter()
    lower_j, upper_j = jnp.asarray(lo), jnp.asarray(hi)
    on_device = _device_settings(settings)
    delta, states = _start(
        algorithm,
        key,
        cost_fn,
        x_start,
        lower_j,
        upper_j,
        on_device,
        settings.n_temperature_samples,
        n_chains,
        n_pad,
    )
    t0 = settings.K * float(delta)
    if math.isnan(t0):
        raise FricjaxError(
            f"{where(source, 'cost')}: not finite at any of the "
            f"{settings.n_temperature_samples} points sampled in the box"
        )
    if math.isinf(t0):
        raise FricjaxError(
            f"{where(source, 'cost')}: its range over the box overflows (K·δ = inf); "
            "rescale the cost"
        )
    states = jax.device_put(states, by_chain)
    lower_j, upper_j = jax.device_put((lower_j, upper_j), replicated)
    temps = np.asarray(temperature(settings.schedule, t0, np.arange(settings.max_levels), settings))

    n_sampled = settings.n_temperature_samples + n_chains  # _sample's evaluations
    rows: list[LevelStats] = []
    times: list[float] = []
    evals: list[int] = []
    reference, stale = math.inf, 0
    interrupted = False
    try:
        for level in range(settings.max_levels):
            new_states, stats = _level(
                algorithm, states, cost_fn, jnp.asarray(temps[level]), lower_j, upper_j, on_device
            )
            stats = LevelStats(*(np.asarray(a)[:n_chains] for a in jax.device_get(stats)))
            # The level counts only once its results are on the host: an interrupt before
            # this point leaves the previous level's states and traces consistent.
            states = new_states
            rows.append(stats)
            times.append(time.perf_counter() - start)
            evals.append(n_sampled + int(stats.n_evals.sum()))
            best_now = float(stats.best_cost.min())
            if improved(best_now, reference, settings):
                reference, stale = best_now, 0
            else:
                stale += 1
            if on_level is not None:
                on_level(
                    LevelInfo(
                        level=level,
                        temperature=float(temps[level]),
                        best_cost=best_now,
                        mean_acceptance=float(stats.acceptance.mean()),
                        n_evals=evals[-1],
                        wall_time=times[-1],
                    )
                )
            if should_stop(float(temps[level]), t0, stale, settings):
                break
    except KeyboardInterrupt:
        interrupted = True

    best_x, best_cost = jax.device_get((states.best_x, states.best_cost))
    chain_x = np.asarray(best_x)[:n_chains]
    chain_cost = np.asarray(best_cost)[:n_chains]
    i = int(np.argmin(chain_cost))
    n_levels = len(rows)

    def stack(field: str) -> np.ndarray:
        if not rows:
            return np.zeros((0, n_chains))
        return np.stack([getattr(r, field) for r in rows])

    traces = Traces(
        best_cost=stack("best_cost"),
        current_cost=stack("current_cost"),
        acceptance=stack("acceptance"),
        temperature=temps[:n_levels].copy(),
        n_evals=np.asarray(evals, dtype=np.int64),
        wall_time=np.asarray(times),
    )
    return SearchResult(
        best_x=chain_x[i].copy(),
        best_cost=float(chain_cost[i]),
        chain_x=chain_x,
        chain_cost=chain_cost,
        traces=traces,
        levels_run=n_levels,
        interrupted=interrupted,
        method=method,
        t0=t0,
        n_devices=n_dev,
    )
