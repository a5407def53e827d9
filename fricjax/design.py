"""Design the next test: an input profile for the rig that tells rival fitted models apart.

A diagnosis can end with an ambiguity set: two or more models (the base plus one
catalogue term each, or the base alone) that explain the record about as well. One more
test can separate them if it moves the body where their predictions differ by more than
the noise *and* more than each model can absorb by refitting its parameters. This module
finds such a test for a rig driven by a measured input (``measured_input``: a force, a
motor current or a voltage the rig can be told to follow), by gradient through the
simulator, from many starts in one vmapped batch.

Criterion
---------
For rival models ``i`` and ``j`` fitted on the record (values ``θ̂_i``, ``θ̂_j``, Gauss–Newton
covariance ``Σ_j`` of ``j``'s free parameters), a new test with input ``u`` [n'] and noise
σ_x [m] on the position, suppose ``i`` is true. Refitting ``j`` on both records, linearised
about ``θ̂_j`` (the old record enters as the Gaussian prior ``N(θ̂_j, Σ_j)``), leaves the
expected (noise-free) likelihood-ratio statistic

    D_ij(u) = min_δ ‖Δ − J_j·δ‖²/σ_x² + δᵀ·Σ_j⁻¹·δ = Δᵀ·(σ_x²·I + J_j·Σ_j·J_jᵀ)⁻¹·Δ   [1]

with ``Δ = x_i(u; θ̂_i) − x_j(u; θ̂_j)`` [m, n'] the two simulated positions' difference and
``J_j = ∂x_j/∂θ_j`` [m/unit, n' × k_j]; the second form (Woodbury) is Buzzi-Ferraris and
Forzatti's divergence with the rival's prediction variance (1983), the first shows what it
means: what model ``j`` still misses after it has adapted to the new test as far as the
old record lets it. Parameter uncertainty of ``j`` thus discounts every difference ``j``
could fit away; that of the true model ``i`` only adds noise-like scatter (its expectation
is a constant ``tr``-term) and is left out. It is computed in scaled parameters
``z = (θ − θ̂)/σ_θ``::

    A = J_zᵀ·J_z + σ_x²·C⁻¹,  b = J_zᵀ·Δ,  D_ij = (ΔᵀΔ − bᵀ·A⁻¹·b)/σ_x²

(``J_z = J·diag(σ_θ)``, ``C`` the correlation matrix, its eigenvalues floored at 1e-8 so a
combination the record pins stays pinned). The design maximises ``min_{i≠j} D_ij`` (a soft
minimum over every ordered pair of the set, so that the new record separates each member
from each other, whichever is true) on the log scale ``log(1 + D)``.

Expected evidence: with ``i`` true, the pair of records should prefer ``i`` over ``j`` by

    ΔBIC_ij ≈ (E_j − E_i) + D_ij − (k_i − k_j)·ln(n + n')

(``E`` the output error on the record in σ_x², ``k`` the free parameters): linearised and
noise-free, so a number to plan with, not a promise.

Profile and limits
------------------
The input is a multisine through a saturating map, so the peak input limit holds exactly::

    u(t) = u_c + U·tanh(c_0 + Σ_{m=1..M} c_m·cos(2πmt/T) + s_m·sin(2πmt/T))

(``U`` [unit of u] the peak, ``u_c`` the middle of the allowed range, T [s] the duration,
M harmonics up to the record's input band: the frequency below which 99 % of the recorded
input's power lies, so the rig is asked for nothing faster than it already did). Travel
``[x_lo, x_hi]`` [m] and speed ``v_max`` [m/s] are limits on the simulated motion of every
rival: a quadratic penalty while optimising, then a hard check (a design any model drives
out of its limits by more than 1 % is not returned). By default the limits are what the
record itself did: its input range, its travel and its peak speed.

Optimiser: Adam (``init``/``step`` on a small pytree, ``lax.scan`` over steps, ``vmap`` over
starts); the starts are drawn from a PRNG key, so a seed reproduces a design.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import h5py
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from fricjax.diagnose.catalogue import candidate
from fricjax.errors import FricjaxError, where
from fricjax.model.simulate import simulate
from fricjax.model.system import Model
from fricjax.problem import Problem, input_signal

SUBSTEPS = 4  # RK4 sub-steps per sample, as the output-error fits use
# The optimiser only needs the criterion's direction: two sub-steps halve its cost (the
# returned design is judged at SUBSTEPS)
SEARCH_SUBSTEPS = 2
CORR_FLOOR = 1e-8  # smallest eigenvalue kept of a fit's correlation matrix
LIMIT_SLACK = 0.01  # a returned design keeps every model within its limits to 1 %
POWER_BAND = 0.99  # share of the recorded input's power that sets the band


@dataclass(frozen=True)
class Rival:
    """One fitted model of the set to separate.

    name: ``"base"`` or the catalogue effect it adds; model: its terms; params: every
    parameter [SI]; free: the fitted ones; cov: their covariance [k, k] (SI units², the
    order of ``free``); cost: its output error on the record [σ_x²]."""

    name: str
    model: Model
    params: Mapping[str, float]
    free: tuple[str, ...]
    cov: np.ndarray
    cost: float

    @property
    def k(self) -> int:
        return len(self.free)


class Limits(NamedTuple):
    """What the rig may do in the new test: peak input ``|u − u_mid|`` [unit of u] around
    ``u_mid``, travel ``[x_lo, x_hi]`` [m] and peak speed [m/s]."""

    u_mid: float
    u_peak: float
    x_lo: float
    x_hi: float
    speed: float


class Plan(NamedTuple):
    """The new test's sampling: n samples [s] every dt, starting at rest at x0 [m]."""

    n: int
    dt: float
    x0: float
    harmonics: int

    @property
    def t(self) -> np.ndarray:
        return np.arange(self.n) * self.dt

    @property
    def duration(self) -> float:
        return self.n * self.dt


