"""A :class:`Problem` bundles what the equation-error cost needs, as arrays.

``residual(theta) = m·a − (F_p − F_f)`` over the preprocessed recording (seed eq. 5/11) and
``cost(theta) = Σ residual²`` are pure, jit- and vmap-able functions of the free-parameter
vector ``theta`` [d]. They are built once per problem and cached, so every search and
refinement stage reuses the same compiled function.

Uniform time base. A validated recording has a uniform ``t`` (trimming keeps it so; the
IDIM decimation acts on the residual, not on ``t``), which the problem splits once into a
:class:`~fricjax.model.term.TimeGrid` ``t_k = outer[j] + inner[r]`` and hands to the
terms as :class:`~fricjax.model.term.GridSignals`: the harmonic drive then takes
``cos/sin(ωt)`` by angle addition from ``J + R`` pairs (15 + 16 for the paper twin's 232
samples) instead of one pair per sample (:func:`fricjax.model.drive.phasor`). The cost
also lays the samples out as ``[J, R]`` (:class:`GridCost`) unless a term is stateful or
the residual decimated. Same numbers as the per-sample evaluation to rounding (≤ 1e-12
relative, tested; 1.6e-15 measured on the paper twin), ~1.4-1.7x the evaluations/s on
batches of 64-4096 θ (2 cores, measured in one process against the per-sample code).
Fixed parameters reach the terms as numpy scalars (:func:`named_static`), so a term may
specialise on them at trace time.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from fricjax.config import Config
from fricjax.data.decimate import antialias_kernel, decimate, decimated_length
from fricjax.data.preprocess import PreprocessSettings, derivatives
from fricjax.data.recording import Recording, require_mass
from fricjax.errors import FricjaxError, where
from fricjax.model.system import MASS, Model, cost
from fricjax.model.term import GridSignals, Signals, TimeGrid, time_grid
from fricjax.params import ParamSpec
from fricjax.programs import stored
from fricjax.units import axis_unit


def named_static(spec: ParamSpec, theta: Float[Array, " d"]) -> dict[str, Any]:
    """:meth:`ParamSpec.unflatten` with each fixed parameter as a numpy float64 scalar
    instead of a traced array: the same value, but a compile-time constant that a term may
    specialise on (e.g. a Stribeck exponent fixed at δ = 1 needs no ``exp(δ·log x)``)."""
    p = spec.unflatten(theta)
    for q in spec.params:
        if not q.free:
            p[q.name] = np.float64(q.init)
    return p


class EquationError(eqx.Module):
    """Equation-error residual ``m·a − (F_p − F_f)`` [N] over a recording (seed eq. 5/11).

    ``t, x, v, u, a`` [n]: the preprocessed recording; ``kernel`` [L], ``q``: decimation of
    the residual; ``grid``: the :class:`~fricjax.model.term.TimeGrid` of a uniform ``t``
    (passed to the terms as :class:`~fricjax.model.term.GridSignals`; the harmonic drive
    then needs J + R sines instead of n), ``None`` for the plain per-sample evaluation;
    ``rest`` [n]: samples where the model force is the stick/slip rule
    (:meth:`~fricjax.model.system.Model.rest_force`), ``None``: the sliding law everywhere
    (the seed's residual).
    """

    model: Model = eqx.field(static=True)
    spec: ParamSpec = eqx.field(static=True)
    t: Float[Array, " n"]
    x: Float[Array, " n"]
    v: Float[Array, " n"]
    u: Float[Array, " n"]
    a: Float[Array, " n"]

    kernel: Float[Array, " L"] | None = None
    q: int = eqx.field(static=True, default=1)
    grid: TimeGrid | None = None
    rest: Bool[Array, " n"] | None = None

    def __call__(self, theta: Float[Array, " d"]) -> Float[Array, " m"]:
        sig = GridSignals(self.t, self.x, self.v, self.u, self.grid)
        r = self.model.residual(named_static(self.spec, theta), sig, self.a, self.rest)
        # IDIM-LS: anti-alias filter + keep every q-th sample of the residual (= of every
        # regressor column and the force), fricjax.data.decimate
        return r if self.q == 1 else decimate(r, self.kernel, self.q)


class Cost(eqx.Module):
    """Seed eq. (11): ``Σ r²`` [N²] of an :class:`EquationError`."""

    residual: EquationError

    def __call__(self, theta: Float[Array, " d"]) -> Float[Array, ""]:
        return cost(self.residual(theta))


class GridCost(eqx.Module):
    """Seed eq. (11), ``Σ_k r_k²`` [N²], with the recording in the ``[J, R]`` layout of its
    :class:`~fricjax.model.term.TimeGrid` (sample ``k`` at ``[k // R, k % R]``).

    ``t, x, v, u, a`` [J, R]: the preprocessed recording arranged on the grid, the
    ``J·R − n`` entries past its end repeating the last sample; ``keep`` [J, R]: True on
    the ``n`` recorded samples (the residual is zeroed elsewhere, before squaring).
    Requires a model without stateful terms (:attr:`~fricjax.model.term.Term.stateful`)
    and an undecimated residual. Same sum as :class:`Cost` up to its order of summation; the
    layout lets XLA's CPU loop over ``r`` innermost with the grid's ``J + R`` sines held
    outside it (the harmonic drive then costs no sine per sample).
    """

    model: Model = eqx.field(static=True)
    spec: ParamSpec = eqx.field(static=True)
    t: Float[Array, "J R"]
    x: Float[Array, "J R"]
    v: Float[Array, "J R"]
    u: Float[Array, "J R"]
    a: Float[Array, "J R"]
    keep: Bool[Array, "J R"]
    grid: TimeGrid

    def __call__(self, theta: Float[Array, " d"]) -> Float[Array, ""]:
        sig = GridSignals(self.t, self.x, self.v, self.u, self.grid)
        r = self.model.residual(named_static(self.spec, theta), sig, self.a)
        return cost(jnp.where(self.keep, r, 0.0))


@stored
def _call(fn: eqx.Module, theta: Float[Array, " d"]) -> Array:
    return fn(theta)


@dataclass(frozen=True, eq=False)
class Problem:
    """Preprocessed signals + model + parameter specification.

    Attributes:
        model: the force model (terms).
        spec: parameters, ``mass`` included (fixed from the recording unless free).
        t, x, v, a, u: float64 arrays [n]: time [s], position [m], velocity [m/s],
            acceleration [m/s²], drive input [u_unit] (zeros when the rig records none).
        name: recording name; checksum: recording sha256; source: recording path.
        preprocess: the settings that made v and a from x (None: not known).
        window: ``(offset, n_parent)`` when these samples are the rows ``offset …
            offset + n − 1`` of a longer preprocessed record of ``n_parent`` samples (a
            held-out split): the noise of v and a at a cut end comes from samples beyond
            it, not from the record's end padding, and the whitener must know which.
            ``None``: the samples are a whole preprocessed record.
        rest: bool [n], samples at or near rest where the residual uses the stick/slip
            rule (:meth:`~fricjax.model.system.Model.rest_force`); set by the diagnosis
            from the noise level (|v| < 4·σ_v). ``None``: the seed's sliding law everywhere.
        axis: ``"linear"`` or ``"rotary"`` (the config's), for the units of what is said.
        drive: float64 [n], the model's recorded input at these samples *as recorded*
            (``u`` is filtered like ``m·a`` for the equation error when
            ``[preprocess].filter_input``): what drives a simulation of the record (output
            error, :attr:`drive_input`). ``None``: ``u`` itself.
        joins: the first sample of each recording after the first, where this problem is
            several recordings of one plant joined end to end (:func:`joined`); empty for
            one recording. The body's state jumps there: the output error's segments
            start afresh at a join (:func:`fricjax.output_error.segmentation`).
    """

    model: Model
    spec: ParamSpec
    t: np.ndarray
    x: np.ndarray
    v: np.ndarray
    a: np.ndarray
    u: np.ndarray
    name: str = ""
    checksum: str = ""
    source: str = ""
    preprocess: PreprocessSettings | None = None
    window: tuple[int, int] | None = None
    rest: np.ndarray | None = None
    axis: str = "linear"
    drive: np.ndarray | None = None
    joins: tuple[int, ...] = ()

    @property
    def n(self) -> int:
        return int(self.t.shape[0])

    @property
    def dt(self) -> float:
        """Sample step [s] (of the first recording where several are joined: each keeps its
        own clock, so ``t`` restarts at a join)."""
        k = self.joins[0] if self.joins else self.n
        return float((self.t[k - 1] - self.t[0]) / (k - 1)) if k > 1 else math.nan

    @property
    def drive_input(self) -> np.ndarray:
        """[n] the input a simulation of the record is driven by: the recorded input,
        unfiltered. The equation error's ``u`` is filtered like ``m·a`` so that the two
        sides of its force balance see one filter; a simulation integrates the force the
        body received, and a filtered input would hand it another (a test with content near
        the filter's cutoff loses or shifts it: tens of newtons on a designed multisine)."""
        return self.u if self.drive is None else self.drive

    @property
    def signals(self) -> Signals:
        """The recording as :class:`Signals` [n], without a grid (callers may reorder or
        select samples; :attr:`grid` is the grid to pass when they do not)."""
        return Signals(
            jnp.asarray(self.t), jnp.asarray(self.x), jnp.asarray(self.v), jnp.asarray(self.u)
        )

    def named(self, theta: Float[Array, " d"]) -> dict[str, Any]:
        return self.spec.unflatten(theta)

    @cached_property
    def residual_fn(self) -> EquationError:
        """``theta [d] -> residual [n]`` in newtons.

        An equinox Module holding the data as array leaves: jitted callers (search, refiner)
        reuse one compilation for every problem with the same model, spec and length.
        """
        return EquationError(
            self.model,
            self.spec.structural(),
            *(jnp.asarray(a) for a in (self.t, self.x, self.v, self.u, self.a)),
            kernel=None if self.q == 1 else jnp.asarray(antialias_kernel(self.q)),
            q=self.q,
            grid=self.grid,
            rest=None if self.rest is None else jnp.asarray(self.rest, dtype=bool),
        )

    @cached_property
    def grid(self) -> TimeGrid | None:
        """``t`` split for angle addition (:func:`~fricjax.model.term.time_grid`): ``None``
        unless ``t`` is uniform to a few roundings (any recording that passed validation,
        trimmed or not; decimation acts on the residual, not on ``t``)."""
        return time_grid(self.t)

    @property
    def q(self) -> int:
        """Decimation factor of the residual (``[preprocess].decimate``; 1 = none)."""
        return self.preprocess.decimate if self.preprocess is not None else 1

    @property
    def n_residual(self) -> int:
        """Length of the residual vector (``n``, or ``⌈n/q⌉`` when decimated)."""
        return decimated_length(self.n, self.q)

    @cached_property
    def cost_fn(self) -> Cost | GridCost:
        """``theta [d] -> Σ r²`` [N²] (seed eq. 11).

        A :class:`GridCost` when ``t`` has a grid, the residual is not decimated, no sample
        is marked at rest and no term is stateful
        (:attr:`~fricjax.model.term.Term.stateful`); otherwise :class:`Cost` of
        :attr:`residual_fn`. The two agree to rounding (order of summation and angle
        addition: ≤ 1e-12 relative, tested; measured 1.6e-15 on the paper twin).
        """
        grid = self.grid
        if (
            grid is None
            or self.q != 1
            or self.rest is not None
            or any(term.stateful for term in self.model.terms)
        ):
            return Cost(self.residual_fn)
        j, r = grid.outer.shape[0], grid.inner.shape[0]
        return GridCost(
            self.model,
            self.spec.structural(),
            *(jnp.asarray(grid.arrange(a)) for a in (self.t, self.x, self.v, self.u, self.a)),
            keep=jnp.asarray((np.arange(j * r) < self.n).reshape(j, r)),
            grid=grid,
        )

    def cost(self, theta: Float[Array, " d"]) -> float:
        return float(_call(self.cost_fn, jnp.asarray(theta, dtype=jnp.float64)))

    def residual(self, theta: Float[Array, " d"]) -> np.ndarray:
        """Residual [n] in newtons, as numpy (jitted evaluation)."""
        return np.asarray(_call(self.residual_fn, jnp.asarray(theta, dtype=jnp.float64)))

    def ems(self, theta: Float[Array, " d"]) -> float:
        """Error mean square ``cost/n`` [N²] (seed Table 4)."""
        return float(np.mean(self.residual(theta) ** 2))

    def theta(self, named: dict[str, float]) -> np.ndarray:
        """Named values (e.g. a twin's truth) -> free vector; absent names take init."""
        known = {k: v for k, v in named.items() if k in self.spec}
        return self.spec.flatten(known)


def needs_input(model: Model) -> bool:
    return input_signal(model) is not None


def input_signal(model: Model) -> str | None:
    """The recorded signal the model's ``measured_input`` reads (``"u"`` or ``"F"``), or
    None when the model has no measured drive."""
    signals = {getattr(t, "signal", "u") for t in model.terms if t.name == "measured_input"}
    if len(signals) > 1:
        raise FricjaxError(
            "model: measured_input appears with signals u and F; one measured drive per model"
        )
    return signals.pop() if signals else None


def bind_input(rec: Recording, model: Model) -> Recording:
    """``rec`` with ``u`` the signal the model's measured drive reads: the measured force
    ``/F`` [N] for ``measured_input`` with ``signal = "F"`` (``u_unit`` "N"), else as is.

    Raises:
        FricjaxError: the model reads a signal the recording lacks.
    """
    signal = input_signal(model)
    if signal is None:
        return rec
    if getattr(rec, signal) is None:
        raise FricjaxError(
            f"{where(rec.path or rec.name, '/' + signal)}: missing (model term measured_input "
            f"reads the recorded {'force' if signal == 'F' else 'drive input'} /{signal})"
        )
    if signal == "F":
        return dataclasses.replace(rec, u=rec.F, u_unit="N")
    return rec


def check_axis(rec: Recording, config: Config) -> None:
    """Refuse a recording whose ``axis`` attr contradicts the config's ``[model].axis``."""
    if rec.axis and rec.axis != config.axis.kind:
        raise FricjaxError(
            f"{where(rec.path or rec.name, 'attr axis')}: recording is {rec.axis!r} but "
            f"{config.source or 'the config'} has [model].axis = {config.axis.kind!r}; "
            "make them agree"
        )


def build_problem(
    rec: Recording, config: Config, *, preprocess: PreprocessSettings | None = None
) -> Problem:
    """Preprocess ``rec`` (seed section 4.1) and bind it to the config's model."""
    settings = preprocess or PreprocessSettings.from_dict(
        config.table("preprocess"), source=config.source or "config"
    )
    spec: ParamSpec = config.spec
    check_axis(rec, config)
    if not config.mass_in_spec:
        m = require_mass(rec)
        # bounds = the value: the recording's mass is a measurement, not a search box, so
        # no box of the config can be blamed for it
        mass = dataclasses.replace(MASS, unit=axis_unit(MASS.unit, config.axis))
        spec = spec.extended([dataclasses.replace(mass, lower=m, upper=m, init=m, free=False)])
    checksum = rec.sha256()
    rec = bind_input(rec, config.model)
    # u and F are filtered like m·a ([preprocess].filter_input); F is handed on as u when
    # the model's measured drive reads it (bind_input)
    d = derivatives(rec.t, rec.x, settings, u=rec.u, source=rec.path or rec.name)
    u = d.u if d.u is not None else np.zeros_like(d.t)
    kept = slice(settings.trim, rec.n - settings.trim)
    drive = None if rec.u is None else np.asarray(rec.u, dtype=np.float64)[kept]
    return Problem(
        model=config.model,
        spec=spec,
        t=d.t,
        x=d.x,
        v=d.v,
        a=d.a,
        u=u,
        name=rec.name,
        checksum=checksum,
        source=rec.path,
        preprocess=settings,
        axis=config.axis.kind,
        drive=drive,
    )


def joined(problems: Sequence[Problem]) -> Problem:
    """Several preprocessed recordings of one plant and one model as one problem: their
    samples end to end, every parameter shared (one run of tests, nothing changed on the
    rig between them; where a level may have moved between runs, the diagnosis across
    recordings judges that, :mod:`fricjax.diagnose.across`).

    Each recording was preprocessed on its own, so no filter reaches across a join. Each
    keeps its own clock (``t`` as recorded, so it restarts at a join): a term of time (an
    impact at t₀, a harmonic of the drive, a drift over the test) acts at the same instants
    of every test, which is how ``fricjax design`` predicts the new test (from its own
    t = 0). ``joins`` marks where each later recording starts; the body's state jumps there
    and the output error's segments start afresh (their continuity defect is not tied
    across a join). Refused in one line: fewer than two, or recordings whose
    model, parameters (the mass included), preprocessing or sample step differ."""
    if len(problems) < 2:
        raise FricjaxError("joined: needs at least two recordings")
    first = problems[0]

    dt = first.dt
    for p in problems[1:]:
        src = p.source or p.name or "recording"
        if p.model != first.model or p.spec != first.spec:
            raise FricjaxError(
                f"{src}: its model or parameters (the mass included) differ from "
                f"{first.source or first.name}'s; joined recordings share every parameter"
            )
        if p.preprocess != first.preprocess:
            raise FricjaxError(f"{src}: preprocessed differently from the first recording")
        if not math.isclose(p.dt, dt, rel_tol=1e-6):
            raise FricjaxError(
                f"{where(src, '/t')}: sample step {p.dt:.6g} s, the first recording's is "
                f"{dt:.6g} s; resample one of them"
            )
    joins, end = [], 0
    for p in problems:
        if end:
            joins.append(end)
        end += p.n

    def cat(name: str) -> np.ndarray:
        return np.concatenate([np.asarray(getattr(p, name), dtype=np.float64) for p in problems])

    rests = [p.rest for p in problems]
    return Problem(
        model=first.model,
        spec=first.spec,
        t=cat("t"),
        x=cat("x"),
        v=cat("v"),
        a=cat("a"),
        u=cat("u"),
        name=" + ".join(p.name for p in problems),
        checksum=" + ".join(p.checksum for p in problems),
        source=" + ".join(str(p.source or p.name) for p in problems),
        preprocess=first.preprocess,
        rest=None if any(r is None for r in rests) else np.concatenate(rests),  # type: ignore[arg-type]
        axis=first.axis,
        drive=np.concatenate([p.drive_input for p in problems]),
        joins=tuple(joins),
    )


def stack_trees(trees: Sequence[Any]) -> Any:
    """Equal-structure pytrees (e.g. the residual functions of problems of one shape)
    stacked along a new leading axis of their array leaves (numpy, on the host); the
    static parts are the first tree's. For vmapping one program over them."""
    arrays, static = eqx.partition(list(trees), eqx.is_array)
    stacked = jax.tree.map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *arrays)
    return eqx.combine(stacked, static[0])
