"""The diagnosis report for a test engineer: ``report.md`` and a self-contained
``report.html`` from the same blocks (:mod:`fricjax.report.document`), with one figure: the
output-error residual (simulated minus recorded position, in units of the record's noise)
of the base and of the final model over time, the places of the findings shaded.

Every figure a sentence quotes comes from diagnosis.json's numbers and carries its unit;
parameters on a bound of their search range are flagged as bounds, not measurements.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import h5py
import numpy as np

from fricjax.diagnose.run import jsonable
from fricjax.diagnose.select import Finding, Verdict, outcome
from fricjax.io.atomic import make_folder, write_hdf5_atomic, write_text_atomic
from fricjax.params import on_bound
from fricjax.report.document import Block, Heading, Image, Items, Para, Table, to_html, to_markdown
from fricjax.report.plots import plt, save
from fricjax.report.tables import fmt, p_text

if TYPE_CHECKING:
    from fricjax.diagnose.across import AcrossDiagnosis
    from fricjax.diagnose.judge import CandidateFit, Fitted
    from fricjax.diagnose.run import Diagnosis
    from fricjax.diagnose.select import Step
    from fricjax.diagnose.stages import Clock

_PLACES = {
    "time_s": ("t", "s"),
    "position_m": ("x", "m"),
    "velocity_mps": ("v", "m/s"),
    "acceleration_mps2": ("a", "m/s²"),
    "frequency_hz": ("f", "Hz"),
    "period_m": ("period", "m"),
    "presliding_distance_m": ("presliding distance", "m"),
}


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


#: The verdict of a diagnosis of one record that finds nothing.
NOTHING = (
    "**Nothing is missing**: no catalogue term passes the judge and the model fits the "
    "record to its noise."
)


def _pct(gain: float) -> str:
    """A relative gain in per cent, or "not computed"."""
    return f"{100 * gain:+.1f} %" if math.isfinite(gain) else "not computed"


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


def params_text(diag: Diagnosis, params: Mapping[str, float]) -> tuple[str, list[str]]:
    """(``name = value unit`` list, a sentence for each parameter on a bound)."""
    spec = diag.final.problem.spec
    shown, bounds = [], []
    for name, value in params.items():
        known = name in spec.names
        unit = spec[name].unit if known else ""
        unit = "" if unit in ("", "1", "-") else f" {unit}"
        shown.append(f"{name} = {fmt(float(value), 4)}{unit}")
        side = on_bound(spec if known else None, name, float(value))
        if side:
            p = spec[name]
            bounds.append(
                f"`{name}` = {fmt(float(value), 4)}{unit} sits on the {side} bound of its search "
                f"range [{fmt(p.lower, 4)}, {fmt(p.upper, 4)}]{unit}: a limit of the search, "
                "not a measurement"
            )
    return ", ".join(shown), bounds


def residual_figure(diag: Diagnosis, path: Path) -> Path:
    """Output-error residual (x_sim − x)/σ_x of the base and the final model against t."""
    pb = diag.problem
    fig, ax = plt.subplots(figsize=(8, 3.2))
    for label, m in (("base", diag.base), ("final", diag.final)):
        if label == "final" and m is diag.base:
            continue
        r = (m.fit.x_sim - pb.x) / m.fit.x_scale
        ax.plot(pb.t, r, lw=0.8, label=f"{label} ({m.cost:.4g} σ_x² in all)")
    for f in diag.findings:
        span = f.location.get("time_s")
        if isinstance(span, list | tuple) and len(span) == 2:
            ax.axvspan(float(span[0]), float(span[1]), color="tab:orange", alpha=0.15)
    ax.axhline(2, color="0.6", lw=0.6, ls=":")
    ax.axhline(-2, color="0.6", lw=0.6, ls=":")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("(x_sim − x)/σ_x")
    ax.legend(fontsize=8)
    fig.suptitle(f"{Path(diag.recording).name}: output-error residual")
    fig.tight_layout()
    return save(fig, path)


def verdict(findings: Sequence[Finding], clock: Clock, nothing: str) -> str:
    """The report's first sentence: the time limit (if hit), then the findings, an
    ambiguity set as ``a`` or ``b``; ``nothing``: what an empty diagnosis means."""
    cut = clock.headline()
    text = _findings_verdict(findings, clock, nothing)
    return f"**{cut}** {text}" if cut else text


def _findings_verdict(findings: Sequence[Finding], clock: Clock, nothing: str) -> str:
    named = [f for f in findings if f.named]
    unexplained = len(findings) - len(named)
    if not findings and clock.skipped:
        # a diagnosis cut short cannot say that nothing is missing
        return "**Nothing found among the candidates tested** (see Time)."
    if not findings:
        return nothing
    parts = []
    if named:
        shown = [" or ".join(f"`{m}`" for m in f.members) for f in named]
        parts.append(f"**{len(named)} finding(s)**: " + ", ".join(shown))
    if unexplained:
        parts.append(
            f"**{unexplained} unexplained** (the record holds more than its noise, and no "
            "catalogue term explains it in a way that carries over)"
        )
    return "; ".join(parts) + "."


def data_blocks(diag: Diagnosis) -> list[Block]:
    ev, band = diag.evidence, diag.near_rest
    return [
        Heading("The record"),
        Para(
            f"Displacement noise measured from the record itself: {ev.describe()}. Every test "
            "is in units of it."
        ),
        Para(
            f"Near rest (|v| < {band.speed:.3g} m/s, where noise can flip the sign of the "
            f"filtered velocity): {100 * band.share:.1f} % of the samples. The judge works in "
            "output error, which needs no velocity, so these samples are judged like the rest."
        ),
    ]


def fit_blocks(diag: Diagnosis) -> list[Block]:
    b, a = diag.fit["before"], diag.fit["after"]
    rows = (
        ("EMS [N²]", fmt(b["ems"], 5), fmt(a["ems"], 5)),
        ("output error [σ_x²]", fmt(b["output_error_cost"], 5), fmt(a["output_error_cost"], 5)),
        ("lack of fit p", f"{b['lack_of_fit_p']:.3g}", f"{a['lack_of_fit_p']:.3g}"),
        ("simulation rms", length(b["simulation_rms_m"]), length(a["simulation_rms_m"])),
        ("free parameters", str(b["n_free"]), str(a["n_free"])),
    )
    return [
        Heading("Fit"),
        Para(
            f"`identify` alone reaches EMS {fmt(diag.identify_ems, 5)} N²; the diagnosis refits "
            "its estimate by output error (the base below)."
        ),
        Table(("", "base", "final"), rows),
    ]


def finding_blocks(
    findings: Sequence[Finding],
    parameters: Callable[[Mapping[str, float], Finding], tuple[str, list[str]]],
    data: str,
) -> list[Block]:
    """Each finding with its evidence, for one record or several (``data``: "record" or
    "recordings"): what and where, its parameters (``parameters(params, finding)``: the
    text and a sentence for each on a bound), its statistics, the held-out checks (each
    part where a check has parts), the warnings and the candidates it cannot be told from."""
    blocks: list[Block] = []
    for i, f in enumerate(findings, 1):
        blocks += [Heading(f"Finding {i}: `{f.label}`", 3), Para(f.explanation)]
        blocks.append(Para(f"Where: {where_text(f.location)}."))
        if f.params:
            shown, bounds = parameters(f.params, f)
            blocks.append(Para(f"Parameters: {shown}."))
            if bounds:
                blocks.append(Items(tuple(bounds)))
        if not f.named:
            continue
        blocks.append(Para(_statistics(f)))
        held = [q for v in f.heldout for q in (v.parts or (v,))]
        if held:
            blocks += [Para("Held out:"), Items(tuple(_held_text(q) for q in held))]
        for w in f.warnings:
            blocks.append(Para(f"**Warning**: {w}.", "note"))
        for a in f.alternatives:
            shown, _ = parameters(a.params, a)
            blocks.append(
                Para(
                    f"Or `{a.label}` ({where_text(a.location)}; {shown}): ΔBIC "
                    f"{a.delta_bic:.1f}; the {data} does not prefer `{f.label}` over it "
                    f"(Vuong t = {a.evidence['vuong_t']:.2f}, {p_text(a.evidence['vuong_p'])})."
                )
            )
    return blocks


def _statistics(f: Finding) -> str:
    """ΔBIC and p, with the judge's own figures: Wald's W across recordings; the record's
    EMS and simulation error beside one record's (reported, never judged)."""
    e = f.evidence
    text = f"ΔBIC {f.delta_bic:.1f}, {p_text(f.p_value)}"
    if "statistic" in e:
        text += f"; W = {e['statistic']:.2f} on {e['dof']} degrees of freedom"
    if "record_ems_gain" in e:
        text += (
            f"; record EMS {_pct(e['record_ems_gain'])}, simulation error "
            f"{_pct(e['record_simulation_gain'])} better"
        )
    return text + "."


