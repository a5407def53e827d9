"""Fleet of independent fits: many recordings identified at once, one compiled program per
recording shape.

Every recording is identified exactly as :func:`fricjax.identify.identify` would identify
it alone (search → Levenberg–Marquardt polish → Gauss–Newton σ), but B recordings of one
*shape* run as one vmapped program:

* **search**: the one-program annealing search of
  :func:`fricjax.search.chains.run_chains_fused` (the same chains, moves, schedule and
  stopping rule as :func:`~fricjax.search.chains.run_chains`), vmapped over the recordings'
  cost functions; on the separable path the chains search the nonlinear parameters of the
  variable projection (:mod:`fricjax.search.separable`) as ``identify`` does. Under vmap the
  loop runs until the slowest recording's chains stop; a recording whose chains stopped is
  held where it stopped (its answer does not depend on its neighbours);
* **polish**: the best ``refine_top`` chain end points of every recording, polished by the
  vmapped Levenberg–Marquardt of :func:`fricjax.refine.refine_many`, the best kept
  (never worse than the search's best, as in ``identify``);
* **σ**: ``r`` and ``J = ∂r/∂θ`` of every recording in one vmapped program, then
  :func:`fricjax.refine.uncertainty_at` per recording on the host.

Seeds. Every recording is searched with the key of the config's ``[search].seed``
(:func:`fricjax.identify.prng_key`): the key ``fricjax identify REC --config C`` uses for
that recording alone. A recording's answer therefore depends neither on its position in
the fleet nor on the shard it lands in. (Equal keys on different recordings are not a
statistical problem: the chains' draws are independent of the data, so the fits' errors
are those of the data.)

Shapes and buckets. A *shape* is the pytree structure of a recording's cost and residual
functions plus the shapes of their arrays (sample count, time grid, decimation, the fixed
parameter values such as a recording's mass, which the model specialises on at trace time).
Recordings are grouped by exact shape, not padded to a bucket length with a mask: a padded
recording would run another program than its single fit (a longer time grid, a masked sum in
another order, σ² = E/(n − d) with the mask's n), and the fleet must reproduce the single fit;
fleets are mostly runs of one test protocol (equal lengths), where one group holds them all.
A group is cut into shards of at most ``shard_size`` recordings; the last shard is padded by
repeating its last recording (dropped afterwards), so a group compiles once.
The shard plan depends only on the recordings, their order and ``shard_size``, so a Dask run
(:func:`run_fleet` with a client) runs the same programs on the same shards as the
in-process run, and gives the same numbers bit for bit on one platform.

Failures (a recording that does not load, a cost that is nowhere finite, a residual shorter
than the parameter vector, …) are results with ``status = "failed"`` and the one-line reason,
never dropped.
"""

from __future__ import annotations

import dataclasses
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import equinox as eqx
import h5py
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from fricjax.config import Config
from fricjax.data.recording import read_recording
from fricjax.errors import FricjaxError
from fricjax.identify import IdentifySettings, prng_key
from fricjax.problem import Problem, build_problem, stack_trees
from fricjax.refine import (
    RefineSettings,
    ResidualNoise,
    checked_refine_settings,
    cluster_minima,
    refine_batch,
    uncertainty_at,
)
from fricjax.residual_noise import residual_noises
from fricjax.search.chains import (
    Control,
    WithAux,
    chain_setup,
    checked_t0,
    device_settings,
    fused_program,
    relative_temperatures,
)
from fricjax.search.separable import projected, separate


def default_shard_size() -> int:
    """Recordings per shard (one vmapped program each) when none is given: 16 on a CPU,
    256 on an accelerator. A CPU gains little from wider batches once the chains' working
    set leaves its caches (axis model, 1 s recordings, 8 chains, a loaded 2-core host:
    18.5 recordings/s at 10 per shard, 16 at 64, 7.8 at 100); a GPU needs wide batches to
    fill its lanes."""
    return 16 if jax.default_backend() == "cpu" else 256


OK, FAILED = "ok", "failed"


