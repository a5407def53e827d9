"""The diagnosis report for a test engineer: ``report.md`` and a self-contained
``report.html`` built from the same blocks (:mod:`fricjax.report.document`), and one figure
per finding (the residual before and after against the variable that located it, with the
fitted term overlaid).

Every figure a sentence quotes is taken from the table it stands beside, and every quantity
carries its unit: σ_x in m under displacement noise, a dimensionless scale under the
spectral noise model; speeds in m/s; forces in N; parameters with their spec's unit, and
flagged when they sit on a bound of their search box (a limit, not a measurement).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import jax.numpy as jnp
import numpy as np

from fricjax.data.preprocess import noise_gains
from fricjax.diagnose.run import (
    CV_FOLDS,
    CV_FOLDS_KEY,
    FROZEN_KEY,
    SPLIT_DEFERS,
    SPLIT_FROZEN,
    on_bound,
)
from fricjax.io.atomic import write_text_atomic
from fricjax.params import ParamSpec
from fricjax.report.document import Block, Heading, Image, Items, Para, Table, to_html, to_markdown
from fricjax.report.plots import plt, save
from fricjax.report.tables import fmt

if TYPE_CHECKING:
    from fricjax.diagnose.run import Diagnosis

# -- numbers the report and its figures share ---------------------------------------------


def residuals(diag: Diagnosis) -> tuple[np.ndarray, np.ndarray]:
    """Equation-error residual [N] of the base fit and of the final model (base + findings)."""
    from fricjax.diagnose.run import with_model

    sel, pb = diag.selection, diag.problem
    before = np.asarray(pb.residual_fn(jnp.asarray(sel.base_theta)))
    after = np.asarray(with_model(pb, sel.model, sel.spec).residual_fn(jnp.asarray(sel.theta)))
    return before, after


def term_force(diag: Diagnosis, finding: Mapping[str, Any]) -> np.ndarray | None:
    """The finding's fitted term as it shows in the residual [N, n]: the final model's
    residual with the finding's parameters at their null (the term switched off) minus
    its residual as fitted. None for a finding without a term in the final model
    (``unexplained``) or whose parameters have no null."""
    from fricjax.diagnose.run import with_model

    sel = diag.selection
    own = [k for k in finding.get("params", {}) if k in sel.spec.names and sel.spec[k].free]
    nulls = {k: sel.spec[k].null for k in own if math.isfinite(sel.spec[k].null)}
    if finding.get("effect") == "unexplained" or not nulls:
        return None
    pb = with_model(diag.problem, sel.model, sel.spec)
    fitted = sel.spec.as_dict(sel.theta)
    off = sel.spec.flatten({**fitted, **nulls})
    return np.asarray(pb.residual_fn(jnp.asarray(off))) - np.asarray(
        pb.residual_fn(jnp.asarray(sel.theta))
    )


def velocity_noise_gain(diag: Diagnosis) -> float:
    """σ_v/σ_x [1/s] of the preprocessing's velocity filter (white displacement noise)."""
    pb = diag.problem
    dt = float((pb.t[-1] - pb.t[0]) / (pb.n - 1))
    return noise_gains(pb.preprocess, 1.0 / dt)[0]


def _spec_of(diag: Diagnosis, name: str) -> ParamSpec | None:
    """A spec holding parameter ``name``: the final model's, else a refitted candidate's."""
    specs = [diag.selection.spec]
    for st in diag.selection.steps:
        specs += [r.spec for r in st.refits] + [r.spec for r, _ in st.rejected]
    return next((s for s in specs if name in s.names), None)


def base_on_bounds(diag: Diagnosis) -> list[tuple[str, float, str, float, str]]:
    """The base fit's free parameters on a bound: (name, value, side, bound, unit)."""
    spec, out = diag.base_spec, []
    for p, v in zip(spec.free, diag.selection.base_theta, strict=True):
        side = on_bound(spec, p.name, float(v))
        if side:
            out.append((p.name, float(v), side, p.lower if side == "lower" else p.upper, p.unit))
    return out


# -- formatting ----------------------------------------------------------------------------


def length(x: float) -> str:
    """A length in the unit that keeps 3 significant figures readable (m, mm, µm)."""
    if not math.isfinite(x):
        return "not computed"
    a = abs(x)
    if a >= 1.0 or a == 0.0:
        return f"{x:.3g} m"
    if a >= 1e-3:
        return f"{1e3 * x:.3g} mm"
    return f"{1e6 * x:.3g} µm"


def _pct(before: float, after: float) -> str:
    if not (math.isfinite(before) and math.isfinite(after)) or before == 0:
        return "–"
    return f"{100 * (after - before) / abs(before):+.1f} %"


