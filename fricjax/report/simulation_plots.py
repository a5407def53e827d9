"""Figure of ``fricjax simulate``: recorded against simulated signals and their residuals."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from fricjax.report.plots import plt, save

if TYPE_CHECKING:
    from fricjax.simulation import SimulationReport

_SYMBOLS = {"x": "x", "v": "v", "a": "a", "force": "m·a", "actuation": "g·u"}


def plot_simulation(report: SimulationReport, path: str | Path) -> Path:
    """One row per signal (x, v, a, force; actuation in closed loop) against t [s]: left,
    recorded and simulated; right, the residual simulated − recorded with its RMS.
    Saved atomically as PNG."""
    names = list(report.recorded)
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
        label = f"{_SYMBOLS[name]} [{m.unit}]"  # units of the axis (fricjax.units)
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