@dataclass
class FleetFit:
    """One recording's result (numpy and Python values; pickles across processes).

    ``name``/``path``/``sha256``: the recording; ``order``: the value it is ordered by in
    the report (a recording attribute or its file name); ``status``: ``"ok"`` or
    ``"failed"``, ``reason``: why it failed ("" when ok). ``value``, ``std``, ``rel_std``
    [d]: identified free parameters, their Gauss–Newton σ and σ/|value| (NaN when failed);
    ``flags`` [d]: identifiability warnings; ``fixed``: every fixed parameter (the
    recording's mass included); ``cost`` [N²] (seed eq. 11) and ``ems = cost/n``;
    ``cost_search``: the search's best before the polish; ``levels``, ``n_evals``: search
    levels run and cost evaluations; ``refined``: the polish ran; ``cond``: condition
    number of the scaled JᵀJ; ``n_minima``: distinct minima the chains ended in; ``n``:
    samples; ``shard``: index of the shard that fitted it (-1: never fitted).
    """

    name: str
    path: str
    sha256: str
    order: str
    status: str
    reason: str = ""
    value: np.ndarray | None = None
    std: np.ndarray | None = None
    rel_std: np.ndarray | None = None
    flags: list[str] = dataclasses.field(default_factory=list)
    fixed: dict[str, float] = dataclasses.field(default_factory=dict)
    cost: float = float("nan")
    ems: float = float("nan")
    cost_search: float = float("nan")
    levels: int = 0
    n_evals: int = 0
    refined: bool = False
    cond: float = float("nan")
    n_minima: int = 0
    n: int = 0
    shard: int = -1

    @property
    def ok(self) -> bool:
        return self.status == OK


class Member(NamedTuple):
    """A fleet member: its provenance and its problem, or the reason it has none."""

    name: str
    path: str
    order: str
    problem: Problem | None
    reason: str = ""


def failed(member: Member, reason: str, *, sha256: str = "", shard: int = -1) -> FleetFit:
    """The result of a member that could not be fitted, with its one-line reason."""
    return FleetFit(
        name=member.name,
        path=member.path,
        sha256=sha256,
        order=member.order,
        status=FAILED,
        reason=reason,
        shard=shard,
    )


# --------------------------------------------------------------------------------------
# Shapes and shards
# --------------------------------------------------------------------------------------


def _search_cost(problem: Problem, separable: bool) -> eqx.Module:
    """The search's cost ``θ -> (E, θ_full)`` (separable) or ``θ -> (E, None)``."""
    return separate(problem).cost_and_theta if separable else WithAux(problem.cost_fn)


def _search_box(problem: Problem, separable: bool) -> tuple[np.ndarray, np.ndarray]:
    spec = separate(problem).nonlinear_spec if separable else problem.spec
    return np.asarray(spec.lower, np.float64), np.asarray(spec.upper, np.float64)


def shape_key(problem: Problem, separable: bool) -> Any:
    """What decides the compiled program of a recording: the pytree structures of its
    search cost and residual (static fields: model, fixed values, decimation, …) and the
    shapes and dtypes of their arrays. Equal keys share one compilation."""
    parts = (_search_cost(problem, separable), problem.residual_fn)
    leaves, treedef = jax.tree.flatten(eqx.filter(parts, eqx.is_array))
    return treedef, tuple((a.shape, str(a.dtype)) for a in leaves)


class Shard(NamedTuple):
    """Members ``index`` (into the fleet) fitted by one program of ``width`` lanes."""

    number: int
    index: tuple[int, ...]
    width: int


def plan_shards(
    problems: Sequence[Problem | None], separable: bool, shard_size: int
) -> list[Shard]:
    """Group the fittable members by :func:`shape_key` (in order of first appearance) and
    cut each group into shards of at most ``shard_size``; every shard of a group has the
    width ``min(shard_size, group size)`` (the last one padded), so a group compiles once.
    A member whose key cannot be built (e.g. a model without a linear basis on the
    separable path) raises :class:`FricjaxError` here, for the caller to record."""
    if shard_size < 1:
        raise FricjaxError(f"--shard-size: must be >= 1, got {shard_size}")
    groups: dict[Any, list[int]] = {}
    for i, p in enumerate(problems):
        if p is not None:
            groups.setdefault(shape_key(p, separable), []).append(i)
    shards: list[Shard] = []
    for members in groups.values():
        width = min(shard_size, len(members))
        for k in range(0, len(members), width):
            shards.append(Shard(len(shards), tuple(members[k : k + width]), width))
    return shards