class DesignSettings(NamedTuple):
    """starts: optimiser lanes (one vmapped batch); steps: Adam steps; rate: Adam's step
    on the profile coefficients (of order 1: tanh saturates near 2); temperature: of the
    soft minimum over pairs, on log(1 + D); penalty: weight of the mean squared relative
    excess of a limit, in units of log(1 + D): 1e4 makes a 1 % excess over the whole test
    cost as much as a factor e in D; seed: PRNG seed."""

    starts: int = 5
    steps: int = 30
    rate: float = 0.08
    temperature: float = 0.1
    penalty: float = 1e4
    seed: int = 0


class Design(NamedTuple):
    """A designed test and what it should show.

    t [s], u [unit of u], column: the profile and the recording column it goes in;
    rivals: the models' names ("base" or the term each adds); models: their terms;
    x [K, n] [m]: each model's predicted position; sigma_x [m];
    divergence [K, K]: D_ij (eq. [1]; row i true, column j rival; diagonal 0);
    expected_delta_bic [K, K]: ΔBIC_ij of the pair of records; standard: for standard
    tests of the same duration and peak input (:func:`standard_inputs`), by name, their
    ``separation`` (D's least off-diagonal value) and ``limit_violation``, and standard_u
    their profiles [n]; limits, plan;
    violation: the largest relative excess of a limit by any model [1];
    origin: :data:`DESIGNED`, or the standard test that separated best (returned as it is)."""

    t: np.ndarray
    u: np.ndarray
    column: str
    rivals: tuple[str, ...]
    models: tuple[str, ...]
    x: np.ndarray
    sigma_x: float
    divergence: np.ndarray
    expected_delta_bic: np.ndarray
    standard: dict[str, dict[str, float]]
    standard_u: dict[str, np.ndarray]
    limits: Limits
    plan: Plan
    violation: float
    origin: str = "designed"

    @property
    def separation(self) -> float:
        """min_{i≠j} D_ij: the least expected evidence between any two members [1]."""
        return _min_off_diagonal(self.divergence)

    def as_json(self) -> dict:
        k = len(self.rivals)
        pairs = [
            {
                "true": self.rivals[i],
                "rival": self.rivals[j],
                "divergence": float(self.divergence[i, j]),
                "expected_delta_bic": float(self.expected_delta_bic[i, j]),
            }
            for i in range(k)
            for j in range(k)
            if i != j
        ]
        return {
            "for": "discriminate",
            "rivals": list(self.rivals),
            "models": list(self.models),
            **_about_the_test(self.column, self.plan, self.sigma_x, self.limits, self.violation),
            "origin": self.origin,
            "separation": self.separation,
            "pairs": pairs,
            "standard_tests": self.standard,
            "criterion": "min over ordered pairs of the expected LR after refitting the "
            "rival on both records (Buzzi-Ferraris divergence with the rival's parameter "
            "covariance), linearised, noise-free",
        }


def _about_the_test(
    column: str, plan: Plan, sigma: float, limits: Limits, violation: float
) -> dict[str, object]:
    """What every designed test's JSON says of the test itself."""
    return {
        "column": column,
        "duration_s": plan.duration,
        "dt_s": plan.dt,
        "harmonics": plan.harmonics,
        "sigma_x_m": sigma,
        "limits": limits._asdict(),
        "limit_violation": violation,
    }


def _min_off_diagonal(d: np.ndarray) -> float:
    k = d.shape[0]
    return float(np.min(d[~np.eye(k, dtype=bool)])) if k > 1 else math.nan