def _held_text(v: Verdict) -> str:
    if not v.judged:
        return f"{v.on}: not judged ({v.why})"
    return f"{v.on}: {100 * v.gain:+.1f} % (cost {fmt(v.cost_base, 4)} → {fmt(v.cost_term, 4)})"


def _candidate_row(st: Step[Fitted, CandidateFit], f: CandidateFit) -> tuple[str, ...]:
    """One candidate's row: its refit's statistic and what the rule made of it."""
    decision = outcome(st, f)
    return (
        f.effect,
        str(f.k),
        str(f.looks),
        f"{f.lr:.1f}",
        p_text(f.p_value).removeprefix("p = "),
        f"{f.delta_bic:.1f}",
        decision,
    )


def candidate_blocks(diag: Diagnosis) -> list[Block]:
    blocks: list[Block] = []
    for i, st in enumerate(diag.steps, 1):
        rows = tuple(_candidate_row(st, f) for f in sorted(st.fits, key=lambda f: -f.delta_bic))
        blocks += [
            Para(
                f"Step {i}: every candidate refitted from each of its starts; one must reach "
                f"p < {st.limit:.2g} (p of the best of its shapes) and ΔBIC > "
                f"{st.min_delta_bic:g}, and hold in cross-validation:"
            ),
            Table(("candidate", "k", "shapes", "LR [σ_x²]", "p", "ΔBIC", "decision"), rows),
        ]
    return [Heading("Candidates"), *blocks] if blocks else []