# --------------------------------------------------------------------------------------
# The vmapped programs
# --------------------------------------------------------------------------------------


def _search_program(
    algorithm: Any,
    key: Array,
    cost_fns: Any,
    lower: Float[Array, "B d"],
    upper: Float[Array, "B d"],
    settings: Any,
    control: Control,
    n_samples: int,
    n_chains: int,
    n_pad: int,
) -> Any:
    def one(cost_fn: Any, lo: Array, hi: Array) -> Any:
        return fused_program(
            algorithm, key, cost_fn, None, lo, hi, settings, control, n_samples, n_chains,
            n_pad, True, None,
        )  # fmt: skip

    return eqx.filter_vmap(one)(cost_fns, lower, upper)


def _polish_program(
    residual_fns: Any,
    starts: Float[Array, "B K d"],
    lower: Float[Array, "B d"],
    upper: Float[Array, "B d"],
    settings: RefineSettings,
) -> Any:
    one = lambda r, x0s, lo, hi: refine_batch(r, x0s, lo, hi, settings)  # noqa: E731
    return eqx.filter_vmap(one)(residual_fns, starts, lower, upper)


def _jacobian_program(residual_fns: Any, x: Float[Array, "B d"]) -> tuple[Array, Array]:
    def one(residual_fn: Any, theta: Array) -> tuple[Array, Array]:
        return residual_fn(theta), jax.jacfwd(residual_fn)(theta)

    return eqx.filter_vmap(one)(residual_fns, x)


_search = eqx.filter_jit(_search_program)
_polish = eqx.filter_jit(_polish_program)
_jacobian = eqx.filter_jit(_jacobian_program)
_exact = eqx.filter_jit(eqx.filter_vmap(lambda pr: projected(pr, jnp.zeros((0,)))))


def fit_shard(
    members: Sequence[Member], width: int, settings: IdentifySettings, number: int = 0
) -> list[FleetFit]:
    """Identify ``members`` (all of one :func:`shape_key`) as one program of ``width``
    lanes (``width ≥ len(members)``; the extra lanes repeat the last member). Pure:
    the same members, width and settings give the same fits, in any process.

    A failure of the whole shard (an error its programs raise) fails each of its members
    with that reason; a member's own failure (cost nowhere finite, σ not computable)
    fails that member only."""
    try:
        return _fit_shard(members, width, settings, number)
    except Exception as err:  # a shard must never take the fleet down with it
        reason = _one_line(err)
        return [failed(m, reason, shard=number) for m in members]


def _one_line(err: BaseException) -> str:
    if isinstance(err, FricjaxError):
        return str(err)
    where_ = traceback.extract_tb(err.__traceback__)[-1] if err.__traceback__ else None
    at = f" ({where_.filename.rsplit('/', 1)[-1]}:{where_.lineno})" if where_ else ""
    return f"{type(err).__name__}: {err}{at}".replace("\n", " ")


