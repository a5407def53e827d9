"""``fricjax simulate``: run an identified model forward and compare it with the recording.

The model is simulated (:func:`simulate_model`: stiction-aware RK4,
:mod:`fricjax.model.simulate`; closed loop through :mod:`fricjax.model.closed_loop` when a
controller is given and the recording has a reference ``/r``, else open loop from the
recorded input or, for a harmonic drive, from the drive function of t) from the
recording's state at the first kept sample ``k0 = trim`` of the config's
``[preprocess]``: position ``x[k0]`` [m] as recorded, velocity the preprocessed ``v`` there
[m/s] (the filtered derivative; a first difference would carry √2·σ_x/dt of noise,
34 mm/s on the twin). Samples ``k0 .. n − trim − 1`` (the m samples whose recorded ``v``,
``a`` the preprocessing keeps) are compared:

    signal       recorded y                       simulated ŷ                  unit
    x            /x                               x_sim                        m
    v            preprocessed v                   v_sim                        m/s
    a            preprocessed a                   a_sim = (F_p − F_f)/m        m/s²
    force        m·a (measured force, eq. 11)     m·a_sim (model force on the
                                                  simulated motion, 0 while stuck)  N
    actuation    g·u (closed loop only)           g·ν_sim (controller output)  N

and for each, with ``e = ŷ − y`` over the m samples:

    RMS error       √(mean e²)                               [unit of y]
    relative error  100·‖e‖/‖y‖                              [%]
    fit             100·(1 − ‖e‖/‖y − mean(y)‖)              [%]  (100 = perfect, 0 = no
                                                                   better than the mean)

``g`` is the model's ``gain`` (1 for a model without one).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from pathlib import Path
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from fricjax.config import Config
from fricjax.data.recording import MAX_MAGNITUDE, Recording
from fricjax.errors import FricjaxError, where
from fricjax.limits import check_substeps
from fricjax.model.closed_loop import CascadePD, input_disturbance, simulate_closed_loop
from fricjax.model.simulate import simulate
from fricjax.model.system import MASS
from fricjax.params import check_known, check_value
from fricjax.problem import Problem, bind_input, build_problem
from fricjax.units import LINEAR, AxisUnits

__all__ = [
    "SIGNAL_UNITS",
    "SignalMetrics",
    "SimulationReport",
    "param_values",
    "problem_for",
    "signal_metrics",
    "simulate_against",
    "simulate_model",
    "trx",
]

FORMAT = "fricjax-simulation-v1"
#: Units of the compared signals on a linear axis (a rotary one: :mod:`fricjax.units`).
SIGNAL_UNITS = LINEAR.signal_units()


class SignalMetrics(NamedTuple):
    """Agreement of one simulated signal with the recorded one (module docstring).

    rms: √(mean e²) [unit of the signal]; relative: 100‖e‖/‖y‖ [%];
    fit: 100(1 − ‖e‖/‖y − ȳ‖) [%]; unit: the signal's unit.
    """

    rms: float
    relative: float
    fit: float
    unit: str


class SimulationReport(NamedTuple):
    """What :func:`simulate_against` computed.

    recording: path or name; params: every model parameter [SI]; mode: "open-loop" or
    "closed-loop"; substeps: RK4 sub-steps per sample; start: first compared sample k0;
    t [m]: compared sample times [s]; recorded, simulated: signal name → [m] arrays (units
    in :data:`SIGNAL_UNITS`); metrics: signal name → :class:`SignalMetrics`; files: what
    was written (json, h5, png) → path; axis: the axis' units and symbols.
    """

    recording: str
    params: dict[str, float]
    mode: str
    substeps: int
    start: int
    t: np.ndarray
    recorded: dict[str, np.ndarray]
    simulated: dict[str, np.ndarray]
    metrics: dict[str, SignalMetrics]
    files: dict[str, Path]
    axis: AxisUnits = LINEAR

    def residual(self, name: str) -> np.ndarray:
        """``simulated − recorded`` of signal ``name`` [its unit], shape [m]."""
        return self.simulated[name] - self.recorded[name]

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready metrics (no series)."""
        return {
            "format": FORMAT,
            "recording": self.recording,
            "mode": self.mode,
            "substeps": self.substeps,
            "start_sample": self.start,
            "samples": int(self.t.shape[0]),
            "params": self.params,
            "metrics": {k: m._asdict() for k, m in self.metrics.items()},
        }


# -- the one simulation of a model against a recording ---------------------------------


def param_values(problem: Problem, params: Mapping[str, float], source: str) -> dict[str, Array]:
    """Every model parameter as a JAX scalar: values from ``params``, else the config's."""
    out = {}
    for p in problem.spec.params:
        if p.name in params:
            value = check_value(p, params[p.name], where(source, p.name))
            out[p.name] = jnp.asarray(value, dtype=jnp.float64)
        elif p.free:
            raise FricjaxError(f"{where(source, p.name)}: missing (free parameter of the model)")
        else:
            out[p.name] = jnp.asarray(p.init, dtype=jnp.float64)
    return out


def problem_for(
    rec: Recording, cfg: Config, params: Mapping[str, float], source: str = "params"
) -> Problem:
    """The problem of ``rec`` and ``cfg``, the mass taken from ``params`` where neither
    the config nor the recording gives it."""
    if not cfg.mass_in_spec and rec.mass is None and "mass" in params:
        # the mass comes from the parameters, so a bad one is blamed on them
        mass = check_value(MASS, params["mass"], where(source, "mass"))
        rec = replace(rec, mass=mass)
    return build_problem(rec, cfg)