# -- reading the rivals from a diagnosis ------------------------------------------------


def read_rivals(
    folder: str | Path, problem: Problem, names: Sequence[str] | None = None
) -> tuple[list[Rival], float]:
    """The rival models of one diagnosis step from a diagnosis folder's ``models.h5``, and
    σ_x [m].

    ``names``: the models to separate (``"base"`` for the step's starting model, else
    catalogue effects), from the last step that fitted them all (its base holds the terms
    named before it); None: the first
    ambiguity set of ``diagnosis.json`` (the named term and its alternatives), from the
    step that named it. ``problem``: the record and config the diagnosis ran on (its base
    model is rebuilt with each fit's catalogue terms)."""
    folder = Path(folder)
    path = folder / "models.h5"
    if not path.is_file():
        raise FricjaxError(f"{where(path)}: no such file (is {folder} a diagnosis folder?)")
    with h5py.File(path, "r") as f:
        if f.attrs.get("format") != "fricjax-diagnosis-models-v1" or "steps" not in f:
            raise FricjaxError(
                f"{where(path)}: not a diagnosis models file with its steps (rerun "
                "fricjax diagnose with this version)"
            )
        sigma = float(f.attrs["sigma_x_m"])
        steps = [f["steps"][k] for k in sorted(f["steps"], key=int)]
        if names is None:
            named, names = ambiguity_set(folder / "diagnosis.json")
            group = next(g for g in steps if g.attrs["named"] == named)
        else:
            group = _step_for(steps, names, path)
        return [_rival(group[n], n, problem, path) for n in names], sigma


def ambiguity_set(diagnosis_json: Path) -> tuple[str, list[str]]:
    """(named term, [it, *its alternatives]) of the first finding with alternatives."""
    try:
        findings = json.loads(diagnosis_json.read_text(encoding="utf-8"))["findings"]
    except (OSError, ValueError, KeyError) as e:
        raise FricjaxError(f"{where(diagnosis_json)}: unreadable ({e})") from None
    for finding in findings:
        if finding.get("alternatives"):
            named = finding["effect"]
            return named, [named, *(a["effect"] for a in finding["alternatives"])]
    raise FricjaxError(
        f"{where(diagnosis_json)}: the diagnosis names no ambiguity set; give the models "
        "to separate with --candidates (e.g. base,stribeck)"
    )


def _step_for(steps: list, names: Sequence[str], path: Path) -> h5py.Group:
    # the last step that fitted them all: its base holds every term named before it
    for g in reversed(steps):
        if all(n in g for n in names):
            return g
    have = sorted({n for g in steps for n in g})
    raise FricjaxError(
        f"{where(path, 'steps')}: no step fitted all of {', '.join(names)} "
        f"(fitted: {', '.join(have)})"
    )


def _rival(g: h5py.Group, name: str, problem: Problem, path: Path) -> Rival:
    model, spec = problem.model, problem.spec
    for effect in json.loads(g.attrs["active"]):
        model, spec = candidate(effect).extend(model, spec, problem)
    names = [n.decode() if isinstance(n, bytes) else str(n) for n in g["names"][()]]
    values = np.asarray(g["values"][()], dtype=np.float64)
    free = np.asarray(g["free"][()], dtype=bool)
    if sorted(names) != sorted(spec.names):
        raise FricjaxError(
            f"{where(path, g.name)}: parameters {', '.join(names)} do not match the "
            f"config's model {model.name} (diagnosed with another config?)"
        )
    return Rival(
        name=name,
        model=model,
        params=dict(zip(names, values.tolist(), strict=True)),
        free=tuple(n for n, fr in zip(names, free, strict=True) if fr),
        cov=np.asarray(g["cov"][()], dtype=np.float64),
        cost=float(g.attrs["cost"]),
    )


# -- the record's own limits and band ---------------------------------------------------


def input_band(u: Float[np.ndarray, " n"], dt: float, share: float = POWER_BAND) -> float:
    """The frequency [Hz] below which ``share`` of the detrended input's power lies."""
    y = np.asarray(u, dtype=np.float64)
    y = y - np.mean(y)
    power = np.abs(np.fft.rfft(y)) ** 2
    f = np.fft.rfftfreq(y.size, dt)
    total = float(np.sum(power[1:]))
    if total <= 0:
        return float(f[1]) if f.size > 1 else 0.0
    cum = np.cumsum(power[1:]) / total
    return float(f[1:][np.searchsorted(cum, share)])


