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

:func:`run_chains_fused` runs the same chains as ONE compiled program (the box sample,
every level with the stopping rule on the device, and optionally the cost's auxiliary
output at the end points), every cost evaluation at one call site: for costs that are
cheap to run and costly to compile (the variable-projection search), where the per-level
host loop would compile the cost into three programs.

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
from fricjax.programs import stored
from fricjax.search import csaa, dsaa, rdsa
from fricjax.search.annealing import (
    SCHEDULES,
    Algorithm,
    AnnealSettings,
    CostFn,
    LevelStats,
    finite_range,
    improved,
    propose,
    run_level,
    should_stop,
    step_with_cost,
    temperature,
)
from fricjax.search.fast_compile import FAST_COMPILE_LOOPS

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


def device_settings(settings: AnnealSettings) -> AnnealSettings:
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


def _start_states(
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


def _level_all(
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


_start = stored(_start_states)
_level = stored(_level_all)


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


class _Setup(NamedTuple):
    """Validated arguments of :func:`run_chains` / :func:`run_chains_fused`."""

    settings: AnnealSettings
    algorithm: Algorithm
    lower: np.ndarray
    upper: np.ndarray
    n_chains: int
    x0: Array | None
    key: Array
    devices: list[jax.Device]
    n_dev: int
    n_pad: int


def chain_setup(
    key: Array | int,
    lower: Float[ArrayLike, " d"],
    upper: Float[ArrayLike, " d"],
    method: str,
    settings: AnnealSettings | None,
    n_chains: int,
    x0: Float[ArrayLike, "C d"] | None,
    devices: Sequence[jax.Device] | None,
    source: object,
) -> _Setup:
    settings = (AnnealSettings() if settings is None else settings).validate(source)
    if method not in METHODS:
        raise FricjaxError(
            f"{where(source, 'method')}: unknown method {method!r} (valid: {', '.join(METHODS)})"
        )
    lo, hi = _bounds(lower, upper, source)
    if isinstance(n_chains, bool) or not isinstance(n_chains, int | np.integer) or n_chains < 1:
        raise FricjaxError(f"{where(source, 'n_chains')}: must be an integer ≥ 1, got {n_chains!r}")
    n_chains = int(n_chains)
    x_start = None if x0 is None else jax.device_put(_start_points(x0, n_chains, lo, hi, source))
    if isinstance(key, int | np.integer):
        key = jax.random.key(int(key))
    devices = list(jax.devices() if devices is None else devices)
    n_dev = len(devices)
    n_pad = -(-n_chains // n_dev) * n_dev
    return _Setup(settings, METHODS[method], lo, hi, n_chains, x_start, key, devices, n_dev, n_pad)


def checked_t0(t0: float, settings: AnnealSettings, source: object) -> float:
    """``t0 = K·δ`` (eq. 15), or the one-line error of a cost that is nowhere finite or
    whose range overflows."""
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
    return t0


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
    run = chain_setup(key, lower, upper, method, settings, n_chains, x0, devices, source)
    settings, algorithm, lo, hi = run.settings, run.algorithm, run.lower, run.upper
    n_chains, x_start, key, n_dev, n_pad = run.n_chains, run.x0, run.key, run.n_dev, run.n_pad
    mesh = Mesh(np.asarray(run.devices), ("chains",))
    by_chain = NamedSharding(mesh, PartitionSpec("chains"))
    replicated = NamedSharding(mesh, PartitionSpec())

    start = time.perf_counter()
    lower_j, upper_j = jnp.asarray(lo), jnp.asarray(hi)
    on_device = device_settings(settings)
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
    t0 = checked_t0(settings.K * float(delta), settings, source)
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
    return _result(chain_x, chain_cost, traces, n_levels, interrupted, method, t0, n_dev)


# --------------------------------------------------------------------------------------
# The whole search as one program
# --------------------------------------------------------------------------------------

# Phases of the one-program search: every iteration of its loop evaluates the cost at one
# batch of points (one call site), which the phase picks and then uses.
_SAMPLE, _ANNEAL, _FINISH, _DONE = 0, 1, 2, 3


class Control(NamedTuple):
    """The host-only fields of the settings as traced values of the one-program search
    (changing them does not recompile): ``K`` (eq. 15), ``rel_temps [L]`` (the schedule's
    ``t_k/t0``, :func:`temperature` at ``t0 = 1``), ``t_min_rel``, ``patience``,
    ``rel_tol``, ``abs_tol`` (the stopping rule of :func:`should_stop`)."""

    K: Float[Array, ""]
    rel_temps: Float[Array, " L"]
    t_min_rel: Float[Array, ""]
    patience: Array
    rel_tol: Float[Array, ""]
    abs_tol: Float[Array, ""]


class _Run(NamedTuple):
    """Carry of the one-program search (P = padded chains, L = max levels, C = chains).

    ``phase``: :data:`_SAMPLE` … :data:`_DONE`; ``batch``: next batch of the box sample;
    ``sample_cost [B·P]``: its costs; ``states``: the chains [P]; ``t0`` (eq. 15);
    ``level``, ``step``: position in the schedule; ``accepted_before [P]``: acceptances at
    the level's start; ``reference``, ``stale``: the stopping rule's state; the history
    ``best``/``current``/``acceptance [L, C]`` and ``n_evals [L]``; ``aux``: the cost's
    auxiliary output at the chains' best points [P, ...] (after :data:`_FINISH`).
    """

    phase: Array
    batch: Array
    sample_cost: Array
    states: Any
    t0: Array
    level: Array
    step: Array
    accepted_before: Array
    reference: Array
    stale: Array
    best: Array
    current: Array
    acceptance: Array
    n_evals: Array
    aux: Any


def fused_program(
    algorithm: Algorithm,
    key: Array,
    cost_fn: Callable[[Float[Array, " d"]], tuple[Float[Array, ""], Any]],
    x0: Float[Array, "C d"] | None,
    lower: Float[Array, " d"],
    upper: Float[Array, " d"],
    settings: AnnealSettings,
    control: Control,
    n_samples: int,
    n_chains: int,
    n_pad: int,
    with_aux: bool,
    sharding: NamedSharding | None,
) -> _Run:
    """The search of :func:`run_chains` in ONE ``lax.while_loop`` whose body evaluates
    ``cost_fn`` (returning ``(cost, aux)``) on one batch of ``n_pad`` points: the box
    sample in batches (then the chains start as in :func:`_start_states`), then one step
    of every chain per iteration (:func:`propose` / :func:`step_with_cost`; level ends,
    adaptation and the stopping rule on the device), then, if ``with_aux``, the chains'
    best points once more for their ``aux``. One call site: the cost compiles once."""
    d = lower.shape[0]
    P = n_pad
    key_box, key_chains = jax.random.split(key)
    # the box sample and start points exactly as _start_states draws them
    n_box = n_chains + n_samples
    u = jax.random.uniform(key_box, (n_box * d,), dtype=lower.dtype)
    points = jnp.clip(lower + u.reshape(n_box, -1) * (upper - lower), lower, upper)
    if x0 is not None:
        points = jnp.concatenate([points, x0])
    points = jax.vmap(lambda x: algorithm.prepare(x, lower, upper, settings))(points)
    n_points = points.shape[0]
    n_batches = -(-n_points // P)
    batches = jnp.concatenate([points, jnp.repeat(points[:1], n_batches * P - n_points, axis=0)])
    batches = batches.reshape(n_batches, P, d)
    keys = jax.random.split(key_chains, n_chains)
    keys = jnp.concatenate([keys, jnp.repeat(keys[:1], P - n_chains, axis=0)])
    n_levels = control.rel_temps.shape[0]
    steps = settings.steps_per_level
    n_sampled = n_samples + n_chains

    def constrain(tree: Any) -> Any:
        return tree if sharding is None else jax.lax.with_sharding_constraint(tree, sharding)

    def init(xs: Array, cs: Array) -> Any:
        pad = P - n_chains
        xs, cs = (jnp.concatenate([a, jnp.repeat(a[:1], pad, axis=0)]) for a in (xs, cs))
        init_one = lambda k, x, c: algorithm.init(k, x, c, lower, upper, settings)  # noqa: E731
        return constrain(jax.vmap(init_one)(keys, xs, cs))

    cost_shape, aux_shape = jax.eval_shape(cost_fn, lower)
    aux0 = jax.tree.map(lambda a: jnp.zeros((P, *a.shape), a.dtype), aux_shape)
    history = jnp.zeros((n_levels, n_chains), dtype=cost_shape.dtype)
    zero = jnp.asarray(0)
    first = _Run(
        phase=jnp.asarray(_SAMPLE),
        batch=zero,
        sample_cost=jnp.zeros(n_batches * P, dtype=cost_shape.dtype),
        states=init(batches[0, :n_chains], jnp.zeros(n_chains, cost_shape.dtype)),
        t0=jnp.zeros((), dtype=lower.dtype),
        level=zero,
        step=zero,
        accepted_before=jnp.zeros(P, dtype=int),
        reference=jnp.asarray(jnp.inf, dtype=cost_shape.dtype),
        stale=zero,
        best=history,
        current=history,
        acceptance=jnp.zeros((n_levels, n_chains), dtype=lower.dtype),
        n_evals=jnp.zeros(n_levels, dtype=jnp.int64),
        aux=aux0,
    )

    def temp_of(r: _Run) -> Array:
        return r.t0 * control.rel_temps[jnp.minimum(r.level, n_levels - 1)]

    def start_chains(r: _Run) -> _Run:
        costs = r.sample_cost[:n_points]
        delta = finite_range(costs[n_chains:n_box])
        if x0 is None:
            order = jnp.argsort(~jnp.isfinite(costs), stable=True)[:n_chains]
            xs, cs = points[order], costs[order]
        else:
            xs, cs = points[n_box:], costs[n_box:]
        t0 = control.K * delta
        # a cost finite nowhere (t0 NaN) or overflowing: no level; the host reports it
        phase = jnp.where(jnp.isfinite(t0), _ANNEAL, _FINISH if with_aux else _DONE)
        states = init(xs, cs)
        return r._replace(phase=phase, states=states, t0=t0, accepted_before=states.n_accepted)

    def after_sample(r: _Run, cost: Array, aux: Any, stepped: Any) -> _Run:
        sample_cost = jax.lax.dynamic_update_slice(r.sample_cost, cost, (r.batch * P,))
        r = r._replace(batch=r.batch + 1, sample_cost=sample_cost)
        return jax.lax.cond(r.batch == n_batches, start_chains, lambda r: r, r)

    def end_level(r: _Run) -> _Run:
        # run_level's end of a level, then annealing.improved and should_stop
        states = r.states
        acceptance = (states.n_accepted - r.accepted_before) / steps
        states = jax.vmap(lambda s, a: algorithm.end_level(s, a, settings))(states, acceptance)
        real = LevelStats(
            *(a[:n_chains] for a in (states.best_cost, states.cost, acceptance, states.n_evals))
        )
        best_now = jnp.min(real.best_cost)
        margin = control.rel_tol * jnp.abs(r.reference) + control.abs_tol
        better = jnp.isfinite(best_now) & (
            ~jnp.isfinite(r.reference) | (best_now < r.reference - margin)
        )
        stale = jnp.where(better, 0, r.stale + 1)
        stop = (temp_of(r) <= control.t_min_rel * r.t0) & (stale >= control.patience)
        level = r.level + 1
        done = stop | (level >= n_levels)
        return r._replace(
            phase=jnp.where(done, _FINISH if with_aux else _DONE, _ANNEAL),
            states=constrain(states),
            level=level,
            step=zero,
            accepted_before=states.n_accepted,
            reference=jnp.where(better, best_now, r.reference),
            stale=stale,
            best=r.best.at[r.level].set(real.best_cost),
            current=r.current.at[r.level].set(real.current_cost),
            acceptance=r.acceptance.at[r.level].set(real.acceptance),
            n_evals=r.n_evals.at[r.level].set(n_sampled + jnp.sum(real.n_evals)),
        )

    def after_step(r: _Run, cost: Array, aux: Any, stepped: Any) -> _Run:
        r = r._replace(states=stepped, step=r.step + 1)
        return jax.lax.cond(r.step == steps, end_level, lambda r: r, r)

    def after_finish(r: _Run, cost: Array, aux: Any, stepped: Any) -> _Run:
        return r._replace(phase=jnp.asarray(_DONE), aux=aux)

    def body(r: _Run) -> _Run:
        # The step is split around its evaluation at the top level of the body, whatever
        # the phase: its proposal and its update then draw the same random numbers in one
        # computation, which XLA computes once (in a branch each, they compiled twice).
        t = temp_of(r)
        proposals = jax.vmap(lambda s: propose(algorithm, s, t, lower, upper, settings))(r.states)
        sample = batches[jnp.minimum(r.batch, n_batches - 1)]
        pts = jnp.where(
            r.phase == _SAMPLE,
            sample,
            jnp.where(r.phase == _FINISH, r.states.best_x, proposals),
        )
        cost, aux = jax.vmap(cost_fn)(constrain(pts))
        step_one = lambda s, c: step_with_cost(algorithm, s, c, t, lower, upper, settings)  # noqa: E731
        stepped = constrain(jax.vmap(step_one)(r.states, cost))
        which = jnp.minimum(r.phase, _FINISH)
        return jax.lax.switch(
            which, (after_sample, after_step, after_finish), r, cost, aux, stepped
        )

    return jax.lax.while_loop(lambda r: r.phase != _DONE, body, first)


_fused = stored(fused_program)
# run_chains_fused's ``fast_compile`` (fricjax.search.fast_compile)
_fused_fast_compile = stored(fused_program, compiler_options=FAST_COMPILE_LOOPS)


def relative_temperatures(settings: AnnealSettings) -> np.ndarray:
    """``t_k / t0`` for ``k = 0 … max_levels − 1`` [L] (numpy, float64): the schedule of
    :func:`temperature` at ``t0 = 1``, computed on the host without compiling anything."""
    k = np.arange(settings.max_levels, dtype=np.float64)
    if settings.schedule == "geometric":
        return settings.alpha**k
    if settings.schedule == "boltzmann":
        return math.log(2.0) / np.log(k + 2.0)
    if settings.schedule == "cauchy":
        return 1.0 / (k + 1.0)
    if settings.schedule == "reheat":
        cycle = np.floor(k / settings.reheat_every)
        within = k - cycle * settings.reheat_every
        return settings.reheat_fraction**cycle * settings.alpha**within
    raise FricjaxError(f"{where(None, 'schedule')}: must be one of {', '.join(SCHEDULES)}")


class WithAux(eqx.Module):
    """``θ -> (cost, None)``: a plain cost in the ``(cost, aux)`` form."""

    cost_fn: Any

    def __call__(self, x: Float[Array, " d"]) -> tuple[Float[Array, ""], None]:
        return self.cost_fn(x), None


def run_chains_fused(
    key: Array | int,
    cost_fn: Callable[[Float[Array, " d"]], Any],
    lower: Float[ArrayLike, " d"],
    upper: Float[ArrayLike, " d"],
    method: str = "csaa",
    settings: AnnealSettings | None = None,
    n_chains: int = 8,
    x0: Float[ArrayLike, "C d"] | None = None,
    on_level: Callable[[LevelInfo], None] | None = None,
    *,
    has_aux: bool = False,
    fast_compile: bool = False,
    devices: Sequence[jax.Device] | None = None,
    source: object = None,
) -> tuple[SearchResult, Any]:
    """:func:`run_chains` as ONE compiled program with ONE call site of the cost.

    For costs that are cheap to run and expensive to compile (the variable-projection
    search of :mod:`fricjax.search.separable`: its solve compiles into every program
    that evaluates it, ~1-2 s each on 2 cores, while the whole search runs for ~0.1 s):
    the box sample, every step of every chain and the final evaluation go through one
    vmapped call of the cost inside one ``lax.while_loop`` (:func:`fused_program`), so
    the cost compiles once instead of once per program (start, level, end points).

    ``has_aux``: ``cost_fn(θ [d]) -> (cost [], aux)``; the chains' best points are then
    evaluated once more and ``aux`` at each of them is returned, stacked along a leading
    chain axis [C, ...] (the separable search's full parameter vectors); without it the
    second result is None. ``fast_compile``: compile with
    :data:`fricjax.search.fast_compile.FAST_COMPILE_LOOPS` (the paper twin's separable
    search: ~0.6-0.9 s of compilation instead of ~5 s, ~0.15 s of run instead of ~0.07 s:
    right for the few hundred evaluations of a 2-D search, wrong for the 10⁵ of a 26-D one).

    Same arguments, chains (moves, acceptance, schedule, stopping rule) and
    :class:`SearchResult` as :func:`run_chains`; the same key gives a bit-identical
    result, though not bit-identical to :func:`run_chains`'s (another program: XLA may
    evaluate the cost's arithmetic differently). Differences:

    * ``on_level`` is called for every level after the program has run (the levels run on
      the device, without a round trip to the host). ``Traces.wall_time``: the time to
      compile the program plus its run time shared out over the levels in proportion to
      their cost evaluations (an estimate, not a per-level clock);
    * ``max_levels`` sizes the history ``[max_levels, C]`` in the program (changing it
      recompiles; the other schedule and stopping fields do not);
    * Ctrl-C cannot stop the program part-way; raised by ``on_level`` it ends the replay
      and sets ``interrupted`` (the result is the complete run).
    """
    run = chain_setup(key, lower, upper, method, settings, n_chains, x0, devices, source)
    settings, n_chains = run.settings, run.n_chains
    sharding = None
    if run.n_dev > 1:
        sharding = NamedSharding(
            Mesh(np.asarray(run.devices), ("chains",)), PartitionSpec("chains")
        )
    rel_temps = relative_temperatures(settings)
    # numpy values: the call transfers them (jnp.asarray would compile a copy per shape)
    control = Control(
        K=np.float64(settings.K),
        rel_temps=rel_temps,
        t_min_rel=np.float64(settings.t_min_rel),
        patience=np.int64(settings.patience),
        rel_tol=np.float64(settings.rel_tol),
        abs_tol=np.float64(settings.abs_tol),
    )
    args = (
        run.algorithm,
        run.key,
        cost_fn if has_aux else WithAux(cost_fn),
        run.x0,
        run.lower,
        run.upper,
        device_settings(settings),
        control,
        settings.n_temperature_samples,
        n_chains,
        run.n_pad,
        has_aux,
        sharding,
    )
    start = time.perf_counter()
    program = (_fused_fast_compile if fast_compile else _fused).compiled(*args)
    ready = time.perf_counter() - start
    out = jax.device_get(program(*args))
    elapsed = time.perf_counter() - start
    t0 = checked_t0(float(out.t0), settings, source)
    n_levels = int(out.level)
    n_evals = np.asarray(out.n_evals[:n_levels], dtype=np.int64)
    # the final evaluation of the best points takes its share of the run time too
    total = (n_evals[-1] if n_levels else settings.n_temperature_samples + n_chains) + (
        n_chains if has_aux else 0
    )
    times = ready + (elapsed - ready) * n_evals / total
    traces = Traces(
        best_cost=np.asarray(out.best[:n_levels]),
        current_cost=np.asarray(out.current[:n_levels]),
        acceptance=np.asarray(out.acceptance[:n_levels]),
        temperature=t0 * rel_temps[:n_levels],
        n_evals=n_evals,
        wall_time=np.asarray(times, dtype=np.float64),
    )
    interrupted = False
    if on_level is not None:
        try:
            for level in range(n_levels):
                on_level(
                    LevelInfo(
                        level=level,
                        temperature=float(traces.temperature[level]),
                        best_cost=float(traces.best_cost[level].min()),
                        mean_acceptance=float(traces.acceptance[level].mean()),
                        n_evals=int(n_evals[level]),
                        wall_time=float(times[level]),
                    )
                )
        except KeyboardInterrupt:
            interrupted = True
    chain_x = np.asarray(out.states.best_x)[:n_chains]
    chain_cost = np.asarray(out.states.best_cost)[:n_chains]
    result = _result(chain_x, chain_cost, traces, n_levels, interrupted, method, t0, run.n_dev)
    aux = jax.tree.map(lambda a: np.asarray(a)[:n_chains], out.aux) if has_aux else None
    return result, aux


def _result(
    chain_x: np.ndarray,
    chain_cost: np.ndarray,
    traces: Traces,
    levels_run: int,
    interrupted: bool,
    method: str,
    t0: float,
    n_devices: int,
) -> SearchResult:
    """The :class:`SearchResult` of end points ``chain_x [C, d]``, ``chain_cost [C]``."""
    i = int(np.argmin(chain_cost))
    return SearchResult(
        best_x=chain_x[i].copy(),
        best_cost=float(chain_cost[i]),
        chain_x=chain_x,
        chain_cost=chain_cost,
        traces=traces,
        levels_run=levels_run,
        interrupted=interrupted,
        method=method,
        t0=t0,
        n_devices=n_devices,
    )
