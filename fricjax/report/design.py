"""What ``fricjax design`` writes and prints: the profile as CSV (the recording's time
column and input column, for the rig to follow), the figure of the models' predicted
responses with the noise band, the design's numbers as JSON, and a plain-text summary."""

from __future__ import annotations

import io
import json
from pathlib import Path

import numpy as np

from fricjax.design import DESIGNED, Design, PrecisionDesign
from fricjax.io.atomic import write_text_atomic
from fricjax.report.plots import plt, save
from fricjax.report.tables import fmt

__all__ = [
    "design_files",
    "format_design",
    "format_precision",
    "plot_design",
    "plot_precision",
    "write_design",
]


def design_files(out_csv: str | Path) -> dict[str, Path]:
    """``NEXT.csv`` → the CSV itself, ``NEXT.png`` and ``NEXT.json`` beside it."""
    out = Path(out_csv)
    return {"csv": out, "png": out.with_suffix(".png"), "json": out.with_suffix(".json")}


def write_design(d: Design | PrecisionDesign, out_csv: str | Path) -> dict[str, Path]:
    """Write the profile (``t,<column>``, one sample a row, the record's sample rate), its
    figure and its numbers, each atomically; returns their paths."""
    paths = design_files(out_csv)
    buf = io.StringIO()
    np.savetxt(buf, np.column_stack([d.t, d.u]), delimiter=",", header=f"t,{d.column}", comments="")
    write_text_atomic(paths["csv"], buf.getvalue())
    write_text_atomic(paths["json"], json.dumps(d.as_json(), indent=2) + "\n")
    if isinstance(d, Design):
        plot_design(d, paths["png"])
    else:
        plot_precision(d, paths["png"])
    return paths


def plot_design(d: Design, path: Path) -> Path:
    """Three panels over time: the input; each model's predicted position; each model's
    difference from the first, in units of σ_x, with the ±2σ_x noise band."""
    fig, axes = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    axes[0].plot(d.t, d.u, color="k", lw=1.0)
    axes[0].axhline(d.limits.u_mid + d.limits.u_peak, color="0.6", ls=":", lw=0.8)
    axes[0].axhline(d.limits.u_mid - d.limits.u_peak, color="0.6", ls=":", lw=0.8)
    axes[0].set_ylabel(f"input {d.column}")
    axes[0].set_title("Designed test: input (limits dotted)")
    for name, x in zip(d.rivals, d.x, strict=True):
        axes[1].plot(d.t, 1e3 * x, lw=1.0, label=name)
    axes[1].axhline(1e3 * d.limits.x_lo, color="0.6", ls=":", lw=0.8)
    axes[1].axhline(1e3 * d.limits.x_hi, color="0.6", ls=":", lw=0.8)
    axes[1].set_ylabel("predicted x [mm]")
    axes[1].legend(fontsize=8, loc="best")
    axes[2].fill_between(d.t, -2, 2, color="0.85", label="±2 σ_x (noise)")
    for name, x in zip(d.rivals[1:], d.x[1:], strict=True):
        axes[2].plot(d.t, (x - d.x[0]) / d.sigma_x, lw=1.0, label=f"{name} − {d.rivals[0]}")
    axes[2].set_ylabel("difference [σ_x]")
    axes[2].set_xlabel("t [s]")
    axes[2].legend(fontsize=8, loc="best")
    return save(fig, path)


def _headline(origin: str) -> str:
    """ "Designed test", or the standard test that did better than every optimised profile
    (it is then the test written)."""
    if origin == DESIGNED:
        return "Designed test"
    return f"Best test found: the standard {origin!r} (no optimised profile did better)"