def record_limits(problem: Problem) -> Limits:
    """What the record did: its input range, its travel and its peak speed."""
    u = np.asarray(problem.drive_input, dtype=np.float64)
    lo, hi = float(np.min(u)), float(np.max(u))
    x = np.asarray(problem.x, dtype=np.float64)
    return Limits(
        u_mid=0.5 * (lo + hi),
        u_peak=0.5 * (hi - lo),
        x_lo=float(np.min(x)),
        x_hi=float(np.max(x)),
        speed=float(np.max(np.abs(problem.v))),
    )


def plan_for(problem: Problem, duration: float | None = None) -> Plan:
    """The new test at the record's sample rate: ``duration`` [s] (default the record's),
    from rest at the record's first position, harmonics up to the record's input band."""
    dt = float(problem.t[1] - problem.t[0])
    n = round((duration if duration is not None else problem.n * dt) / dt)
    if n < 16:
        raise FricjaxError(f"{where('design', 'duration')}: {n} samples; at least 16 needed")
    band = input_band(np.asarray(problem.drive_input), dt)
    harmonics = int(np.clip(math.floor(band * n * dt), 2, n // 4))
    return Plan(n=n, dt=dt, x0=float(problem.x[0]), harmonics=harmonics)


# -- the criterion -----------------------------------------------------------------------


def basis(plan: Plan) -> Float[np.ndarray, "n 2M+1"]:
    """The multisine's columns ``(1, cos 2πmt/T …, sin 2πmt/T …)``, m = 1..M."""
    t = plan.t
    phase = 2 * np.pi * np.outer(t, np.arange(1, plan.harmonics + 1)) / plan.duration
    return np.column_stack([np.ones(plan.n), np.cos(phase), np.sin(phase)])


def profile(c: Float[Array, " 2M+1"], plan: Plan, limits: Limits) -> Float[Array, " n"]:
    """``u(t)`` [unit of u] of coefficients ``c = (c_0, c_1..c_M, s_1..s_M)`` (module
    docstring, "Profile and limits")."""
    return limits.u_mid + limits.u_peak * jnp.tanh(jnp.asarray(basis(plan)) @ c)


def project(u: Float[np.ndarray, " n"], plan: Plan, limits: Limits) -> np.ndarray:
    """The coefficients whose profile is nearest ``u`` (least squares on artanh of the
    scaled input, clipped at ±0.98 of the peak so saturated samples stay finite)."""
    y = np.clip((np.asarray(u) - limits.u_mid) / limits.u_peak, -0.98, 0.98)
    return np.linalg.lstsq(basis(plan), np.arctanh(y), rcond=None)[0]


class Scaled(NamedTuple):
    """A rival in the scaled parameters z: values of every parameter, the free ones' names,
    their σ_θ [k] and σ_x²·C⁻¹ [k, k] (the old record's information on z, times σ_x²)."""

    params: dict[str, Array]
    free: tuple[str, ...]
    std: Array
    prior: Array


def scale_rival(r: Rival, sigma: float) -> Scaled:
    std = np.sqrt(np.clip(np.diag(r.cov), 0.0, None))
    # a parameter the record does not determine (σ = inf or nan) is left to the new test:
    # a σ a million times its value makes its prior precision nil without overflowing z
    value = np.array([abs(r.params[n]) for n in r.free], dtype=np.float64)
    loose = ~np.isfinite(std)
    std = np.where(loose, 1e6 * np.maximum(value, 1e-9), std)
    safe = np.where(std > 0, std, 1.0)
    corr = np.where(loose[:, None] | loose[None, :], 0.0, r.cov) / np.outer(safe, safe)
    np.fill_diagonal(corr, 1.0)
    w, v = np.linalg.eigh(0.5 * (corr + corr.T))
    prior = (v / np.maximum(w, CORR_FLOOR)) @ v.T * sigma**2
    return Scaled(
        {k: jnp.asarray(val, dtype=jnp.float64) for k, val in r.params.items()},
        r.free,
        jnp.asarray(std),
        jnp.asarray(prior),
    )


def _trajectory(
    model: Model,
    s: Scaled,
    z: Float[Array, " k"],
    u: Float[Array, " n"],
    plan: Plan,
    substeps: int = SUBSTEPS,
) -> tuple[Float[Array, " n"], Float[Array, " n"]]:
    p = dict(s.params)
    for i, name in enumerate(s.free):
        p[name] = s.params[name] + s.std[i] * z[i]
    t = jnp.arange(plan.n) * plan.dt
    traj = simulate(model, p, t, plan.x0, 0.0, u, substeps=substeps)
    return traj.x, traj.v


def responses(
    rivals: Sequence[Rival],
    scaled: Sequence[Scaled],
    u: Array,
    plan: Plan,
    substeps: int = SUBSTEPS,
) -> tuple[list[Array], list[Array], list[Array]]:
    """Each rival's position [n], velocity [n] and scaled Jacobian J_z [n, k] on ``u``.

    A gradient in ``u`` runs back through the Jacobians too: how much a rival can absorb
    depends on the input as much as the difference does (holding J_z fixed gave a gradient
    of the wrong sign on the example axis, against central differences)."""
    xs, vs, js = [], [], []
    for r, s in zip(rivals, scaled, strict=True):
        z0 = jnp.zeros(len(s.free))

        def pos(z: Array, r: Rival = r, s: Scaled = s) -> Array:
            return _trajectory(r.model, s, z, u, plan, substeps)[0]

        x, v = _trajectory(r.model, s, z0, u, plan, substeps)
        xs.append(x)
        vs.append(v)
        js.append(jax.jacfwd(pos)(z0) if s.free else jnp.zeros((plan.n, 0)))
    return xs, vs, js


def divergence(
    xs: Sequence[Array], js: Sequence[Array], scaled: Sequence[Scaled], sigma: float
) -> Float[Array, "K K"]:
    """D_ij of eq. [1] for every ordered pair (row i true, column j rival), diagonal 0."""
    k = len(xs)
    rows = []
    for i in range(k):
        row = []
        for j in range(k):
            if i == j:
                row.append(jnp.zeros(()))
                continue
            delta = xs[i] - xs[j]
            jz = js[j]
            a = jz.T @ jz + scaled[j].prior
            b = jz.T @ delta
            absorbed = b @ jnp.linalg.solve(a, b) if jz.shape[1] else 0.0
            row.append(jnp.maximum(delta @ delta - absorbed, 0.0) / sigma**2)
        rows.append(jnp.stack(row))
    return jnp.stack(rows)


def _excess(xs: Sequence[Array], vs: Sequence[Array], limits: Limits) -> Array:
    """[K, n] the largest relative excess of travel or speed at each sample (0 inside)."""
    span = max(limits.x_hi - limits.x_lo, 1e-12)
    out = []
    for x, v in zip(xs, vs, strict=True):
        travel = jnp.maximum(x - limits.x_hi, 0.0) + jnp.maximum(limits.x_lo - x, 0.0)
        speed = jnp.maximum(jnp.abs(v) - limits.speed, 0.0) / max(limits.speed, 1e-12)
        out.append(jnp.maximum(travel / span, speed))
    return jnp.stack(out)


def _objective(
    c: Array,
    rivals: Sequence[Rival],
    scaled: Sequence[Scaled],
    sigma: float,
    plan: Plan,
    limits: Limits,
    settings: DesignSettings,
) -> Array:
    """−(soft minimum over pairs of log(1 + D_ij)) + penalty: Adam minimises it."""
    u = profile(c, plan, limits)
    xs, vs, js = responses(rivals, scaled, u, plan, SEARCH_SUBSTEPS)
    d = divergence(xs, js, scaled, sigma)
    k = len(rivals)
    off = jnp.log1p(d[~np.eye(k, dtype=bool)])
    tau = settings.temperature
    softmin = -tau * jax.nn.logsumexp(-off / tau)
    excess = _excess(xs, vs, limits)
    return -softmin + settings.penalty * jnp.sum(jnp.mean(excess**2, axis=1))


# -- Adam as an init/step pair ----------------------------------------------------------


class AdamState(NamedTuple):
    """Adam's moments [P] and step count (Kingma & Ba 2015, β = 0.9, 0.999)."""

    m: Array
    v: Array
    count: Array


def adam_init(c: Array) -> AdamState:
    return AdamState(jnp.zeros_like(c), jnp.zeros_like(c), jnp.zeros((), jnp.int32))


def adam_step(c: Array, g: Array, state: AdamState, rate: float) -> tuple[Array, AdamState]:
    """One Adam update of ``c`` along the gradient ``g`` (minimising)."""
    b1, b2, eps = 0.9, 0.999, 1e-8
    count = state.count + 1
    m = b1 * state.m + (1 - b1) * g
    v = b2 * state.v + (1 - b2) * g * g
    m_hat = m / (1 - b1**count)
    v_hat = v / (1 - b2**count)
    # a non-finite gradient (a start whose motion diverges) leaves the lane where it is
    step = jnp.where(jnp.isfinite(g), rate * m_hat / (jnp.sqrt(v_hat) + eps), 0.0)
    return c - step, AdamState(m, v, count)


# -- the design -------------------------------------------------------------------------


def commanded_input(problem: Problem) -> str:
    """The recording column a new test commands (``u``, or ``F`` for a model driven by the
    measured force); an error for a model whose drive is not a recorded input."""
    column = input_signal(problem.model)
    if column is None:
        raise FricjaxError(
            f"{where('design', 'model')}: {problem.model.name} has no measured input "
            "(measured_input) to design; a modelled drive (the seed's harmonic_drive) "
            "cannot be commanded"
        )
    return column


def design(
    problem: Problem,
    rivals: Sequence[Rival],
    sigma: float,
    *,
    limits: Limits | None = None,
    duration: float | None = None,
    settings: DesignSettings | None = None,
) -> Design:
    """The input profile that best separates ``rivals`` (module docstring) on a rig driven
    by ``problem``'s measured input; σ_x [m] the record's position noise."""
    settings = settings or DesignSettings()
    column = commanded_input(problem)
    if len(rivals) < 2:
        raise FricjaxError(f"{where('design', 'candidates')}: at least two models to separate")
    limits = limits or record_limits(problem)
    plan = plan_for(problem, duration)
    scaled = [scale_rival(r, sigma) for r in rivals]

    def loss(c: Array) -> Array:
        return _objective(c, rivals, scaled, sigma, plan, limits, settings)

    assess = _assessor(rivals, scaled, sigma, plan, limits)

    def score(u: np.ndarray) -> tuple[float, float]:
        d, _, violation = assess(u)
        return _min_off_diagonal(d), violation

    best, origin, standard = _optimise(loss, score, problem, plan, limits, settings)
    d, xs, violation = assess(best)
    cost = np.array([r.cost for r in rivals])
    k = np.array([r.k for r in rivals], dtype=np.float64)
    dbic = (
        (cost[None, :] - cost[:, None])
        + d
        - (k[:, None] - k[None, :]) * math.log(problem.n + plan.n)
    )
    np.fill_diagonal(dbic, 0.0)
    return Design(
        t=plan.t,
        u=best,
        column=column,
        rivals=tuple(r.name for r in rivals),
        models=tuple(r.model.name for r in rivals),
        x=xs,
        sigma_x=sigma,
        divergence=d,
        expected_delta_bic=dbic,
        standard={name: _standard(assess(u)) for name, u in standard.items()},
        standard_u=standard,
        limits=limits,
        plan=plan,
        violation=violation,
        origin=origin,
    )


#: Where a returned test came from when the optimiser's profile won (else a standard test's
#: name, :func:`standard_inputs`).
DESIGNED = "designed"


def _optimise(
    loss: Callable[[Array], Array],
    score: Callable[[np.ndarray], tuple[float, float]],
    problem: Problem,
    plan: Plan,
    limits: Limits,
    settings: DesignSettings,
) -> tuple[np.ndarray, str, dict[str, np.ndarray]]:
    """Adam on ``loss`` of the profile's coefficients from ``settings.starts`` lanes in one
    vmapped batch; returns the input [n] with the best ``score`` (higher is better) among
    the optimised profiles and the standard inputs within the limits (``score``'s second
    value ≤ :data:`LIMIT_SLACK`), where it came from (:data:`DESIGNED` or a standard
    test's name), and the standard inputs (:func:`standard_inputs`, and the chirp scaled
    down to keep the limits, :func:`_held`), whose projections are the first starts."""
    grad = jax.value_and_grad(loss)

    def run(c0: Array) -> Array:
        def body(carry: tuple[Array, AdamState], _: None) -> tuple:
            c, state = carry
            _, g = grad(c)
            return adam_step(c, g, state, settings.rate), None

        (c, _), _ = jax.lax.scan(body, (c0, adam_init(c0)), None, length=settings.steps)
        return c

    standard = standard_inputs(problem, plan, limits)
    standard["chirp within limits"] = _held(standard["chirp"], limits, score)
    # the standard tests, projected onto the profile, are starts: the design then begins
    # where a test engineer would and only moves where the criterion gains
    given = np.stack([project(u, plan, limits) for u in standard.values()])[: settings.starts]
    width = 2 * plan.harmonics + 1
    drawn = jax.random.normal(jax.random.key(settings.seed), (settings.starts - len(given), width))
    starts = jnp.concatenate([jnp.asarray(given), drawn / math.sqrt(plan.harmonics)])
    coefs = jax.jit(jax.vmap(run))(starts)
    us = np.asarray(jax.vmap(lambda c: profile(c, plan, limits))(coefs))
    found = []
    # the standard tests themselves compete: a profile of M harmonics cannot hold a chirp
    # whose band is wider, and the test handed to the user must never be worse than one
    # it is compared with
    candidates = [*((DESIGNED, u) for u in us), *standard.items()]
    for origin, u in candidates:
        value, violation = score(u)
        if violation <= LIMIT_SLACK and math.isfinite(value):
            found.append((value, origin, u))
    if not found:
        raise FricjaxError(
            f"{where('design', 'limits')}: no start kept every model within the travel and "
            "speed limits; widen --limits or shorten --duration"
        )
    _, origin, best = max(found, key=lambda a: a[0])
    return best, origin, standard


def _held(
    u: np.ndarray,
    limits: Limits,
    score: Callable[[np.ndarray], tuple[float, float]],
    halvings: int = 12,
) -> np.ndarray:
    """``u`` scaled about the middle of the input range by the largest factor in (0, 1]
    (bisection, to 2⁻¹² of the range) under which every model keeps the travel and speed
    limits: the standard test a test engineer would run on this rig."""
    if score(u)[1] <= LIMIT_SLACK:
        return u
    lo, hi = 0.0, 1.0
    for _ in range(halvings):
        mid = 0.5 * (lo + hi)
        if score(limits.u_mid + mid * (u - limits.u_mid))[1] <= LIMIT_SLACK:
            lo = mid
        else:
            hi = mid
    return limits.u_mid + lo * (u - limits.u_mid)


def _standard(judged: tuple[np.ndarray, np.ndarray, float]) -> dict[str, float]:
    d, _, violation = judged
    return {"separation": _min_off_diagonal(d), "limit_violation": violation}


def _assessor(
    rivals: Sequence[Rival], scaled: Sequence[Scaled], sigma: float, plan: Plan, limits: Limits
) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, float]]:
    """``u`` [n] -> (D [K, K], the models' positions [K, n], the largest relative excess of
    a limit), compiled once for every profile judged."""

    @jax.jit
    def judge(u: Array) -> tuple[Array, Array, Array]:
        xs, vs, js = responses(rivals, scaled, u, plan)
        d = divergence(xs, js, scaled, sigma)
        return d, jnp.stack(xs), jnp.max(_excess(xs, vs, limits))

    def assess(u: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        d, xs, violation = judge(jnp.asarray(u, dtype=jnp.float64))
        return np.asarray(d), np.asarray(xs), float(violation)

    return assess


def standard_inputs(problem: Problem, plan: Plan, limits: Limits) -> dict[str, np.ndarray]:
    """Standard tests of the same duration and peak input: a linear chirp from 1/T to the
    record's input band, and the record's own input (tiled or cut to the duration)."""
    t = plan.t
    f1 = plan.harmonics / plan.duration
    f0 = 1.0 / plan.duration
    chirp = limits.u_mid + limits.u_peak * np.sin(
        2 * np.pi * (f0 * t + 0.5 * (f1 - f0) * t**2 / plan.duration)
    )
    u = np.asarray(problem.drive_input, dtype=np.float64)
    again = np.resize(u, plan.n)
    return {
        "chirp": chirp,
        "record's input": np.clip(
            again, limits.u_mid - limits.u_peak, limits.u_mid + limits.u_peak
        ),
    }


# -- a test for precision: determine what the record does not ---------------------------


class StandardPrecision(NamedTuple):
    """What a standard test would give (``design --for identify``): each free parameter's σ
    after it [k], the focus' shrink and the largest relative excess of a limit."""

    sigma_after: np.ndarray
    shrink: float
    limit_violation: float


class PrecisionDesign(NamedTuple):
    """A test designed to determine parameters (``design --for identify``).

    t [s], u [unit of u], column: the profile; model: its terms; x [1, n] [m]: the model's
    predicted position; sigma_x [m]; names: the free parameters; focus: those the design
    targets; value [k]: their identified values; sigma_before [k]: their σ from the record;
    sigma_after [k]: the σ expected from the record and the new test together; shrink:
    the focus' uncertainty ellipsoid after, relative to now, as the geometric mean of its
    axes (det ratio^(1/2k), the D_s criterion in words); standard: for the standard tests
    (:func:`standard_inputs`), by name, ``sigma_after`` [k], ``shrink`` and
    ``limit_violation``; limits, plan; violation [1]; origin: as :attr:`Design.origin`."""

    t: np.ndarray
    u: np.ndarray
    column: str
    model: str
    x: np.ndarray
    sigma_x: float
    names: tuple[str, ...]
    focus: tuple[str, ...]
    value: np.ndarray
    sigma_before: np.ndarray
    sigma_after: np.ndarray
    shrink: float
    standard: dict[str, StandardPrecision]
    limits: Limits
    plan: Plan
    violation: float
    origin: str = "designed"

    def as_json(self) -> dict:
        return {
            "for": "identify",
            "model": self.model,
            "origin": self.origin,
            **_about_the_test(self.column, self.plan, self.sigma_x, self.limits, self.violation),
            "shrink": self.shrink,
            "focus": list(self.focus),
            "params": [
                {
                    "name": n,
                    "value": float(v),
                    "sigma_before": float(b),
                    "sigma_after": float(a),
                    **{
                        f"sigma_after_{k}": float(std.sigma_after[i])
                        for k, std in self.standard.items()
                    },
                }
                for i, (n, v, b, a) in enumerate(
                    zip(self.names, self.value, self.sigma_before, self.sigma_after, strict=True)
                )
            ],
            "criterion": "D_s-optimal: the smallest volume of the focus parameters' "
            "covariance after the record and the new test, linearised",
        }


def posterior_sigma(jz: Float[Array, "n k"], scaled: Scaled, sigma: float) -> Float[Array, " k"]:
    """σ [SI] of each free parameter after the record and a test with scaled sensitivity
    ``jz``: ``σ_θ·√(σ_x²·(M⁻¹)_ii)``, ``M = J_zᵀJ_z + σ_x²·C⁻¹`` (the record's information on
    z plus the test's, times σ_x²; with J_z = 0 it gives back σ_θ)."""
    m = jz.T @ jz + scaled.prior
    return scaled.std * sigma * jnp.sqrt(jnp.diag(jnp.linalg.inv(m)))


def _focus_logdet(jz: Array, scaled: Scaled, focus: np.ndarray) -> Array:
    """log det of the focus parameters' block of M⁻¹ (D_s criterion; minimised)."""
    m = jz.T @ jz + scaled.prior
    inv = jnp.linalg.inv(m)
    return jnp.linalg.slogdet(inv[np.ix_(focus, focus)])[1]


def design_precision(
    problem: Problem,
    model: Rival,
    sigma: float,
    focus: Sequence[str],
    *,
    limits: Limits | None = None,
    duration: float | None = None,
    settings: DesignSettings | None = None,
) -> PrecisionDesign:
    """The input profile that best determines ``focus`` (free parameters of ``model``, the
    identified model with its covariance) in a new test, D_s-optimal: it minimises the
    volume of their joint covariance after the record and the test, linearised about the
    identified values (the record enters as the prior ``N(θ̂, Σ)``, as in eq. [1])."""
    settings = settings or DesignSettings()
    column = commanded_input(problem)
    unknown = [n for n in focus if n not in model.free]
    if unknown or not focus:
        raise FricjaxError(
            f"{where('design', 'focus')}: {', '.join(unknown) or 'nothing'} is not a free "
            f"parameter of the identified model ({', '.join(model.free)})"
        )
    limits = limits or record_limits(problem)
    plan = plan_for(problem, duration)
    scaled = scale_rival(model, sigma)
    idx = np.array([model.free.index(n) for n in focus])

    def loss(c: Array) -> Array:
        u = profile(c, plan, limits)
        xs, vs, js = responses([model], [scaled], u, plan, SEARCH_SUBSTEPS)
        excess = _excess(xs, vs, limits)
        penalty = settings.penalty * jnp.sum(jnp.mean(excess**2, axis=1))
        return _focus_logdet(js[0], scaled, idx) + penalty

    @jax.jit
    def judge(u: Array) -> tuple[Array, Array, Array, Array]:
        xs, vs, js = responses([model], [scaled], u, plan)
        return (
            posterior_sigma(js[0], scaled, sigma),
            _focus_logdet(js[0], scaled, idx),
            jnp.stack(xs),
            jnp.max(_excess(xs, vs, limits)),
        )

    def score(u: np.ndarray) -> tuple[float, float]:
        _, logdet, _, violation = judge(jnp.asarray(u))
        return -float(logdet), float(violation)

    best, origin, standard = _optimise(loss, score, problem, plan, limits, settings)
    after, logdet, xs, violation = judge(jnp.asarray(best))
    before = np.sqrt(np.diag(model.cov))
    now = float(_focus_logdet(jnp.zeros((1, model.k)), scaled, idx))

    def shrink(value: Array) -> float:
        return math.exp((float(value) - now) / (2 * len(idx)))

    def summary(u: np.ndarray) -> StandardPrecision:
        s_after, value, _, over = judge(jnp.asarray(u))
        return StandardPrecision(np.asarray(s_after), shrink(value), float(over))

    return PrecisionDesign(
        t=plan.t,
        u=best,
        column=column,
        model=model.model.name,
        x=np.asarray(xs),
        sigma_x=sigma,
        names=model.free,
        focus=tuple(focus),
        value=np.array([model.params[n] for n in model.free]),
        sigma_before=before,
        sigma_after=np.asarray(after),
        shrink=shrink(logdet),
        standard={name: summary(u) for name, u in standard.items()},
        limits=limits,
        plan=plan,
        violation=float(violation),
        origin=origin,
    )
