"""Joint fit of several recordings of one axis: shared parameters, per-recording ones.

``K`` recordings (members) ``k = 1 … K`` of one axis, each preprocessed on its own (its own
rate, trim, filter state) into a :class:`~fricjax.problem.Problem`, share the config's
model. The config's ``[joint]`` table names the parameters that take one value per
recording (``per_recording = ["offset", "Fc"]``); every other free parameter is shared.
The joint free vector ``θ [D]`` holds the shared parameters (spec order), then each
per-recording parameter once per member, named ``NAME[k]`` (1-based, in the order the
recordings were given): ``offset[1], offset[2], Fc[1], Fc[2]``. Member ``k`` sees its own
free vector ``θ_k = θ[index_k]`` [d].

Cost. Each member's equation-error residual ``r_k(θ_k)`` [N] (seed eq. 5/11) is divided by
that recording's residual noise scale ``s_k`` [N]:

    r(θ) = [r_1(θ_1)/s_1, …, r_K(θ_K)/s_K]            [1]   (Σ n_k entries)
    E(θ) = Σ_k ‖r_k(θ_k)‖² / s_k²                      [1]

so every sample counts by its own information (the maximum-likelihood weighting of
experiments with unequal Gaussian noise): a longer recording weighs more only because it
holds more samples, and a noisy one counts less per sample instead of dominating the sum
with its larger forces errors.

Weights. ``s_k² = E_k / (n_k − d)``: the residual variance of recording ``k``'s own fit (the
same model, fitted to it alone; ``n_k`` residual entries, ``d`` free parameters). Why this
and not the x noise of :func:`fricjax.data.noise.estimate_noise` propagated to force: the
equation-error residual holds the x noise after two differentiations *and* the
preprocessing filter, the drive input's noise times its gain and the stick/slip samples
the sliding law misses, in proportions that depend on the recording's rate, filter and
motion; the own fit's residual variance measures their sum directly (relative error
≈ √(2/n_k), 4.5 % at 1000 samples). A recording whose model misses more physics then
weighs less, which is what its larger scatter around the model says. The own fits are
also the joint search's starting points (below).

Search and refine. The own fits (:func:`fricjax.identify.identify` on each member, the
separable path where the config asks for it) give ``K + 1`` joint starts: member ``k``'s
fit with everyone's own per-recording values (k = 1 … K), and the inverse-variance mean of
the shared values. Without ``separable`` the joint cost is also searched by the config's
annealing chains (:func:`fricjax.search.chains.run_chains`) over the joint box; the
``refine_top`` best chain end points and the ``K + 1`` starts are polished together by
Levenberg–Marquardt on ``r`` (:func:`fricjax.refine.refine_many`) and the best is kept.
With ``separable`` the own fits' variable-projection searches stand for the search (the
joint minimum lies where each recording's does, the shared values pulled together; a
projection over the block-structured joint basis is not built). σ for every joint
parameter is Gauss–Newton's from the joint Jacobian, ``C = σ̂² (JᵀJ)⁻¹`` with
``σ̂² = E/(Σn_k − D)`` ≈ 1 when the weights are right
(:func:`fricjax.refine.uncertainty_at`).

One recording is not a joint fit: :func:`fricjax.api.identify_recordings` hands it to
:func:`fricjax.identify.identify` unchanged.
"""

from __future__ import annotations

import json
import re
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from fricjax.config import Config
from fricjax.data.recording import Recording
from fricjax.errors import FricjaxError, where
from fricjax.identify import IdentifySettings, identify, prng_key, sigma_attrs
from fricjax.io.results import RunResult
from fricjax.limits import check_chains
from fricjax.problem import Problem
from fricjax.refine import cluster_minima, refine_many, uncertainty_at, value_and_jacobian
from fricjax.residual_noise import stacked_noise
from fricjax.search.chains import LevelInfo, run_chains

JOINT_TABLE = "joint"
JOINT_KEYS = ("per_recording",)
#: Run attribute holding the members (JSON list, one object per recording, in order).
MEMBERS_ATTR = "members"
#: The run attribute ``objective`` of a joint fit (its cost is dimensionless).
JOINT_OBJECTIVE = "joint equation error, each recording over its noise scale (fricjax.joint)"
_MEMBER_NAME = re.compile(r"^(?P<base>.+)\[(?P<k>[1-9][0-9]*)\]$")


def member_name(name: str, k: int) -> str:
    """The joint name of parameter ``name`` of member ``k`` (0-based): ``name[k+1]``."""
    return f"{name}[{k + 1}]"