def timing_blocks(clock: Clock) -> list[Block]:
    """Wall time per stage, the limits, and what a limit left out, each by name."""
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
        Para(f"{t['total_s']:.1f} s in all (limit {fmt(limits['total'], 4)} s)."),
        Table(("stage", "time [s]", "limit [s]"), rows),
    ]
    if t["skipped"]:
        why = "Interrupted (Ctrl-C)" if t.get("interrupted") else "Time limit hit"
        blocks += [
            Para(f"**{why}**: this diagnosis is incomplete; left out:", "note"),
            Items(tuple(f"at {s['stage']} ({s['at_s']:.1f} s): {s['what']}" for s in t["skipped"])),
        ]
    return blocks


def report_blocks(diag: Diagnosis, figure: Path) -> list[Block]:
    return [
        Heading(f"Diagnosis of `{diag.recording}`", 1),
        Para(
            f"Base model: `{diag.base_model}`. "
            f"Verdict: {verdict(diag.findings, diag.clock, NOTHING)}"
        ),
        *finding_blocks(diag.findings, lambda params, _: params_text(diag, params), "record"),
        *data_blocks(diag),
        *fit_blocks(diag),
        Image(figure, "Output-error residual of the base and final models; orange: findings."),
        *candidate_blocks(diag),
        *timing_blocks(diag.clock),
    ]


def write_reports(diag: Diagnosis, out: Path) -> dict[str, Path]:
    """The figure, ``report.md`` and the self-contained ``report.html`` into ``out``."""
    figure = residual_figure(diag, out / "residual_output_error.png")
    blocks = report_blocks(diag, figure)
    return {
        "figure": figure,
        "report": write_text_atomic(out / "report.md", to_markdown(blocks)),
        "html": write_text_atomic(
            out / "report.html", to_html(blocks, f"Diagnosis of {Path(diag.recording).name}")
        ),
    }


# -- several recordings ---------------------------------------------------------------------

#: The verdict of a diagnosis across recordings that finds nothing.
NOTHING_ACROSS = "**Nothing found**: no shared catalogue term and no drift passes the judge."


def _with_sigma(params: Mapping[str, float], f: Finding) -> tuple[str, list[str]]:
    """``value ± σ (name)`` for each parameter of a joint finding (no bounds are flagged:
    the joint box is the union of the recordings')."""
    sigma = f.evidence.get("sigma", {})
    shown = ", ".join(
        (f"{fmt(v, 4)} ± {fmt(sigma[n], 2)}" if sigma.get(n) else fmt(v, 4)) + f" ({n})"
        for n, v in params.items()
    )
    return shown, []


def across_blocks(diag: AcrossDiagnosis) -> list[Block]:
    """The report across recordings: the verdict, each finding with its evidence, the
    recordings, every candidate of every step, the fit and the time."""
    d = diag.to_json()
    blocks: list[Block] = [
        Heading(f"Diagnosis across {len(d['recordings'])} recordings", 1),
        Para(f"Verdict: {verdict(diag.findings, diag.clock, NOTHING_ACROSS)}"),
    ]
    blocks += finding_blocks(diag.findings, _with_sigma, "recordings")
    blocks += [
        Heading("The recordings"),
        Table(
            ("#", "recording", "direction", "σ_x", "ν", "weight scale s_k [N]"),
            tuple(
                (
                    str(k),
                    r["name"],
                    r["direction"],
                    length(r["sigma_x_m"]),
                    str(r["nu"]),
                    fmt(r["sigma_weight_N"], 4),
                )
                for k, r in enumerate(d["recordings"], 1)
            ),
        ),
        Heading("Candidates"),
    ]
    for st in d["candidates"]:
        blocks += [
            Para(
                f"Step {st['step']}: every shared term and drift fitted jointly; one must "
                f"reach p < {st['limit_p']:.2g} and ΔBIC > {st['min_delta_bic']:g}, and gain "
                "where a recording can be left out:"
            ),
            Table(
                ("candidate", "k", "shapes", "W", "p", "ΔBIC", "decision"),
                tuple(
                    (
                        t["name"],
                        str(t["k"]),
                        str(t["looks"]),
                        fmt(t["statistic"], 4),
                        p_text(t["p_value"]).removeprefix("p = "),
                        fmt(t["delta_bic"], 4),
                        t["verdict"],
                    )
                    for t in sorted(d["candidates"][st["step"] - 1]["tested"], key=_by_bic)
                ),
            ),
        ]
    before, after = d["fit"]["before"], d["fit"]["after"]
    blocks += [
        Heading("Fit"),
        Table(
            ("", "base", "final"),
            (
                ("weighted joint cost", fmt(before["cost"], 6), fmt(after["cost"], 6)),
                ("parameters", str(len(before["parameters"])), str(len(after["parameters"]))),
            ),
        ),
        *timing_blocks(diag.clock),
    ]
    return blocks