def _searched(
    lanes: Sequence[Problem], settings: IdentifySettings
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]:
    """The annealing search of every lane as one vmapped program: chain end points [W, C,
    d], their costs [W, C], levels run [W], evaluations per level [W, L], t0 [W], C."""
    separable = settings.separable
    spec = lanes[0].spec
    lo, hi = _search_box(lanes[0], separable)
    run = chain_setup(
        prng_key(settings.seed), lo, hi, settings.method, settings.anneal, settings.chains,
        None, None, spec.source,
    )  # fmt: skip
    anneal = run.settings
    control = Control(
        K=np.float64(anneal.K),
        rel_temps=relative_temperatures(anneal),
        t_min_rel=np.float64(anneal.t_min_rel),
        patience=np.int64(anneal.patience),
        rel_tol=np.float64(anneal.rel_tol),
        abs_tol=np.float64(anneal.abs_tol),
    )
    boxes = [_search_box(p, separable) for p in lanes]
    out = _search(
        run.algorithm,
        run.key,
        stack_trees([_search_cost(p, separable) for p in lanes]),
        np.stack([b[0] for b in boxes]),
        np.stack([b[1] for b in boxes]),
        device_settings(anneal),
        control,
        anneal.n_temperature_samples,
        run.n_chains,
        run.n_pad,
    )
    out = jax.device_get(out)
    n_chains = run.n_chains
    chain_cost = np.asarray(out.states.best_cost)[:, :n_chains]
    # separable: the full vectors are the cost's auxiliary output at the end points
    chain_x = np.asarray(out.aux if separable else out.states.best_x)[:, :n_chains]
    levels = np.asarray(out.level)
    n_evals = np.asarray(out.n_evals)
    t0 = np.asarray(out.t0)
    return chain_x, chain_cost, levels, n_evals, t0, n_chains


def _fit_shard(
    members: Sequence[Member], width: int, settings: IdentifySettings, number: int
) -> list[FleetFit]:
    if settings.objective == "simulation":
        raise FricjaxError(
            "[search].objective: the fleet fits by equation error only "
            f"(got {settings.objective!r}; run `fricjax identify` per recording for it)"
        )
    problems = [m.problem for m in members]
    if any(p is None for p in problems) or not 1 <= len(problems) <= width:
        raise FricjaxError(f"fleet shard {number}: needs 1..{width} loaded recordings")
    lanes = [*problems, *[problems[-1]] * (width - len(problems))]
    separable = settings.separable
    if separable and separate(lanes[0]).n_nonlinear == 0:
        # every free parameter linear: one exact solve per recording, nothing to search
        # (identify does the same)
        projections = stack_trees([separate(p).full_theta.projection for p in lanes])
        theta, cost = jax.device_get(_exact(projections))
        chain_cost = np.asarray(cost)[:, None]
        chain_x = np.asarray(theta)[:, None, :]
        n_chains = 1
        levels = np.zeros(width, dtype=int)
        n_evals = np.zeros((width, 1), dtype=int)
        t0 = np.zeros(width)
    else:
        chain_x, chain_cost, levels, n_evals, t0, n_chains = _searched(lanes, settings)
    lower = np.stack([np.asarray(p.spec.lower, np.float64) for p in lanes])
    upper = np.stack([np.asarray(p.spec.upper, np.float64) for p in lanes])
    best_i = np.argmin(chain_cost, axis=1)
    search_x = chain_x[np.arange(width), best_i]
    search_cost = chain_cost[np.arange(width), best_i]
    best_x, best_cost = search_x.copy(), search_cost.copy()
    if settings.refine:
        top = min(settings.refine_top, n_chains)
        order = np.argsort(chain_cost, axis=1, kind="stable")[:, :top]
        starts = np.take_along_axis(chain_x, order[:, :, None], axis=1)
        # a start the search left outside the box (non-finite lane) is polished from the
        # box's centre instead; its result is discarded below unless it is finite and better
        safe = np.all(
            np.isfinite(starts) & (starts >= lower[:, None]) & (starts <= upper[:, None]), axis=2
        )
        starts = np.where(safe[:, :, None], starts, ((lower + upper) / 2)[:, None])
        residuals = stack_trees([p.residual_fn for p in lanes])
        polished = jax.device_get(
            _polish(residuals, starts, lower, upper, checked_refine_settings(settings.refiner))
        )
        costs = np.where(safe, np.asarray(polished.cost_after), np.inf)
        k = np.argmin(costs, axis=1)
        x_new = np.asarray(polished.x)[np.arange(width), k]
        c_new = costs[np.arange(width), k]
        keep = np.isfinite(c_new) & ~(c_new > search_cost)
        best_x = np.where(keep[:, None], x_new, search_x)
        best_cost = np.where(keep, c_new, search_cost)
    else:
        residuals = stack_trees([p.residual_fn for p in lanes])
    r_all, jac_all = jax.device_get(_jacobian(residuals, best_x))

    # the members' noise models at once: one program per shard for the pointwise ones
    n = len(members)
    noises = residual_noises(problems, list(best_x[:n]), [np.asarray(j) for j in jac_all[:n]])
    fits = []
    for i, member in enumerate(members):
        fits.append(
            _member_fit(
                member, settings, number, float(t0[i]), int(levels[i]),
                int(n_evals[i, levels[i] - 1]) if levels[i] else 0, chain_x[i], chain_cost[i],
                best_x[i], float(best_cost[i]), float(search_cost[i]), np.asarray(r_all[i]),
                np.asarray(jac_all[i]), noises[i],
            )
        )  # fmt: skip
    return fits