def format_design(d: Design) -> str:
    """The summary a test engineer reads: the pairs' expected evidence, the standard
    tests' beside it, and the limits kept."""
    lines = [
        f"{_headline(d.origin)}: {d.plan.duration:g} s at {1 / d.plan.dt:g} Hz, input "
        f"{d.column} within {fmt(d.limits.u_mid)} ± {fmt(d.limits.u_peak)}, "
        f"{d.plan.harmonics} harmonics of {1 / d.plan.duration:.3g} Hz.",
        f"Models to separate (σ_x = {d.sigma_x:.3g} m):",
        *(f"  {name:>22}: {model}" for name, model in zip(d.rivals, d.models, strict=True)),
        "Expected evidence if the first is true (linearised, noise-free; the rival refitted "
        "on both records):",
    ]
    k = len(d.rivals)
    for i in range(k):
        for j in range(k):
            if i != j:
                lines.append(
                    f"  {d.rivals[i]:>22} over {d.rivals[j]:<22} D = "
                    f"{d.divergence[i, j]:10.3g}   ΔBIC of the two records ≈ "
                    f"{d.expected_delta_bic[i, j]:.3g}"
                )
    lines.append(f"Least separation of any pair: D = {d.separation:.3g}")
    lines.append("Standard tests of the same length and peak input:")
    for name, std in d.standard.items():
        value, over = std["separation"], std["limit_violation"]
        ratio = d.separation / value if value > 0 else float("inf")
        lines.append(
            f"  {name:>24}: D = {value:.3g} (the design: {ratio:.3g} times that)"
            + (f"; it leaves the limits by {100 * over:.2g} %" if over > 0.01 else "")
        )
    lines.append(
        f"Travel {fmt(d.limits.x_lo)}–{fmt(d.limits.x_hi)} m and speed ≤ {fmt(d.limits.speed)} "
        f"m/s kept by every model (largest excess {100 * d.violation:.2g} %)."
    )
    lines.append(
        "Run it from rest at the record's first position, record it, then judge both records "
        "as one: fricjax diagnose REC NEXT_REC --joined --config C"
    )
    return "\n".join(lines)


def plot_precision(d: PrecisionDesign, path: Path) -> Path:
    """The input, and the identified model's predicted position within the travel limits."""
    fig, axes = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    axes[0].plot(d.t, d.u, color="k", lw=1.0)
    for level in (d.limits.u_mid - d.limits.u_peak, d.limits.u_mid + d.limits.u_peak):
        axes[0].axhline(level, color="0.6", ls=":", lw=0.8)
    axes[0].set_ylabel(f"input {d.column}")
    axes[0].set_title(f"Designed test to determine {', '.join(d.focus)} (limits dotted)")
    axes[1].plot(d.t, 1e3 * d.x[0], lw=1.0, label=d.model)
    for level in (d.limits.x_lo, d.limits.x_hi):
        axes[1].axhline(1e3 * level, color="0.6", ls=":", lw=0.8)
    axes[1].set_ylabel("predicted x [mm]")
    axes[1].set_xlabel("t [s]")
    axes[1].legend(fontsize=8, loc="best")
    return save(fig, path)


def format_precision(d: PrecisionDesign) -> str:
    """Each parameter's σ now, after the designed test, and after the standard tests."""
    names = list(d.standard)
    lines = [
        f"{_headline(d.origin)}: {d.plan.duration:g} s at {1 / d.plan.dt:g} Hz, input "
        f"{d.column} within {fmt(d.limits.u_mid)} ± {fmt(d.limits.u_peak)}, "
        f"{d.plan.harmonics} harmonics of {1 / d.plan.duration:.3g} Hz; "
        f"σ_x = {d.sigma_x:.3g} m.",
        f"To determine: {', '.join(d.focus)} (D_s-optimal; σ expected from the record and "
        "the new test together, linearised):",
        f"  {'parameter':>14} {'value':>11} {'σ now':>11} {'σ designed':>11} "
        + " ".join(f"{'σ ' + n:>16}" for n in names),
    ]
    for i, name in enumerate(d.names):
        mark = "*" if name in d.focus else " "
        row = (
            f"{mark} {name:>14} {d.value[i]:11.4g} {d.sigma_before[i]:11.3g} "
            f"{d.sigma_after[i]:11.3g} "
        )
        row += " ".join(f"{d.standard[n].sigma_after[i]:16.3g}" for n in names)
        lines.append(row)
    lines.append(
        f"The focus' uncertainty shrinks to {d.shrink:.3g} of now (geometric mean over its "
        "axes); " + ", ".join(f"with a {n}: {s.shrink:.3g}" for n, s in d.standard.items()) + "."
    )
    over = {n: s.limit_violation for n, s in d.standard.items()}
    out = [f"{n} leaves the limits by {100 * v:.2g} %" for n, v in over.items() if v > 0.01]
    lines.append(
        f"Travel {fmt(d.limits.x_lo)}–{fmt(d.limits.x_hi)} m and speed ≤ {fmt(d.limits.speed)} "
        f"m/s kept (largest excess {100 * d.violation:.2g} %)"
        + (f"; {'; '.join(out)}." if out else ".")
    )
    return "\n".join(lines)