def split_name(joint_name: str) -> tuple[str, int | None]:
    """``"Fc[2]" -> ("Fc", 1)`` (member index 0-based); ``"Fc" -> ("Fc", None)``."""
    m = _MEMBER_NAME.match(joint_name)
    return (m["base"], int(m["k"]) - 1) if m else (joint_name, None)


def member_params(params: Mapping[str, float], k: int) -> dict[str, float]:
    """Member ``k``'s (0-based) plain parameter mapping from a joint one: shared names as
    they are, ``NAME[k+1]`` as ``NAME``, other members' entries left out."""
    out: dict[str, float] = {}
    for key, value in params.items():
        base, j = split_name(key)
        if j is None or j == k:
            out[base] = float(value)
    return out


@dataclass(frozen=True)
class JointSettings:
    """The ``[joint]`` config table: ``per_recording``, the free parameters that take one
    value per recording (an offset, a Coulomb level per run); the others are shared."""

    per_recording: tuple[str, ...] = ()

    @classmethod
    def from_config(cls, cfg: Config) -> JointSettings:
        """Read and check ``[joint]``: known keys, names of free parameters only."""
        table = cfg.table(JOINT_TABLE)
        source = cfg.source or "config"
        for key in table:
            if key not in JOINT_KEYS:
                raise FricjaxError(
                    f"{where(source, f'[{JOINT_TABLE}].{key}')}: unknown key "
                    f"(known: {', '.join(JOINT_KEYS)})"
                )
        names = table.get("per_recording", [])
        loc = where(source, f"[{JOINT_TABLE}].per_recording")
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise FricjaxError(f"{loc}: must be a list of parameter names, got {names!r}")
        for name in names:
            if name == "mass" and not cfg.mass_in_spec:
                raise FricjaxError(
                    f"{loc}: 'mass' is not in [params]: each recording's own mass is used already"
                )
            if name not in cfg.spec:
                raise FricjaxError(
                    f"{loc}: {name!r} is not a parameter of the model (it takes: "
                    f"{', '.join(cfg.spec.names)})"
                )
            if not cfg.spec[name].free:
                raise FricjaxError(
                    f"{loc}: {name!r} is fixed in [params]; only a free parameter can take "
                    "one value per recording"
                )
        if len(set(names)) != len(names):
            dup = next(n for n in names if names.count(n) > 1)
            raise FricjaxError(f"{loc}: {dup!r} appears twice")
        return cls(per_recording=tuple(names))


def check_alike(recordings: Sequence[Recording], labels: Sequence[str]) -> None:
    """Refuse recordings of different kinds for one joint fit (one line naming the first
    that differs from the first recording): another axis, another set of recorded signals
    (drive input ``/u``, force ``/F``), another input unit, or the same recording twice."""
    first, name0 = recordings[0], labels[0]
    seen = {first.sha256(): name0}
    for rec, name in zip(recordings[1:], labels[1:], strict=True):
        if (rec.axis or "") != (first.axis or ""):
            raise FricjaxError(
                f"{where(name, 'attr axis')}: recordings of different kinds: {rec.axis!r}, "
                f"{name0} is {first.axis!r}; a joint fit takes recordings of one axis"
            )
        for signal in ("u", "F"):
            if (getattr(rec, signal) is None) != (getattr(first, signal) is None):
                has, lacks = (name, name0) if getattr(rec, signal) is not None else (name0, name)
                raise FricjaxError(
                    f"{where(name, '/' + signal)}: recordings of different kinds: {has} records "
                    f"/{signal}, {lacks} does not"
                )
        if rec.u is not None and rec.u_unit != first.u_unit:
            raise FricjaxError(
                f"{where(name, 'attr u_unit')}: recordings of different kinds: input in "
                f"{rec.u_unit!r}, {name0}'s in {first.u_unit!r}"
            )
        sha = rec.sha256()
        if sha in seen:
            raise FricjaxError(
                f"{where(name)}: the same recording as {seen[sha]} (sha256 {sha[:16]}); a joint "
                "fit needs distinct recordings"
            )
        seen[sha] = name


class JointCost(eqx.Module):
    """``θ [D] -> E(θ) = Σ_k w_k·cost_k(θ[index_k])`` [1] (module docstring), with
    ``w_k = 1/s_k²`` [1/N²]; pure, jit/vmap-able (a search cost)."""

    costs: tuple[eqx.Module, ...]
    weight: Float[Array, " K"]
    index: tuple[tuple[int, ...], ...] = eqx.field(static=True)

    def __call__(self, theta: Float[Array, " D"]) -> Float[Array, ""]:
        total = jnp.zeros((), theta.dtype)
        for k, (cost, idx) in enumerate(zip(self.costs, self.index, strict=True)):
            total = total + self.weight[k] * cost(theta[np.asarray(idx)])
        return total