def trx(rec: Recording) -> tuple[np.ndarray, ...]:
    """(t, x, r, u) of ``rec``: the arguments of :func:`input_disturbance`."""
    return rec.t, rec.x, rec.r, rec.u


def simulate_model(
    rec: Recording,
    problem: Problem,
    p: Mapping[str, Array],
    controller: CascadePD | None,
    *,
    substeps: int = 4,
    start: int = 0,
    stop: int | None = None,
    v0: float | None = None,
) -> tuple[bool, np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
    """Simulate ``problem.model`` at ``p`` over samples ``start:stop`` of ``rec``.

    Closed loop (:func:`simulate_closed_loop`, reference ``/r[start:stop]``, external input
    :func:`input_disturbance` of the whole record) when ``controller`` is given and the
    record has ``/r``; else open loop from the recorded input. Initial state: ``x[start]``
    [m] and ``v0`` [m/s] (default: the first difference ``(x[start+1] − x[start])/dt``).

    Returns:
        (closed, x [m], v [m/s], a [m/s²], u) over the m samples, numpy; ``u`` [unit of /u]
        is the simulated controller output in closed loop, None in open loop.
    """
    rec = bind_input(rec, problem.model)
    keep = slice(start, stop)
    t = jnp.asarray(rec.t[keep])
    x0 = float(rec.x[start])
    if v0 is None:
        v0 = float((rec.x[start + 1] - rec.x[start]) / rec.dt)
    u = None if rec.u is None else jnp.asarray(rec.u[keep])
    closed = controller is not None and rec.r is not None
    if closed:
        w = None
        if rec.u is not None:
            w = jnp.asarray(input_disturbance(controller, *trx(rec))[keep])
        traj = simulate_closed_loop(
            problem.model, p, t, jnp.asarray(rec.r[keep]), x0, v0, controller, w, substeps=substeps
        )
        xs, vs, acc, us = (np.asarray(y) for y in traj)
        return True, xs, vs, acc, us
    traj = simulate(problem.model, p, t, x0, v0, u, substeps=substeps)
    xs, vs, acc = (np.asarray(y) for y in traj)
    return False, xs, vs, acc, None


def signal_metrics(simulated: np.ndarray, recorded: np.ndarray, unit: str = "") -> SignalMetrics:
    """RMS error, relative error [%] and fit [%] of ``simulated`` against ``recorded``."""
    y = np.asarray(recorded, dtype=np.float64)
    e = np.asarray(simulated, dtype=np.float64) - y
    err = float(np.linalg.norm(e))
    norm = float(np.linalg.norm(y))
    spread = float(np.linalg.norm(y - np.mean(y)))
    return SignalMetrics(
        rms=float(np.sqrt(np.mean(e * e))),
        relative=100.0 * err / norm if norm > 0 else float("inf"),
        fit=100.0 * (1.0 - err / spread) if spread > 0 else float("-inf"),
        unit=unit,
    )


def simulate_against(
    rec: Recording,
    cfg: Config,
    params: Mapping[str, float],
    *,
    controller: CascadePD | None = None,
    substeps: int = 4,
    source: str = "params",
) -> SimulationReport:
    """Simulate ``params`` over ``rec`` and compare (module docstring); nothing written.

    ``params`` must name only parameters of the config's model (``mass`` included); the
    free ones are required, fixed ones default to the config's values.
    """
    if isinstance(substeps, bool) or not isinstance(substeps, int) or substeps < 1:
        raise FricjaxError(f"{where('simulate', 'substeps')}: must be an integer >= 1")
    check_substeps(substeps, rec.n, "simulate")
    src = rec.path or rec.name
    if controller is not None and rec.r is None:
        raise FricjaxError(
            f"{where(src, '/r')}: missing (closed-loop simulation with a controller needs "
            "the reference position)"
        )
    problem = problem_for(rec, cfg, params, source)
    check_known(params, problem.spec.names, source)
    p = param_values(problem, params, source)
    trim = problem.preprocess.trim if problem.preprocess is not None else 0
    m = problem.n
    closed, xs, vs, acc, us = simulate_model(
        rec,
        problem,
        p,
        controller,
        substeps=substeps,
        start=trim,
        stop=trim + m,
        v0=float(problem.v[0]),
    )
    if not all(np.all(np.isfinite(arr)) for arr in (xs, vs, acc)):
        culprit = problem.model.overflowing(p, problem.signals, MAX_MAGNITUDE)
        raise FricjaxError(
            f"{where(source)}: the simulation is not finite at these parameters "
            f"({'overflows: ' + culprit if culprit else 'the motion diverges'}); "
            "nothing to compare"
        )
    mass = float(p["mass"])
    recorded = {
        "x": np.asarray(problem.x),
        "v": np.asarray(problem.v),
        "a": np.asarray(problem.a),
        "force": mass * np.asarray(problem.a),
    }
    simulated = {"x": xs, "v": vs, "a": acc, "force": mass * acc}
    if closed and us is not None and rec.u is not None:
        gain = float(p["gain"]) if "gain" in p else 1.0
        recorded["actuation"] = gain * np.asarray(rec.u[trim : trim + m])
        simulated["actuation"] = gain * us
    units = cfg.axis.signal_units()
    metrics = {k: signal_metrics(simulated[k], recorded[k], units[k]) for k in recorded}
    return SimulationReport(
        recording=str(rec.path or rec.name),
        params={k: float(v) for k, v in p.items()},
        mode="closed-loop" if closed else "open-loop",
        substeps=substeps,
        start=trim,
        t=np.asarray(problem.t),
        recorded=recorded,
        simulated=simulated,
        metrics=metrics,
        files={},
        axis=cfg.axis,
    )