_PLACES = {
    "time_s": ("t", "s"),
    "position_m": ("x", "m"),
    "velocity_mps": ("v", "m/s"),
    "acceleration_mps2": ("a", "m/s²"),
    "frequency_hz": ("f", "Hz"),
    "period_m": ("period", "m"),
    "presliding_distance_m": ("presliding distance", "m"),
}


def where_text(location: Mapping[str, Any]) -> str:
    """A finding's location in words with units."""
    parts = []
    for key, value in location.items():
        if key == "direction":
            parts.append(f"moving in the {value} direction")
        elif key == "reversals_s":
            times = ", ".join(f"{float(t):.3g}" for t in list(value)[:6])
            more = ", …" if len(value) > 6 else ""
            parts.append(f"at the {len(value)} velocity reversals (t = {times}{more} s)")
        elif key in _PLACES:
            name, unit = _PLACES[key]
            if isinstance(value, list | tuple) and len(value) == 2:
                parts.append(f"{name} from {float(value[0]):.4g} to {float(value[1]):.4g} {unit}")
            else:
                parts.append(f"{name} = {float(value):.4g} {unit}")
        else:
            parts.append(f"{key} = {value}")
    return "; ".join(parts) or "the whole record"


def params_text(diag: Diagnosis, params: Mapping[str, float]) -> tuple[str, list[tuple[str, str]]]:
    """(``name = value unit`` list, (name, why in words) of each parameter on a bound)."""
    shown, bounds = [], []
    for name, value in params.items():
        spec = _spec_of(diag, name)
        unit = spec[name].unit if spec is not None else ""
        unit = "" if unit in ("", "1", "-") else f" {unit}"
        shown.append(f"{name} = {fmt(float(value), 4)}{unit}")
        side = on_bound(spec, name, float(value))
        if side:
            assert spec is not None
            p = spec[name]
            bounds.append(
                (
                    name,
                    f"`{name}` = {fmt(float(value), 4)}{unit} sits on the {side} bound of its "
                    f"search range [{fmt(p.lower, 4)}, {fmt(p.upper, 4)}]{unit}: the data push it "
                    "further, so this is a limit of the search, not a measurement",
                )
            )
    return ", ".join(shown), bounds


# -- figures -------------------------------------------------------------------------------

_VARIABLES = {
    "time_s": ("t", "t [s]", "time"),
    "position_m": ("x", "x [m]", "position"),
    "velocity_mps": ("v", "v [m/s]", "velocity"),
    "direction": ("v", "v [m/s]", "velocity"),
    "acceleration_mps2": ("a", "a [m/s²]", "acceleration"),
    "frequency_hz": ("f", "f [Hz]", "frequency"),
}
# which key locates a finding when it has several (the most specific first)
_PREFERENCE = (
    "frequency_hz",
    "velocity_mps",
    "direction",
    "position_m",
    "acceleration_mps2",
    "time_s",
)


# effects whose signature follows a signal their location does not name
_SIGNATURE = {"mass_error": "acceleration_mps2"}


def located_variable(finding: Mapping[str, Any]) -> str:
    """The variable a finding's figure is drawn against: the one its signature follows,
    else the most specific key of its location (time when none)."""
    if finding.get("effect") in _SIGNATURE:
        return _SIGNATURE[finding["effect"]]
    location = finding.get("location", {})
    return next((k for k in _PREFERENCE if k in location), "time_s")


def _binned(xs: np.ndarray, ys: Sequence[np.ndarray], n_bins: int) -> tuple[np.ndarray, ...]:
    """Mean of each ``ys`` in equal-width bins of ``xs`` (empty ones dropped): (bin centres,
    means...). Equal widths resolve a narrow place the plant passes quickly (few samples),
    which quantile bins would merge with its surroundings."""
    edges = np.linspace(float(np.min(xs)), float(np.max(xs)), n_bins + 1)
    idx = np.clip(np.searchsorted(edges, xs, side="right") - 1, 0, len(edges) - 2)
    keep = np.bincount(idx, minlength=len(edges) - 1) > 0
    count = np.bincount(idx, minlength=len(edges) - 1)[keep]
    centres = np.bincount(idx, weights=xs, minlength=len(edges) - 1)[keep] / count
    means = [np.bincount(idx, weights=y, minlength=len(edges) - 1)[keep] / count for y in ys]
    return centres, *means