class JointResidual(eqx.Module):
    """``θ [D] -> r(θ)`` [Σ n_k], each member's residual divided by its ``s_k`` [N]:
    ``r = [√w_1·r_1(θ[index_1]), …]`` (module docstring)."""

    residuals: tuple[eqx.Module, ...]
    weight: Float[Array, " K"]
    index: tuple[tuple[int, ...], ...] = eqx.field(static=True)

    def __call__(self, theta: Float[Array, " D"]) -> Float[Array, " n"]:
        parts = [
            jnp.sqrt(self.weight[k]) * res(theta[np.asarray(idx)])
            for k, (res, idx) in enumerate(zip(self.residuals, self.index, strict=True))
        ]
        return jnp.concatenate(parts)


@dataclass(frozen=True, eq=False)
class JointProblem:
    """``K`` member problems and the map between their free vectors and the joint one.

    Attributes:
        problems: the members, each preprocessed on its own (same model and free names).
        per_recording: the free parameters with one value per member.
        names, units: joint free parameters [D] (shared first, then ``NAME[k]``).
        lower, upper: their box [D] (a per-recording parameter keeps its config box).
        index: per member, the positions in θ [D] of its free vector [d].
        sigma: per member, the residual noise scale ``s_k`` [N] (module docstring).
    """

    problems: tuple[Problem, ...]
    per_recording: tuple[str, ...]
    names: tuple[str, ...]
    units: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    index: tuple[tuple[int, ...], ...]
    sigma: np.ndarray

    @property
    def n(self) -> int:
        """Residual entries over all members (``Σ n_k``, decimated lengths)."""
        return sum(p.n_residual for p in self.problems)

    @property
    def weight(self) -> np.ndarray:
        return 1.0 / self.sigma**2

    @property
    def cost_fn(self) -> JointCost:
        return JointCost(
            tuple(p.cost_fn for p in self.problems), jnp.asarray(self.weight), self.index
        )

    @property
    def residual_fn(self) -> JointResidual:
        return JointResidual(
            tuple(p.residual_fn for p in self.problems), jnp.asarray(self.weight), self.index
        )

    def theta(self, member_thetas: Sequence[np.ndarray], shared_from: int) -> np.ndarray:
        """Joint θ [D] from member free vectors [K, d]: per-recording entries from each
        member, shared ones from member ``shared_from``."""
        theta = np.empty(len(self.names))
        for k, (idx, x) in enumerate(zip(self.index, member_thetas, strict=True)):
            for pos, name, value in zip(idx, self.problems[k].spec.free_names, x, strict=True):
                if name in self.per_recording or k == shared_from:
                    theta[pos] = value
        return theta

    def fixed(self) -> dict[str, float]:
        """Fixed parameters: one entry when every member has the same value (the config's),
        ``NAME[k]`` per member otherwise (each recording's own mass)."""
        out: dict[str, float] = {}
        for p in self.problems[0].spec.params:
            if p.free:
                continue
            values = [float(q.spec[p.name].init) for q in self.problems]
            if all(v == values[0] for v in values):
                out[p.name] = values[0]
            else:
                out.update({member_name(p.name, k): v for k, v in enumerate(values)})
        return out


def joint_problem(
    problems: Sequence[Problem], per_recording: Sequence[str], sigma: Sequence[float]
) -> JointProblem:
    """Lay out the joint free vector of ``problems`` (module docstring); they come from one
    config, so their free parameters are the same names in the same order."""
    spec = problems[0].spec
    shared = [p for p in spec.free if p.name not in per_recording]
    own = [p for p in spec.free if p.name in per_recording]
    names = [p.name for p in shared] + [
        member_name(p.name, k) for p in own for k in range(len(problems))
    ]
    units = [p.unit for p in shared] + [p.unit for p in own for _ in problems]
    lower = [p.lower for p in shared] + [p.lower for p in own for _ in problems]
    upper = [p.upper for p in shared] + [p.upper for p in own for _ in problems]
    pos = {n: i for i, n in enumerate(names)}
    index = tuple(
        tuple(
            pos[member_name(n, k) if n in per_recording else n] for n in problems[k].spec.free_names
        )
        for k in range(len(problems))
    )
    return JointProblem(
        problems=tuple(problems),
        per_recording=tuple(per_recording),
        names=tuple(names),
        units=tuple(units),
        lower=np.asarray(lower, np.float64),
        upper=np.asarray(upper, np.float64),
        index=index,
        sigma=np.asarray(sigma, np.float64),
    )