def _by_bic(t: Mapping[str, Any]) -> float:
    b = t["delta_bic"]
    return -b if isinstance(b, float) and math.isfinite(b) else math.inf


def write_across(diag: AcrossDiagnosis, out_dir: str | Path) -> dict[str, Path]:
    """Write diagnosis.json, report.md and report.html into ``out_dir`` (atomic)."""
    out = make_folder(out_dir)
    with diag.clock.stage("report", "report"):
        blocks = across_blocks(diag)
        paths = {
            "report": write_text_atomic(out / "report.md", to_markdown(blocks)),
            "html": write_text_atomic(
                out / "report.html", to_html(blocks, "Diagnosis across recordings")
            ),
        }
    text = json.dumps(jsonable(diag.to_json()), indent=2, ensure_ascii=False)
    paths["json"] = write_text_atomic(out / "diagnosis.json", text + "\n")
    return paths


# -- output --------------------------------------------------------------------------------

#: The files :func:`write_diagnosis` writes under fixed names (plus its figures).
OUTPUT_FILES = ("diagnosis.json", "models.h5", "report.md", "report.html")


def write_diagnosis(diag: Diagnosis, out_dir: str | Path) -> dict[str, Path]:
    """Write diagnosis.json, models.h5, report.md, report.html and its figures into
    ``out_dir``."""
    out = make_folder(out_dir)
    json_name, models_name = OUTPUT_FILES[:2]
    paths = {"json": out / json_name}
    with diag.clock.stage("report", "figures, models file and report"):
        paths["models"] = _write_models(diag, out / models_name)
        paths.update(write_reports(diag, out))
    # diagnosis.json last, so its timing holds the report stage too
    write_text_atomic(paths["json"], json.dumps(diag.as_json(), indent=2) + "\n")
    return paths


def _write_models(diag: Diagnosis, path: Path) -> Path:
    def fill(f: h5py.File) -> None:
        f.attrs["format"] = "fricjax-diagnosis-models-v1"
        f.attrs["recording"] = diag.recording
        f.attrs["sigma_x_m"] = diag.evidence.sigma_x
        f.attrs["n_samples"] = diag.problem.n
        for label, m in (("base", diag.base), ("final", diag.final)):
            _write_fitted(f.create_group(label), m)
        # every model each step compared, so that a next test can be designed to tell any
        # of them apart (fricjax design) without refitting them
        for i, step in enumerate(diag.steps):
            g = f.create_group(f"steps/{i}")
            chosen = step.chosen
            g.attrs["named"] = chosen.fit.effect if chosen is not None else ""
            _write_fitted(g.create_group("base"), step.current)
            for cf in step.fits:
                sub = g.create_group(cf.effect)
                _write_fitted(sub, cf.fitted)
                sub.attrs["delta_bic"] = cf.delta_bic
                sub.attrs["p_value"] = cf.p_value

    return write_hdf5_atomic(path, fill)


def _write_fitted(g: h5py.Group, m: Fitted) -> None:
    """One fitted model: its catalogue terms (``active``), every parameter's value, and
    the Gauss–Newton covariance of the free ones (``cov`` [k, k], SI units²)."""
    model, spec, theta = m.reduced()
    g.attrs["model"] = model.name
    g.attrs["terms"] = json.dumps([t.name for t in model.terms])
    g.attrs["active"] = json.dumps(list(m.active))
    g.attrs["cost"] = m.cost
    named = spec.as_dict(theta)
    g["names"] = np.array(list(named), dtype=h5py.string_dtype())
    g["values"] = np.array(list(named.values()), dtype=np.float64)
    g["free"] = np.array([spec[n].free for n in named], dtype=bool)
    g["units"] = np.array([spec[n].unit for n in named], dtype=h5py.string_dtype())
    g["cov"] = m.covariance([n for n in named if spec[n].free])
