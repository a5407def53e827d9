"""The fleet report: every parameter across recordings with its σ, drift flagged.

Drift statistic. For parameter j and recording i (among the recordings fitted ``ok`` with a
finite σ > 0), the leave-one-out pooled estimate of the *other* recordings is the
inverse-variance weighted mean

    μ₋ᵢ = Σ_{k≠i} w_k x_k / Σ_{k≠i} w_k,   w_k = 1/σ_k²,   Var(μ₋ᵢ) = 1 / Σ_{k≠i} w_k

and the recording's z-score against it

    z_ij = (x_ij − μ₋ᵢ) / √(σ_ij² + Var(μ₋ᵢ))                                  [1]

(independent recordings, Gaussian estimates with their Gauss–Newton σ). A recording is
flagged as *moved* when some |z_ij| exceeds the Bonferroni threshold of a two-sided test
at family-wise level α over all m tests (m = number of z-scores computed):

    z* = Φ⁻¹(1 − α / (2m))      (α = 0.05: z* = 3.29 for m = 20, 4.56 for m = 26 000)

so on a fleet of one unchanged plant the chance of any flag is at most α. Leaving the
recording out keeps a large drift from pulling the pooled value towards itself; and since a
drifted recording would still pull the *other* recordings' references (with few
recordings, enough to flag them too), the test is sequential: the recording with the
largest |z| above z* is flagged and leaves the pool, the z-scores are recomputed against
the remaining pool, until none exceeds z* (or two recordings are left: with two, a
difference cannot be attributed to either). Flagged recordings report their z against the
final pool; the pooled value is the final pool's. The σ are
those of the model's own residual: a model that misses physics has σ too small and flags
recordings that differ only in what it misses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from scipy.stats import norm

from fricjax.io.atomic import write_text_atomic
from fricjax.io.fleet import FleetFile
from fricjax.report.plots import save

ALPHA = 0.05


@dataclass(frozen=True)
class Drift:
    """Drift test of a fleet (module docstring).

    ``z [N, d]``: z-scores (NaN where not computed: failed recording, σ not finite, fewer
    than two recordings); ``pooled [d]``, ``pooled_std [d]``: the all-recordings
    inverse-variance mean and its σ; ``threshold``: z* for ``m`` tests at ``alpha``;
    ``moved [N]``: some |z| above z*.
    """

    z: np.ndarray
    pooled: np.ndarray
    pooled_std: np.ndarray
    threshold: float
    m: int
    alpha: float
    moved: np.ndarray


def drift(values: np.ndarray, stds: np.ndarray, *, alpha: float = ALPHA) -> Drift:
    """z-scores of ``values [N, d]`` with σ ``stds [N, d]`` against the leave-one-out pooled
    estimate, and the Bonferroni flag with sequential removal (module docstring). NaN rows
    are left out."""
    x = np.asarray(values, np.float64)
    s = np.asarray(stds, np.float64)
    usable = np.isfinite(x) & np.isfinite(s) & (s > 0)
    w_all = np.where(usable, 1.0 / np.where(usable, s, 1.0) ** 2, 0.0)
    xs = np.where(usable, x, 0.0)
    pool = np.ones(x.shape[0], dtype=bool)
    moved = np.zeros(x.shape[0], dtype=bool)
    z = _scores(xs, s, w_all, usable, pool)
    m = int(np.isfinite(z).sum())
    threshold = float(norm.isf(alpha / (2 * m))) if m else math.inf
    while pool.sum() > 2:
        worst = np.max(np.abs(np.nan_to_num(z)), axis=1)
        worst[~pool] = -np.inf
        i = int(np.argmax(worst))
        if not worst[i] > threshold:
            break
        moved[i], pool[i] = True, False
        z = _scores(xs, s, w_all, usable, pool)
    w = w_all * pool[:, None]
    with np.errstate(divide="ignore", invalid="ignore"):
        pooled = (w * xs).sum(axis=0) / w.sum(axis=0)
        pooled_std = 1.0 / np.sqrt(w.sum(axis=0))
    return Drift(z, pooled, pooled_std, threshold, m, alpha, moved)


def _scores(
    xs: np.ndarray, s: np.ndarray, w_all: np.ndarray, usable: np.ndarray, pool: np.ndarray
) -> np.ndarray:
    """z [N, d] of every recording against the pooled recordings other than itself."""
    w = w_all * pool[:, None]
    rest_w = w.sum(axis=0) - w
    rest = (w * xs).sum(axis=0) - w * xs
    with np.errstate(divide="ignore", invalid="ignore"):
        z = (xs - rest / rest_w) / np.sqrt(s**2 + 1.0 / rest_w)
    return np.where(usable & (rest_w > 0), z, np.nan)


def ordering(orders: list[str]) -> np.ndarray:
    """Indices that sort the recordings by their order value: numerically when every value
    is a number, else as text (ISO dates and times sort correctly as text)."""
    try:
        keys: list[float] | list[str] = [float(o) for o in orders]
    except ValueError:
        keys = list(orders)
    return np.asarray(sorted(range(len(orders)), key=lambda i: (keys[i], i)), dtype=np.int64)


def _pm(value: float, std: float) -> str:
    if not np.isfinite(value):
        return "—"
    if not np.isfinite(std) or std <= 0:
        return f"{value:.6g} ± ?"
    digits = max(0, 2 - math.floor(math.log10(std)))
    return f"{value:.{digits}f} ± {std:.2g}" if digits < 10 else f"{value:.4g} ± {std:.2g}"


def fleet_markdown(fleet: FleetFile, result: Drift, source: str = "") -> str:
    """The report's text: summary, the drift statistic, one row per recording (in order),
    the failures with their reasons."""
    fits = fleet.fits
    order = ordering([f.order for f in fits])
    by = fleet.attrs.get("order_by") or "file name"
    n_ok = sum(f.ok for f in fits)
    lines = [
        f"# Fleet report{f': {source}' if source else ''}",
        "",
        f"{len(fits)} recordings: {n_ok} fitted, {len(fits) - n_ok} failed; ordered by {by}.",
        "",
        "**Drift**: z = (x − μ₋ᵢ)/√(σ² + Var μ₋ᵢ) against the inverse-variance mean μ₋ᵢ of the "
        f"other recordings; flagged when some |z| > z* = {result.threshold:.3g} (two-sided, "
        f"Bonferroni over m = {result.m} tests at family-wise α = {result.alpha:g}). "
        f"{int(result.moved.sum())} recording(s) flagged.",
        "",
        "| parameter | unit | pooled | spread (std of values) |",
        "|---|---|---|---|",
    ]
    values = fleet.values
    for j, (name, unit) in enumerate(zip(fleet.names, fleet.units, strict=True)):
        col = values[:, j][np.isfinite(values[:, j])]
        spread = f"{np.std(col, ddof=1):.3g}" if col.size > 1 else "—"
        lines.append(
            f"| {name} | {unit} | {_pm(result.pooled[j], result.pooled_std[j])} | {spread} |"
        )
    lines += [
        "",
        "| # | recording | order | status | max abs z (parameter) | moved | "
        + " | ".join(fleet.names)
        + " |",
        "|" + "---|" * (6 + len(fleet.names)),
    ]
    stds = fleet.stds
    for rank, i in enumerate(order, start=1):
        fit = fits[i]
        zi = result.z[i]
        if fit.ok and np.isfinite(zi).any():
            j = int(np.nanargmax(np.abs(zi)))
            zcell = f"{zi[j]:+.2f} ({fleet.names[j]})"
        else:
            zcell = "—"
        cells = [_pm(values[i, j], stds[i, j]) for j in range(len(fleet.names))]
        moved = "**yes**" if result.moved[i] else ""
        lines.append(
            f"| {rank} | {fit.name} | {fit.order} | {fit.status} | {zcell} | {moved} | "
            + " | ".join(cells)
            + " |"
        )
    failed = [f for f in fits if not f.ok]
    lines += ["", f"## Failures ({len(failed)})", ""]
    lines += [f"- {f.name} ({f.path or 'in memory'}): {f.reason}" for f in failed] or ["none"]
    return "\n".join(lines) + "\n"


def fleet_figure(fleet: FleetFile, result: Drift, path: str | Path) -> Path:
    """One panel per parameter: value ± σ of every fitted recording in order, the pooled
    value, flagged recordings in red (PNG, written atomically)."""
    fits = fleet.fits
    order = ordering([f.order for f in fits])
    d = len(fleet.names)
    cols = min(d, 4)
    rows = -(-d // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 2.6 * rows), squeeze=False)
    values, stds = fleet.values[order], fleet.stds[order]
    moved = result.moved[order]
    k = np.arange(len(order))
    for j, ax in enumerate(axes.flat):
        if j >= d:
            ax.axis("off")
            continue
        for sel, colour in ((~moved, "C0"), (moved, "C3")):
            ax.errorbar(
                k[sel], values[sel, j], yerr=stds[sel, j], fmt="o", ms=3, color=colour, lw=1
            )
        if np.isfinite(result.pooled[j]):
            ax.axhline(result.pooled[j], color="0.5", lw=0.8, ls="--")
        ax.set_title(f"{fleet.names[j]} [{fleet.units[j]}]", fontsize=9)
        ax.tick_params(labelsize=7)
    by = fleet.attrs.get("order_by") or "file name"
    fig.supxlabel(
        f"recording (ordered by {by}); red: moved beyond σ (|z| > {result.threshold:.3g})"
    )
    fig.tight_layout()
    return save(fig, path)


def write_fleet_report(fleet: FleetFile, markdown: str | Path, png: str | Path) -> Drift:
    """Write the Markdown report and its PNG; returns the drift test."""
    result = drift(fleet.values, fleet.stds)
    fleet_figure(fleet, result, png)
    text = fleet_markdown(fleet, result, str(fleet.attrs.get("config_path", "")))
    text += f"\n![parameters across the fleet]({Path(png).name})\n"
    write_text_atomic(markdown, text)
    return result