def residual_scale(run: RunResult, problem: Problem) -> float:
    """``s_k = √(E_k/(n_k − d))`` [N] of a member's own equation-error fit ``run``."""
    dof = problem.n_residual - len(run.names)
    s2 = float(run.cost) / dof if dof > 0 else float("nan")
    if not (np.isfinite(s2) and s2 > 0.0):
        raise FricjaxError(
            f"{where(problem.source or problem.name)}: its own fit leaves no residual to weigh "
            f"it by (cost {run.cost:g} over {problem.n_residual} samples, {len(run.names)} "
            "parameters)"
        )
    return float(np.sqrt(s2))


def identify_joint(
    problems: Sequence[Problem],
    settings: IdentifySettings,
    joint: JointSettings,
    *,
    on_level: Callable[[LevelInfo], None] | None = None,
    on_member: Callable[[int, int, str], None] | None = None,
    label: str | None = None,
) -> RunResult:
    """Fit ``problems`` jointly (module docstring); a :class:`RunResult` over the joint
    parameters whose ``attrs["members"]`` (JSON) lists each recording's name, source,
    sha256, residual entries ``n``, weight scale ``sigma`` [N] and its EMS at the joint
    optimum [N²]. ``on_member(k, K, name)`` is called before each own fit."""
    if len(problems) < 2:
        raise FricjaxError("joint fit: needs at least two recordings")
    if settings.objective == "simulation":
        raise FricjaxError(
            "[search].objective: a joint fit minimises the equation error only; set "
            'objective = "equation" (or fit the recordings one at a time)'
        )
    # the own fits only weight the joint one: equation error, as the joint fit
    settings = replace(settings, objective="equation")
    start = time.perf_counter()
    own = []
    for k, problem in enumerate(problems):
        if on_member is not None:
            on_member(k, len(problems), problem.name)
        own.append(identify(problem, settings))
        if own[-1].attrs.get("interrupted"):
            # Ctrl-C in an own fit: no weights, so no joint fit to keep (nothing is written)
            raise KeyboardInterrupt
    sigma = [residual_scale(run, p) for run, p in zip(own, problems, strict=True)]
    jp = joint_problem(problems, joint.per_recording, sigma)
    d = len(jp.names)
    starts = _starts(jp, own)
    cost_fn = jp.cost_fn
    start_cost = np.asarray(_batch_cost(cost_fn, jnp.asarray(starts)))
    if settings.separable:
        chain_x, chain_cost = starts, start_cost
        per_chain = ("best_cost", "current_cost", "acceptance")
        traces = {k: np.zeros((0, len(starts))) for k in per_chain}
        traces.update({k: np.zeros(0) for k in ("temperature", "n_evals", "wall_time")})
        levels, t0, interrupted, polish = 0, 0.0, False, starts
        candidates, costs = starts, start_cost
    else:
        check_chains(settings.chains, jp.n, d, settings.anneal.max_levels, "identify (joint)")
        search = run_chains(
            prng_key(settings.seed),
            cost_fn,
            jp.lower,
            jp.upper,
            method=settings.method,
            settings=settings.anneal,
            n_chains=settings.chains,
            on_level=on_level,
            source=problems[0].spec.source,
        )
        chain_x, chain_cost = np.asarray(search.chain_x), np.asarray(search.chain_cost)
        traces = {k: np.asarray(v) for k, v in search.traces._asdict().items()}
        levels, t0, interrupted = search.levels_run, float(search.t0), bool(search.interrupted)
        top = np.argsort(chain_cost)[: min(settings.refine_top, chain_cost.size)]
        polish = np.concatenate([chain_x[top], starts])
        candidates = np.concatenate([chain_x, starts])
        costs = np.concatenate([chain_cost, start_cost])
    i = int(np.nanargmin(costs))
    best_x, cost_search = candidates[i], float(costs[i])
    best_cost, refined = cost_search, False
    residual = jp.residual_fn
    if settings.refine and not interrupted:
        out = refine_many(
            residual,
            polish,
            jp.lower,
            jp.upper,
            settings.refiner,
            fast_compile=settings.fast_compile,
        )
        xs, cs = np.asarray(out.x), np.asarray(out.cost_after)
        j = int(np.nanargmin(cs))
        if np.isfinite(cs[j]) and cs[j] <= best_cost:
            best_x, best_cost = xs[j], float(cs[j])
        refined = True
    wall = time.perf_counter() - start
    r, jac = value_and_jacobian(residual, best_x, fast_compile=settings.fast_compile)
    noise = stacked_noise(
        problems, [best_x[np.asarray(i)] for i in jp.index], jac, 1.0 / np.asarray(sigma)
    )
    unc = uncertainty_at(r, jac, best_x, jp.lower, jp.upper, names=list(jp.names), noise=noise)
    minima = cluster_minima(chain_x, chain_cost, jp.lower, jp.upper)
    members = []
    offset = 0
    for k, p in enumerate(problems):
        m = p.n_residual
        rk = r[offset : offset + m] * sigma[k]  # back to newtons
        offset += m
        members.append(
            {
                "name": p.name,
                "source": p.source,
                "sha256": p.checksum,
                "n": m,
                "sigma": sigma[k],
                "ems": float(np.mean(rk**2)),
                "own_ems": float(own[k].cost) / m,
            }
        )
    return RunResult(
        label=label or f"joint_{settings.method}",
        method=settings.method,
        names=list(jp.names),
        units=list(jp.units),
        value=np.asarray(best_x, np.float64),
        lower=jp.lower,
        upper=jp.upper,
        fixed=jp.fixed(),
        cost=best_cost,
        ems=best_cost / jp.n,
        cost_search=cost_search,
        ems_search=cost_search / jp.n,
        std=np.asarray(unc.std, np.float64),
        rel_std=np.asarray(unc.rel_std, np.float64),
        corr=np.asarray(unc.corr, np.float64).reshape(d, d),
        flags=["; ".join(f) for f in unc.flags],
        chain_x=chain_x,
        chain_cost=chain_cost,
        traces=traces,
        minima_x=np.array([m.x for m in minima]).reshape(len(minima), d),
        minima_cost=np.array([m.cost for m in minima], dtype=np.float64),
        minima_count=np.array([m.count for m in minima], dtype=np.int64),
        attrs={
            "seed": settings.seed,
            "n_chains": settings.chains if not settings.separable else len(starts),
            "schedule": settings.anneal.schedule,
            "alpha": settings.anneal.alpha,
            "steps_per_level": settings.anneal.steps_per_level,
            "levels": levels,
            "n_evals": int(traces["n_evals"][-1]) if levels else 0,
            "interrupted": interrupted,
            "refined": refined,
            "wall_time": wall,
            "t0": t0,
            "objective": JOINT_OBJECTIVE,
            "cond": float(unc.cond),
            **sigma_attrs(unc),
            "separable": settings.separable,
            "search_space": (
                f"joint ({d}-D over {len(problems)} recordings; "
                + (
                    "starts from each recording's separable fit)"
                    if settings.separable
                    else f"{settings.chains} chains + {len(starts)} starts from the own fits)"
                )
            ),
            "per_recording": json.dumps(list(joint.per_recording)),
            MEMBERS_ATTR: json.dumps(members),
        },
    )


