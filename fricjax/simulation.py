"""``fricjax simulate``: run an identified model forward and compare it with the recording.

The model is simulated (:func:`fricjax.validate.simulate_model`: stiction-aware RK4,
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

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple

import h5py
import numpy as np

from fricjax.config import Config
from fricjax.data.recording import MAX_MAGNITUDE, Recording
from fricjax.errors import FricjaxError, where
from fricjax.io.atomic import make_folder, write_hdf5_atomic, write_text_atomic
from fricjax.limits import check_substeps
from fricjax.model.closed_loop import CascadePD
from fricjax.params import check_known
from fricjax.units import LINEAR
from fricjax.validate import _named, _problem, simulate_model

__all__ = [
    "SIGNAL_UNITS",
    "SignalMetrics",
    "SimulationReport",
    "format_simulation",
    "signal_metrics",
    "simulate_against",
    "write_simulation",
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
    was written (json, h5, png) → path.
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
    problem = _problem(rec, cfg, params, source)
    check_known(params, problem.spec.names, source)
    p = _named(problem, params, source)
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
    )


#: What :func:`write_simulation` writes into its folder.
OUTPUT_FILES = ("simulation.json", "simulation.h5", "simulation.png")


def write_simulation(report: SimulationReport, out: str | Path) -> SimulationReport:
    """Write ``out/simulation.json`` (metrics), ``out/simulation.h5`` (series) and
    ``out/simulation.png`` (figure), each atomically; returns the report with ``files``.

    HDF5 layout: ``/t`` [m] (s); ``/recorded/<signal>``, ``/simulated/<signal>``,
    ``/residual/<signal>`` (simulated − recorded) [m] with a ``unit`` attribute each; root
    attrs ``format``, ``recording``, ``mode``, ``substeps``, ``start_sample``, ``params``
    and ``metrics`` (JSON text).
    """
    from fricjax.report.simulation_plots import plot_simulation

    out = make_folder(out)
    meta = report.as_dict()
    json_name, h5_name, png_name = OUTPUT_FILES
    json_path = write_text_atomic(out / json_name, json.dumps(meta, indent=2) + "\n")

    def fill(f: h5py.File) -> None:
        f.attrs["format"] = FORMAT
        f.attrs["recording"] = report.recording
        f.attrs["mode"] = report.mode
        f.attrs["substeps"] = report.substeps
        f.attrs["start_sample"] = report.start
        f.attrs["params"] = json.dumps(report.params)
        f.attrs["metrics"] = json.dumps(meta["metrics"])
        ds = f.create_dataset("t", data=report.t)
        ds.attrs["unit"] = "s"
        for group, series in (
            ("recorded", report.recorded),
            ("simulated", report.simulated),
            ("residual", {k: report.residual(k) for k in report.recorded}),
        ):
            g = f.create_group(group)
            for name, y in series.items():
                ds = g.create_dataset(name, data=np.asarray(y, dtype=np.float64))
                ds.attrs["unit"] = report.metrics[name].unit

    h5_path = write_hdf5_atomic(out / h5_name, fill)
    png_path = plot_simulation(report, out / png_name)
    return report._replace(files={"json": json_path, "h5": h5_path, "png": png_path})


def format_simulation(report: SimulationReport) -> str:
    """Plain-text table: one row per signal (RMS error, relative error, fit)."""
    from fricjax.report.tables import format_table

    rows = [
        (name, f"{m.rms:.4g} {m.unit}", f"{m.relative:.4g} %", f"{m.fit:.2f} %")
        for name, m in report.metrics.items()
    ]
    head = (
        f"simulation ({report.mode}, {report.substeps} sub-steps, samples "
        f"{report.start}..{report.start + report.t.shape[0] - 1}) against {report.recording}"
    )
    table = format_table(rows, ("signal", "RMS error", "relative error", "fit"))
    return f"{head}\n{table}"
