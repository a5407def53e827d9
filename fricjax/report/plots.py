"""Figures (matplotlib, Agg backend: no display needed)."""

from __future__ import annotations

import io
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from fricjax.io.atomic import write_bytes_atomic
from fricjax.units import LINEAR, AxisUnits


def save(fig: plt.Figure, path: str | Path) -> Path:
    """Save atomically and close the figure."""
    path = Path(path)
    buffer = io.BytesIO()
    try:
        fig.savefig(buffer, format=path.suffix.lstrip(".") or "png", dpi=110)
    finally:
        plt.close(fig)
    return write_bytes_atomic(path, buffer.getvalue())


def plot_signals(
    t: np.ndarray,
    x: np.ndarray,
    v: np.ndarray,
    a: np.ndarray,
    force: np.ndarray,
    *,
    title: str,
    path: str | Path,
    units: AxisUnits = LINEAR,
) -> Path:
    """Four stacked panels: x [m], v [m/s], a [m/s²], measured force m·a [N] against t [s]
    (rad, rad/s, rad/s², J·α [N·m] on a rotary axis, ``units``)."""
    fig, axes = plt.subplots(4, 1, figsize=(8, 8), sharex=True)
    labels = (
        units.label("position", "x"),
        units.label("velocity", "v"),
        units.label("acceleration", "a"),
        units.label("force", units.inertial),
    )
    for ax, y, label in zip(axes, (x, v, a, force), labels, strict=True):
        ax.plot(t, y, lw=1)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("t [s]")
    axes[0].set_title(title)
    fig.tight_layout()
    return save(fig, path)


def plot_convergence(
    traces: dict[str, dict[str, np.ndarray]],
    *,
    path: str | Path,
    x_key: str = "n_evals",
    title: str = "",
) -> Path:
    """Best cost (median over chains, IQR band) against evaluations or wall time, per run."""
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for label, tr in traces.items():
        best = np.minimum.accumulate(np.asarray(tr["best_cost"]), axis=0)
        med = np.median(best, axis=1)
        lo, hi = np.percentile(best, [25, 75], axis=1)
        xs = np.asarray(tr[x_key])
        ax.plot(xs, med, label=label)
        ax.fill_between(xs, lo, hi, alpha=0.2)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("cost evaluations" if x_key == "n_evals" else "wall time [s]")
    ax.set_ylabel("best cost [N²] (median, IQR over chains)")
    ax.grid(alpha=0.3, which="both")
    ax.legend()
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return save(fig, path)