@eqx.filter_jit
def _batch_cost(cost_fn: JointCost, theta: Float[Array, "B D"]) -> Float[Array, " B"]:
    return jax.vmap(cost_fn)(theta)


def _starts(jp: JointProblem, own: Sequence[RunResult]) -> np.ndarray:
    """``K + 1`` joint starts [K+1, D] from the members' own fits: member ``k``'s shared
    values (k = 1 … K), then their inverse-variance mean (plain mean where a σ is not
    finite), each with every member's own per-recording values; clipped into the box."""
    thetas = [np.asarray(run.value) for run in own]
    rows = [jp.theta(thetas, k) for k in range(len(own))]
    values = np.stack(thetas)  # [K, d]
    stds = np.stack([np.asarray(run.std) for run in own])
    ok = np.all(np.isfinite(stds) & (stds > 0), axis=0)
    w = np.where(ok, 1.0 / np.where(stds > 0, stds, 1.0) ** 2, 1.0)
    pooled = (w * values).sum(axis=0) / w.sum(axis=0)
    own_names = jp.problems[0].spec.free_names
    mixed = [
        np.where([n in jp.per_recording for n in own_names], theta, pooled) for theta in thetas
    ]
    rows.append(jp.theta(mixed, 0))
    return np.clip(np.stack(rows), jp.lower, jp.upper)


def is_joint(run: RunResult) -> bool:
    """Whether ``run`` is a joint fit (it lists its members)."""
    return MEMBERS_ATTR in run.attrs


def members_of(run: RunResult) -> list[dict[str, Any]]:
    """The members of a joint ``run`` (JSON attr ``members``), [] for a single fit."""
    if not is_joint(run):
        return []
    return list(json.loads(str(run.attrs[MEMBERS_ATTR])))