def _smooth(y: np.ndarray, width: int) -> np.ndarray:
    width = max(1, min(width, y.size // 4 or 1))
    return np.convolve(y, np.ones(width) / width, mode="same")


def _ems_title(before: np.ndarray, after: np.ndarray) -> str:
    b, a = float(np.mean(before**2)), float(np.mean(after**2))
    return f"EMS {fmt(b, 5)} → {fmt(a, 5)} N² ({_pct(b, a)})"


def _shade(ax: Any, location: Mapping[str, Any], key: str) -> None:
    value = location.get(key)
    if isinstance(value, list | tuple) and len(value) == 2:
        ax.axvspan(
            float(value[0]), float(value[1]), color="tab:orange", alpha=0.15, label="located"
        )
    elif isinstance(value, int | float):
        ax.axvline(float(value), color="tab:orange", lw=2, alpha=0.6, label="located")


def overview_figure(diag: Diagnosis, before: np.ndarray, after: np.ndarray, path: Path) -> Path:
    """Residual against t [s]: samples, running mean, located time intervals and the
    samples marked at rest; before (base model) and after (base + findings) in two panels,
    one panel when nothing was added."""
    pb = diag.problem
    t = np.asarray(pb.t)
    panels = [(before, "before: base model")]
    if diag.findings:
        panels.append((after, "after: base + findings"))
    fig, axes = plt.subplots(
        len(panels),
        1,
        figsize=(10, 2.0 + 2.4 * len(panels)),
        sharex=True,
        sharey=True,
        squeeze=False,
    )
    width = max(pb.n // 50, 1)
    for ax, (r, label) in zip(axes[:, 0], panels, strict=True):
        ax.plot(t, r, lw=0.5, color="0.6", label="residual")
        ax.plot(
            t, _smooth(r, width), lw=1.6, color="tab:red", label=f"running mean ({width} samples)"
        )
        ax.axhline(0.0, color="0.3", lw=0.6)
        if pb.rest is not None and np.any(pb.rest):
            rest = np.asarray(pb.rest)
            ax.plot(
                t[rest],
                r[rest],
                "|",
                ms=6,
                color="tab:purple",
                alpha=0.6,
                label="at rest (not tested)",
            )
        for f in diag.findings:
            _shade(ax, f.get("location", {}), "time_s")
        ax.set_ylabel("residual [N]")
        rms = float(np.sqrt(np.mean(r**2)))
        ax.set_title(f"{label}: mean {np.mean(r):+.3g} N, RMS {rms:.3g} N", fontsize=9)
        ax.grid(alpha=0.3)
        handles, names = ax.get_legend_handles_labels()
        uniq = dict(zip(names, handles, strict=True))
        ax.legend(uniq.values(), uniq.keys(), loc="upper right", fontsize=8)
    axes[-1, 0].set_xlabel("t [s]")
    what = (
        _ems_title(before, after)
        if diag.findings
        else (f"no finding, EMS {fmt(float(np.mean(before**2)), 5)} N²")
    )
    fig.suptitle(f"{Path(diag.recording).name}: equation-error residual, {what}")
    fig.tight_layout()
    return save(fig, path)


def finding_figure(
    diag: Diagnosis,
    index: int,
    finding: Mapping[str, Any],
    before: np.ndarray,
    after: np.ndarray,
    path: Path,
) -> Path:
    """The residual before and after against the variable that located ``finding``, with
    the fitted term (:func:`term_force`) overlaid; a spectrum for a frequency finding."""
    pb = diag.problem
    loc = finding.get("location", {})
    key = located_variable(finding) if finding else "velocity_mps"
    attr, label, word = _VARIABLES[key]
    term = term_force(diag, finding) if finding else None
    effect = finding.get("effect", "no finding")
    fig, ax = plt.subplots(figsize=(10, 4.8))
    if key == "frequency_hz":
        dt = float((pb.t[-1] - pb.t[0]) / (pb.n - 1))
        f = np.fft.rfftfreq(pb.n, dt)

        def amp(r: np.ndarray) -> np.ndarray:
            return 2.0 * np.abs(np.fft.rfft(r)) / pb.n

        ax.semilogy(f[1:], amp(before)[1:], color="0.45", lw=1.0, label="residual before")
        ax.semilogy(f[1:], amp(after)[1:], color="tab:blue", lw=1.0, label="residual after")
        if term is not None:
            ax.semilogy(f[1:], amp(term)[1:], color="tab:red", ls="--", lw=1.2, label="fitted term")
        ax.set_ylabel("amplitude [N]")
        _shade(ax, loc, key)
    else:
        xs = np.asarray(getattr(pb, attr))
        ax.plot(xs, before, ".", ms=2, color="0.7", alpha=0.6, label="residual before (samples)")
        n_bins = int(np.clip(pb.n // 15, 8, 60))
        series = [before] + ([after] if finding else []) + ([term] if term is not None else [])
        centres, *means = _binned(xs, series, n_bins)
        ax.plot(centres, means[0], color="0.2", lw=1.8, label="before: binned mean")
        if finding:
            ax.plot(centres, means[1], color="tab:blue", lw=1.8, label="after: binned mean")
        if term is not None:
            ax.plot(
                centres,
                means[-1],
                color="tab:red",
                ls="--",
                lw=1.8,
                label="fitted term (binned mean)",
            )
        ax.axhline(0.0, color="0.3", lw=0.6)
        ax.set_ylabel("residual [N]")
        band = diag.near_rest.speed
        if attr == "v" and band > 0:
            ax.axvspan(-band, band, color="tab:purple", alpha=0.12, label=f"|v| < {band:.3g} m/s")
        _shade(ax, loc, key if key != "direction" else "")
    ax.set_xlabel(label)
    ax.grid(alpha=0.3, which="both")
    ax.legend(loc="best", fontsize=8)
    if finding:
        bic = finding.get("delta_bic")
        key_fig = f"ΔBIC {fmt(bic, 4)}" if bic is not None else ""
        ax.set_title(
            f"{index}. {effect} against {word} ({key_fig}); whole record: "
            f"{_ems_title(before, after)}",
            fontsize=10,
        )
    else:
        ax.set_title(
            f"No finding: residual against {word}; mean {np.mean(before):+.3g} N, "
            f"RMS {np.sqrt(np.mean(before**2)):.3g} N",
            fontsize=10,
        )
    fig.tight_layout()
    return save(fig, path)


def report_figures(diag: Diagnosis, out: Path) -> dict[str, Path]:
    """The overview against time and one figure per finding (or, with none, the residual
    against velocity, where a friction law's misfit shows)."""
    before, after = residuals(diag)
    paths = {"residual_time": overview_figure(diag, before, after, out / "residual_time.png")}
    for i, f in enumerate(diag.findings, 1):
        paths[f"finding_{i}"] = finding_figure(
            diag, i, f, before, after, out / f"finding_{i}_{f['effect']}.png"
        )
    if not diag.findings:
        paths["residual_v"] = finding_figure(diag, 0, {}, before, after, out / "residual_vs_v.png")
    return paths


# -- the report ----------------------------------------------------------------------------


def noise_blocks(diag: Diagnosis) -> list[Block]:
    """What the record allows: the noise model with its scale, error and degrees of
    freedom, the near-rest band in m/s and its share of the samples."""
    pb, ev, band = diag.problem, diag.evidence, diag.near_rest
    dt = float((pb.t[-1] - pb.t[0]) / (pb.n - 1))
    rows = [
        ("samples", f"{pb.n} over {pb.t[-1] - pb.t[0]:.4g} s ({1 / dt:.4g} Hz)"),
        ("σ_x of the record itself (its own high band, model-free)", ev.describe()),
    ]
    if diag.selection.whitener.spectral:
        text = (
            "Noise model: **spectral**. The drive input is recorded, so the residual's noise "
            "includes that input's own noise, which the displacement record cannot measure; "
            "the equation-error tests are scaled by the base residual's smoothed spectrum "
            f"(whitened scale {diag.selection.sigma:.3g}, dimensionless). The simulation "
            f"(output-error) test uses the record's own σ_x = {length(ev.sigma_x)}."
        )
    else:
        text = (
            f"Noise model: **displacement noise** on x ({ev.noise.model}), σ_x = "
            f"{length(ev.sigma_x)} measured from the record itself, not from any model's "
            f"residual. Every test and the BIC use it; its own uncertainty enters as ν = "
            f"{ev.nu} degrees of freedom (F instead of χ² references)."
        )
    blocks: list[Block] = [Para(text)]
    rows.append(("near-rest band |v| < κ·σ_v", f"|v| < {band.speed:.3g} m/s (κ = {band.kappa:g})"))
    n_band = int(np.sum(band.mask))
    rows.append(("samples in it", f"{n_band} of {pb.n} ({100 * band.share:.1f} %)"))
    held = pb.rest is not None and bool(np.any(pb.rest))
    blocks.append(
        Para(
            f"Near rest: {100 * band.share:.1f} % of the samples ({n_band} of {pb.n}) have "
            f"|v| < {band.speed:.3g} m/s, where noise could flip the sign of v (σ_v = "
            f"σ_x·{velocity_noise_gain(diag):.3g}/s through the velocity filter). "
            + (
                "The equation error holds them by the stick/slip rule and leaves them out of "
                "its tests; the simulation (output-error) test sees them."
                if held
                else "The base model at its fit has no static friction, so none is held at rest."
            )
        )
    )
    return [Heading("The record and its noise"), *blocks, Table(("quantity", "value"), tuple(rows))]


def fit_rows(diag: Diagnosis) -> list[tuple[str, str, str, str]]:
    """The fit table: (figure with its unit, base, base + findings, change)."""
    fb, fa = diag.fit["before"], diag.fit["after"]
    rows = [
        (
            "EMS, mean squared force residual [N²]",
            fmt(fb["ems"], 5),
            fmt(fa["ems"], 5),
            _pct(fb["ems"], fa["ems"]),
        ),
        (
            "BIC [-] (lower is better)",
            fmt(fb["bic"], 5),
            fmt(fa["bic"], 5),
            f"{fa['bic'] - fb['bic']:+.4g}" if math.isfinite(fa["bic"] - fb["bic"]) else "–",
        ),
        (
            "whiteness p (Ljung–Box; small = structure left)",
            fmt(fb["whiteness_p"], 3),
            fmt(fa["whiteness_p"], 3),
            "",
        ),
    ]
    sb, sa = fb["simulation_rms_m"], fa["simulation_rms_m"]
    rows.append(
        (
            "position RMS of one simulation over the whole record [mm]",
            fmt(1e3 * sb, 4) if math.isfinite(sb) else "not computed",
            fmt(1e3 * sa, 4) if math.isfinite(sa) else "not computed",
            _pct(sb, sa),
        )
    )
    if "output_error_cost" in fb:
        ob, oa = fb["output_error_cost"], fa["output_error_cost"]
        rows.append(
            (
                "output error of 0.05 s simulated segments [σ_x², whole record]",
                fmt(ob, 5),
                fmt(oa, 5),
                _pct(ob, oa),
            )
        )
    return rows


def fit_sentence(diag: Diagnosis) -> str:
    """The fit table in one sentence, from the same numbers."""
    fb, fa = diag.fit["before"], diag.fit["after"]
    text = f"EMS {fmt(fb['ems'], 5)} → {fmt(fa['ems'], 5)} N² ({_pct(fb['ems'], fa['ems'])})"
    sb, sa = fb["simulation_rms_m"], fa["simulation_rms_m"]
    if math.isfinite(sb) and math.isfinite(sa):
        text += f"; simulated position RMS {1e3 * sb:.3g} → {1e3 * sa:.3g} mm ({_pct(sb, sa)})"
    elif math.isfinite(sb):
        text += (
            f"; simulated position RMS {1e3 * sb:.3g} mm for the base (not computed with the "
            "findings: a term with internal state, which the simulator cannot integrate)"
        )
    if "output_error_cost" in fb:
        ob, oa = fb["output_error_cost"], fa["output_error_cost"]
        text += (
            f"; output error of the 0.05 s segments {fmt(ob, 4)} → {fmt(oa, 4)} σ_x² "
            f"({_pct(ob, oa)}, the measure the simulation test judged by)"
        )
    return text + "."


def _not_tested(diag: Diagnosis) -> list[str]:
    """Candidates a time limit left untested (a diagnosis with a stage clock), else []."""
    clock = getattr(diag, "clock", None)
    return list(clock.not_tested()) if clock is not None else []


def timing_blocks(diag: Diagnosis) -> list[Block]:
    """Wall time per stage, the limits, and what a limit left out, each by name."""
    clock = getattr(diag, "clock", None)
    if clock is None:
        return []
    from fricjax.diagnose.stages import STAGES

    t = clock.summary()
    limits = t["limits_s"]
    rows = tuple(
        (k, f"{t['stages_s'][k]:.1f}", fmt(limits.get(k), 4) if k in limits else "–")
        for k in STAGES
        if k in t["stages_s"]
    )
    blocks: list[Block] = [
        Heading("Time"),
        Para(
            f"{t['total_s']:.1f} s in all (limit {fmt(limits['total'], 4)} s); by stage "
            "(the report's own time so far):"
        ),
        Table(("stage", "time [s]", "limit [s]"), rows),
    ]
    if t["skipped"]:
        blocks += [
            Para("**Time limit hit**: this diagnosis is incomplete; what was left out:", "note"),
            Items(
                tuple(
                    f"at {s['stage']} ({s['at_s']:.1f} s, {s['limit']} limit): {s['what']}"
                    for s in t["skipped"]
                )
            ),
            Para("Raise `--time-limit` or `[diagnose] stage_limits` to test them."),
        ]
    return blocks


def _verdict(diag: Diagnosis) -> str:
    named = [f["effect"] for f in diag.findings if f["effect"] != "unexplained"]
    unexplained = sum(f["effect"] == "unexplained" for f in diag.findings)
    if not diag.findings and _not_tested(diag):
        return "**Nothing found among the candidates tested** (the others: see below)."
    if not diag.findings:
        return (
            "**Nothing is missing**: no catalogue term lowers BIC significantly and the "
            "residual shows no significant structure."
        )
    parts = []
    if named:
        parts.append(
            f"**{len(named)} finding{'s' if len(named) > 1 else ''}**: "
            + ", ".join(f"`{e}`" for e in named)
        )
    if unexplained:
        parts.append(
            f"**{unexplained} unexplained structure{'s' if unexplained > 1 else ''}** "
            "(significant, but no catalogue term explains it in a way that carries over)"
        )
    return "; ".join(parts) + "."


def _next_steps(diag: Diagnosis, bounded: Sequence[str]) -> list[str]:
    steps = []
    for i, f in enumerate(diag.findings, 1):
        effect = f["effect"]
        if effect == "unexplained":
            steps.append(
                f"Finding {i} (unexplained, {where_text(f.get('location', {}))}): look at its "
                "figure; check the sensor, the drive (saturation, current limit) and the "
                "mechanics at that place. A second recording of the same motion "
                "(`--validation`) tells reproducible physics from a one-off."
            )
            continue
        step = (
            f"Finding {i} (`{effect}`): add the term to your model in the config (see the "
            "config reference for its parameters and bounds), identify again and check "
            "the simulated position improves; its fitted values are in `models.h5` "
            "(group `final`)."
        )
        if not f.get("heldout_confirmed", False):
            step += (
                "The held-out check did not confirm it: record a second run and pass it with "
                "`--validation` before you rely on it."
            )
        if "near_rest_caveat" in f or "indistinguishable_from" in f:
            step += (
                "Its name is uncertain (see its caution): record slower motion with longer "
                "low-speed sliding to tell the low-speed laws apart."
            )
        steps.append(step)
    if bounded:
        steps.append(
            "Parameters on a bound of their search range ("
            + ", ".join(f"`{n}`" for n in bounded)
            + "): widen the bound in the config if a value beyond it is physically plausible, "
            "or record a motion that determines them (more cycles, a wider speed range); "
            "until then read them as limits."
        )
    if not diag.findings:
        left, n_base = diag.selection.whitener.dof, diag.base_spec.n_free
        if left <= 2 * n_base:
            steps.append(
                "Record a longer run of the same motion (several cycles): this one is too "
                "short "
                "to rule effects out."
            )
        else:
            steps.append(
                "No catalogue term is missing at this record's noise level: identify the "
                "base model (`fricjax identify`) and check it on a second recording "
                "(`fricjax validate`, `fricjax simulate`)."
            )
    ident = diag.extra.get("base_identify_ems")
    ems = diag.fit["before"]["ems"]
    if ident is not None and math.isfinite(ident) and ems > 2.0 * ident:
        steps.append(
            f"The diagnosis' base fit leaves EMS {fmt(ems, 5)} N², `identify` with the same "
            f"config {fmt(ident, 5)} N²: the tests were made around the poorer fit, so an "
            "effect may hide in what it leaves. Compare the two fits (`models.h5` group "
            "`base` against `fricjax identify`) before ruling effects out."
        )
    return steps


def simulation_blocks(diag: Diagnosis) -> list[Block]:
    """What the output-error test asked, where it ran and named nothing."""
    sim = diag.extra.get("simulation_test")
    if not sim or sim.get("chosen"):
        return []
    cands = sorted(sim.get("candidates", []), key=lambda c: -c["delta_bic"])
    text = (
        "Equation error named nothing here, so the friction laws were also tested by "
        "simulation (output error of short simulated segments), where how the plant stops "
        "and breaks away shows; none was named."
    )
    if cands:
        best = cands[0]
        text += (
            f" Best candidate: `{best['effect']}`, ΔBIC {fmt(best['delta_bic'], 4)}, "
            f"p = {best['p_value']:.2g} (a term must clear the ΔBIC bar, 10 by default, "
            "with a significant p)."
        )
    return [Para(text)]


def report_blocks(diag: Diagnosis, figures: Mapping[str, Path]) -> list[Block]:
    """The whole report, section by section (see docs/reading-a-report.md)."""
    blocks: list[Block] = [
        Heading(f"Diagnosis of `{diag.recording}`", 1),
        Para(f"Base model: `{diag.base_model}`. Verdict: {_verdict(diag)}"),
    ]
    if _not_tested(diag):
        blocks.append(
            Para(
                f"**Not tested (time limit)**: {', '.join(_not_tested(diag))} (section Time).",
                "note",
            )
        )
    blocks += [Para(fit_sentence(diag))]
    blocks += noise_blocks(diag)
    bounded_names: list[str] = []
    base_bounds = base_on_bounds(diag)
    if base_bounds:
        bounded_names += [b[0] for b in base_bounds]
        blocks += [
            Heading("Base parameters the record does not determine"),
            Para(
                "These base-fit parameters sit on a bound of their search range: the data "
                "push them further, so their values are limits of the search, not "
                "measurements, and the other parameters may compensate for them."
            ),
            Table(
                ("parameter", "fitted", "bound"),
                tuple(
                    (n, f"{fmt(v, 5)} {u}", f"{side} = {fmt(b, 5)} {u}")
                    for n, v, side, b, u in base_bounds
                ),
            ),
        ]
    blocks.append(Heading("Findings"))
    if not diag.findings:
        r = np.asarray(diag.problem.residual(diag.selection.base_theta))
        blocks.append(
            Para(
                f"{_verdict(diag)} The base fit's residual has mean {np.mean(r):+.3g} N and "
                f"RMS {np.sqrt(np.mean(r**2)):.3g} N (figure below)."
            )
        )
        left, n_base = diag.selection.whitener.dof, diag.base_spec.n_free
        if left <= 2 * n_base:
            # A short record's absence of findings is weak evidence: the base's parameters
            # take most of its whitened dimensions, and with them most of an effect's
            # signature.
            blocks.append(
                Para(
                    f"**Weak evidence on this record**: it leaves {left} whitened noise "
                    f"dimensions for the base's {n_base} parameters to fit, so the base "
                    "absorbs most of what a missing term would add and only large effects "
                    "can show. A longer recording of the same motion (several cycles) is "
                    "needed to rule effects out.",
                    "note",
                )
            )
        blocks += simulation_blocks(diag)
        if "residual_v" in figures:
            blocks.append(
                Image(
                    figures["residual_v"],
                    "Residual of the base fit against velocity: grey samples, binned mean; "
                    "the purple band is the samples marked at rest.",
                )
            )
    for i, f in enumerate(diag.findings, 1):
        blocks += finding_blocks(diag, i, f, figures.get(f"finding_{i}"), bounded_names)
    blocks += [Heading("Fit before and after"), Para(fit_sentence(diag))]
    blocks.append(Table(("figure", "base", "base + findings", "change"), tuple(fit_rows(diag))))
    ident = diag.extra.get("base_identify_ems")
    if ident is not None and math.isfinite(ident):
        blocks.append(
            Para(
                f"`identify` with the same config reached EMS {fmt(ident, 5)} N² on this "
                "record; the diagnosis refits the base in its whitened metric (GLS), which "
                "weighs frequencies by the noise model, not by force."
            )
        )
    if diag.extra.get("locate_after_skipped"):
        blocks.append(
            Para(
                "Residual maps and whiteness after the findings: not computed "
                f"({diag.extra['locate_after_skipped']}).",
                "note",
            )
        )
    blocks += heldout_blocks(diag)
    blocks += [Heading("Candidates scored at the first step"), score_table(diag)]
    blocks += [
        Heading("Next steps"),
        Items(tuple(_next_steps(diag, bounded_names)), ordered=True),
        Heading("Overview figure"),
        Image(
            figures["residual_time"],
            ("Residual before (top) and after (bottom)" if diag.findings else "Base residual")
            + " against time: grey samples, red running mean; orange: where a finding acts "
            "in time; purple ticks: samples at rest.",
        ),
    ]
    blocks += timing_blocks(diag)
    return blocks


def finding_blocks(
    diag: Diagnosis,
    i: int,
    f: Mapping[str, Any],
    figure: Path | None,
    bounded_names: list[str],
) -> list[Block]:
    """One finding: what, where, how big (bounds flagged), how sure, its figure."""
    blocks: list[Block] = [Heading(f"{i}. {f['effect']}", 3)]
    items = [f"**Where**: {where_text(f.get('location', {}))}"]
    bounds: list[tuple[str, str]] = []
    if "rejected_candidate" in f:
        rej = f["rejected_candidate"]
        shown, bounds = params_text(diag, rej["params"])
        items.append(f"**Fitted as** `{rej['effect']}` (not claimed): {shown}")
        if rej.get(FROZEN_KEY):
            items.append(f"**Held-out check**: {FROZEN_NOTE}")
    elif f.get("params"):
        shown, bounds = params_text(diag, f["params"])
        items.append(f"**Size**: {shown}")
    items.append(
        f"**How sure**: p = {f['p_value']:.2g} (calibrated), ΔBIC = {fmt(f['delta_bic'], 4)} "
        "(above 10: very strong evidence)"
    )
    if "heldout_improvement" in f:
        items.append(f"**Held-out gain**: {_heldout_verdict(dict(f))}")
    lead = "**Its size sits on a search bound (below): read it as a limit.** " if bounds else ""
    blocks += [Para(lead + f["explanation"]), Items(tuple(items))]
    for name, why in bounds:
        blocks.append(Para(f"**At a bound**: {why}.", "note"))
        bounded_names.append(name)
    if figure is not None:
        term = "; red dashed: the fitted term" if f.get("effect") != "unexplained" else ""
        blocks.append(
            Image(
                figure,
                f"Finding {i}: residual before (black) and after (blue) against the variable "
                f"that located it{term}; orange: where it acts.",
            )
        )
    return blocks


def heldout_blocks(diag: Diagnosis) -> list[Block]:
    if not diag.heldout:
        return []
    h = diag.heldout
    # the whitened residual is in m under displacement noise, in noise units under spectral
    unit = "" if diag.selection.whitener.spectral else " m²"
    blocks: list[Block] = [
        Heading("Held-out check"),
        Para(
            f"Fitted without the {h.get('on')} and scored on it: whitened RSS "
            f"{fmt(h['rss_w_before'], 6)} → {fmt(h['rss_w_after'], 6)}{unit} over {h['dof']} "
            f"noise dimensions ({100 * h['rss_w_improvement']:+.1f} %); EMS "
            f"{fmt(h['ems_before'], 6)} → {fmt(h['ems_after'], 6)} N² "
            f"({100 * h['ems_improvement']:+.1f} %). Decided by the {h['metric']} (the "
            "metric in which the noise model is white)."
        ),
    ]
    if h.get("mode") == "frozen":
        blocks.append(Para(FROZEN_NOTE, "note"))
    if "split" in h:
        hs = h["split"]
        blocks.append(
            Para(
                f"Also on the {hs['on']} (fitted on the rest; another part of the motion, "
                "where a term that only imitates the missing physics does not carry over): "
                f"{hs['metric']} {100 * hs['improvement']:+.1f} %. A finding must gain in "
                "every check that reaches its place."
            )
        )
    return blocks


# what a check that could fit only the finding's own parameters means (short records)
FROZEN_NOTE = (
    "The part the fit may use holds fewer whitened dimensions than the model has "
    "parameters, so only the finding's own parameters were fitted there, the others kept "
    "at the whole-record fit, which has seen the test part: the check leans towards the "
    "model without the finding. A longer recording, or a second one (--validation), "
    "judges it fully."
)


def _heldout_verdict(finding: dict) -> str:
    if finding.get(FROZEN_KEY):
        return (
            _heldout_text(finding)
            + " (only its own parameters fitted: "
            + ("the record is too short to refit the base on part of it)")
        )
    return _heldout_text(finding)


def _heldout_text(finding: dict) -> str:
    gain = f"{100 * finding['heldout_improvement']:+.1f} %"
    if "heldout_split_improvement" in finding:
        split = f"{100 * finding['heldout_split_improvement']:+.1f} %"
        why = finding.get("heldout_split_untestable")
        if why == SPLIT_DEFERS:
            split += " (not judging: the record's first part cannot determine the model)"
        elif why:
            split += " (untested there)"
        gain += f" on the second recording, {split} on the record's last part"
    if finding.get("heldout_untestable"):
        if finding.get("heldout_cv_improvement") is not None:
            cv = f"{100 * finding['heldout_cv_improvement']:+.1f} %"
            k = finding.get(CV_FOLDS_KEY, CV_FOLDS)
            verdict = "confirmed" if finding.get("heldout_confirmed") else "NOT confirmed"
            why = finding["heldout_untestable"]
            said = "not judging" if why == SPLIT_FROZEN else "untested"
            return (
                f"{gain} ({said}: {why}); judged instead by "
                f"{k}-fold cross-validation over the record's whitened coordinates: "
                f"{cv} ({verdict}; a second recording that passes there, --validation, is "
                "the stronger test)"
            )
        return (
            f"{gain} (untested: {finding['heldout_untestable']}; a second recording that "
            "passes there, --validation, can confirm it)"
        )
    return f"{gain} ({'confirmed' if finding.get('heldout_confirmed') else 'NOT confirmed'})"


def score_table(diag: Diagnosis) -> Block:
    if not diag.selection.steps:
        return Para("(no candidate applicable)")
    step = diag.selection.steps[0]
    refit = {r.effect: r for r in step.refits}
    rows = []
    for s in sorted(step.scores, key=lambda s: s.p_value):
        r = refit.get(s.effect)
        rows.append(
            (
                f"`{s.effect}`",
                s.test,
                fmt(s.stat, 4),
                f"{s.p_value:.2g}",
                fmt(s.delta_bic_linear, 4),
                fmt(r.delta_bic, 4) if r else "–",
            )
        )
    return Table(
        ("effect", "test", "statistic", "p (calibrated)", "ΔBIC (linearised)", "ΔBIC after refit"),
        tuple(rows),
    )


def write_reports(diag: Diagnosis, out: Path) -> dict[str, Path]:
    """Figures, ``report.md`` and the self-contained ``report.html`` into ``out``."""
    figures = report_figures(diag, out)
    blocks = report_blocks(diag, figures)
    return {
        **figures,
        "report": write_text_atomic(out / "report.md", to_markdown(blocks)),
        "html": write_text_atomic(
            out / "report.html", to_html(blocks, f"Diagnosis of {Path(diag.recording).name}")
        ),
    }


def markdown_report(diag: Diagnosis, figures: Mapping[str, Path]) -> str:
    """The report as Markdown (``figures`` from :func:`report_figures`)."""
    return to_markdown(report_blocks(diag, figures))