def _member_fit(
    member: Member,
    settings: IdentifySettings,
    number: int,
    t0: float,
    levels: int,
    n_evals: int,
    chain_x: np.ndarray,
    chain_cost: np.ndarray,
    x: np.ndarray,
    cost: float,
    cost_search: float,
    r: np.ndarray,
    jac: np.ndarray,
    noise: ResidualNoise | None,
) -> FleetFit:
    problem = member.problem
    assert problem is not None
    spec = problem.spec
    sha = problem.checksum
    try:
        checked_t0(t0, settings.anneal, spec.source)
        if not np.isfinite(cost):
            raise FricjaxError(f"{member.name}: cost not finite at the best point found")
        unc = uncertainty_at(
            r,
            jac,
            x,
            spec.lower,
            spec.upper,
            names=list(spec.free_names),
            noise=noise,
        )
    except FricjaxError as err:
        return failed(member, str(err), sha256=sha, shard=number)
    minima = cluster_minima(chain_x, chain_cost, spec.lower, spec.upper)
    return FleetFit(
        name=member.name,
        path=member.path,
        sha256=sha,
        order=member.order,
        status=OK,
        value=np.asarray(x, np.float64),
        std=np.asarray(unc.std, np.float64),
        rel_std=np.asarray(unc.rel_std, np.float64),
        flags=["; ".join(f) for f in unc.flags],
        fixed={p.name: float(p.init) for p in spec.params if not p.free},
        cost=cost,
        ems=cost / problem.n,
        cost_search=cost_search,
        levels=levels,
        n_evals=n_evals,
        refined=bool(settings.refine),
        cond=float(unc.cond),
        n_minima=len(minima),
        n=problem.n,
        shard=number,
    )


# --------------------------------------------------------------------------------------
# Running a fleet: in process, or one Dask task per shard
# --------------------------------------------------------------------------------------

#: ``on_shard(done_shards, total_shards, fits_so_far)`` after every finished shard.
OnShard = Callable[[int, int, list[FleetFit]], None]


def run_fleet(
    members: Sequence[Member],
    settings: IdentifySettings,
    *,
    shard_size: int | None = None,
    client: Any = None,
    retries: int = 3,
    on_shard: OnShard | None = None,
) -> list[FleetFit]:
    """Identify every member independently; one :class:`FleetFit` per member, in order.

    ``client``: a ``distributed.Client``: one task per shard (:func:`fit_shard`), each
    retried up to ``retries`` times if its worker dies; a finished shard's fits are
    gathered as soon as it finishes (a worker lost later costs nothing finished). Without
    a client the shards run in this process, one after another. Same shards either way
    (:func:`plan_shards`), hence the same numbers.
    """
    shard_size = default_shard_size() if shard_size is None else shard_size
    fits: list[FleetFit | None] = [None] * len(members)
    for i, m in enumerate(members):
        if m.problem is None:
            fits[i] = failed(m, m.reason or "not loaded")
    try:
        shards = plan_shards([m.problem for m in members], settings.separable, shard_size)
    except FricjaxError as err:
        if shard_size < 1:
            raise
        for i, m in enumerate(members):
            if fits[i] is None:
                fits[i] = failed(m, str(err))
        shards = []

    def place(shard: Shard, result: list[FleetFit], done: int) -> None:
        for i, fit in zip(shard.index, result, strict=True):
            fits[i] = fit
        if on_shard is not None:
            on_shard(done, len(shards), [f for f in fits if f is not None])

    def shard_members(shard: Shard) -> list[Member]:
        # to a worker only arrays and structure travel; in process the cached cost
        # functions of the problems are reused
        return [_fresh(members[i]) if client is not None else members[i] for i in shard.index]

    if client is None:
        for done, shard in enumerate(shards, start=1):
            place(shard, fit_shard(shard_members(shard), shard.width, settings, shard.number), done)
    else:
        from distributed import as_completed

        futures = {
            client.submit(
                _fit_shard_on_worker,
                shard_members(shard),
                shard.width,
                settings,
                shard.number,
                key=f"fricjax-fleet-shard-{shard.number}-{time.time_ns()}",
                retries=retries,
                pure=False,
            ): shard
            for shard in shards
        }
        for done, future in enumerate(as_completed(futures), start=1):
            shard = futures[future]
            try:
                result = future.result()
            except Exception as err:  # the shard's task failed for good (e.g. KilledWorker)
                result = [
                    failed(members[i], _one_line(err), shard=shard.number) for i in shard.index
                ]
            place(shard, result, done)
    return [f for f in fits if f is not None]


