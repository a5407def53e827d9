"""What ``fricjax simulate`` writes and prints: the comparison's JSON, HDF5 series, figure
(recorded against simulated signals and their residuals) and plain-text table."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import numpy as np

from fricjax.io.atomic import make_folder, write_hdf5_atomic, write_text_atomic
from fricjax.report.plots import plt, save
from fricjax.report.tables import format_table
from fricjax.simulation import FORMAT, SimulationReport

__all__ = ["OUTPUT_FILES", "format_simulation", "plot_simulation", "write_simulation"]


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


def plot_simulation(report: SimulationReport, path: str | Path) -> Path:
    """One row per signal (x, v, a, force; actuation in closed loop) against t [s]: left,
    recorded and simulated; right, the residual simulated − recorded with its RMS.
    Saved atomically as PNG."""
    names = list(report.recorded)
    symbols = {"x": "x", "v": "v", "a": "a", "force": report.axis.inertial, "actuation": "g·u"}
    fig, axes = plt.subplots(
        len(names),
        2,
        figsize=(11, 2.1 * len(names) + 0.8),
        sharex=True,
        gridspec_kw={"width_ratios": (3, 2)},
        squeeze=False,
    )
    t = report.t
    for row, name in enumerate(names):
        left, right = axes[row]
        left.plot(t, report.recorded[name], lw=1.0, color="0.25", label="recorded")
        left.plot(t, report.simulated[name], lw=1.0, color="tab:red", ls="--", label="simulated")
        m = report.metrics[name]
        label = f"{symbols[name]} [{m.unit}]"
        left.set_ylabel(label)
        left.grid(alpha=0.3)
        right.plot(t, report.residual(name), lw=0.8, color="tab:blue")
        right.axhline(0.0, color="0.5", lw=0.6)
        right.set_ylabel(f"Δ{label}")
        right.set_title(f"RMS {m.rms:.3g} {m.unit}, fit {m.fit:.1f} %", fontsize=9)
        right.grid(alpha=0.3)
    axes[0, 0].legend(loc="best", fontsize=8)
    axes[0, 0].set_title(f"{report.mode} simulation of {Path(report.recording).name}", fontsize=10)
    for ax in axes[-1]:
        ax.set_xlabel("t [s]")
    fig.tight_layout()
    return save(fig, path)