def _fit_shard_on_worker(
    members: Sequence[Member], width: int, settings: IdentifySettings, number: int
) -> list[FleetFit]:
    """:func:`fit_shard` in a Dask worker, with jax's persistent compilation cache on
    (:func:`fricjax.api.enable_compilation_cache`): every worker, and a worker restarted
    after a crash, loads the shard's programs instead of compiling them again."""
    from fricjax.programs import enable_compilation_cache

    enable_compilation_cache()
    return fit_shard(members, width, settings, number)


def _fresh(member: Member) -> Member:
    """The member with a problem free of cached jax objects: only its numpy arrays and
    static structure travel to a Dask worker (the worker builds its own cost functions)."""
    p = member.problem
    if p is None:
        return member
    fields = {f.name: getattr(p, f.name) for f in dataclasses.fields(p)}
    return member._replace(problem=Problem(**fields))


# --------------------------------------------------------------------------------------
# Loading a fleet
# --------------------------------------------------------------------------------------

RECORDING_SUFFIXES = (".h5", ".hdf5", ".csv")


def expand_paths(paths: Sequence[str | Path]) -> list[Path]:
    """Recordings named directly, and every ``.h5``/``.hdf5``/``.csv`` file directly inside a
    named directory (sorted by name); one line naming a path that does not exist."""
    out: list[Path] = []
    for raw in paths:
        path = Path(raw)
        if path.is_dir():
            out += sorted(q for q in path.iterdir() if q.suffix.lower() in RECORDING_SUFFIXES)
        elif path.exists():
            out.append(path)
        else:
            raise FricjaxError(f"{path}: no such recording or directory")
    if not out:
        raise FricjaxError(f"{', '.join(map(str, paths))}: no recordings (.h5, .hdf5, .csv)")
    return out


def order_value(path: Path, attr: str | None) -> str:
    """The value a recording is ordered by: root attribute ``attr`` of an HDF5 recording
    (e.g. a date or time stamp; "" when absent), else the file name."""
    if attr is None:
        return path.name
    if path.suffix.lower() not in (".h5", ".hdf5"):
        return ""
    try:
        with h5py.File(path, "r") as f:
            value = f.attrs.get(attr, "")
    except OSError:
        return ""
    return value.decode() if isinstance(value, bytes) else str(value)


def load_members(
    paths: Sequence[str | Path],
    config: Config,
    *,
    order_by: str | None = None,
    mass: float | None = None,
) -> list[Member]:
    """One :class:`Member` per recording of :func:`expand_paths`: its problem
    (:func:`fricjax.problem.build_problem`, the config's own preprocessing), or the one-line
    reason it could not be read or bound to the config."""
    members = []
    for path in expand_paths(paths):
        order = order_value(path, order_by)
        try:
            rec = read_recording(path, mass=mass)
            problem = build_problem(rec, config)
        except FricjaxError as err:
            members.append(Member(path.stem, str(path), order, None, str(err)))
            continue
        members.append(Member(rec.name or path.stem, str(path), order, problem))
    return members
