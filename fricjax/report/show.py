"""Text reports of identification results (``fricjax identify`` / ``fricjax show``)."""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fricjax.config import parse_config
from fricjax.errors import FricjaxError, where
from fricjax.identify import MISFIT_LIMIT
from fricjax.io.results import ResultsFile, RunResult, read_results
from fricjax.joint import is_joint, members_of, split_name
from fricjax.model.system import MASS
from fricjax.params import check_value
from fricjax.report.tables import SEED_GROUPS, fmt, format_fields, format_table, seed_tables
from fricjax.units import AxisUnits, axis_units


def run_units(run: RunResult) -> AxisUnits:
    """The axis units of a run (``axis`` attr written by identify; linear if absent)."""
    return axis_units(str(run.attrs.get("axis", "linear") or "linear"))


def _truth_for(path: str | Path | None) -> dict[str, float] | None:
    """A twin's generating parameters, for error columns (scoring only, never fitting)."""
    if path is None or not Path(path).exists():
        return None
    from fricjax.data.twin import read_truth

    truth = read_truth(path)
    if not truth:
        return None
    return {k: float(v) for k, v in truth.items() if isinstance(v, int | float)}


def parameter_table(run: RunResult) -> str:
    """Identified values with σ, relative σ and identifiability flags."""
    rows = []
    for i, name in enumerate(run.names):
        rows.append(
            (
                name,
                run.units[i],
                fmt(float(run.value[i]), 6),
                fmt(float(run.std[i]), 3),
                f"{100 * float(run.rel_std[i]):.3g}%" if np.isfinite(run.rel_std[i]) else "inf",
                run.flags[i],
            )
        )
    return format_table(rows, ("parameter", "unit", "value", "σ", "σ/|value|", "flags"))


#: A parameter is loose when its ±2σ interval (95 %) is wider than ±half its scale, i.e.
#: σ > scale/4: the record cannot tell the value from half or 1.5 times it. Scale: |value|,
#: or half the box width when the box holds 0 or the value is 0 (an offset or a phase may
#: sit near 0).
LOOSE_SIGMA = 0.25
#: Pairs with |ρ| above this are reported as traded against each other: along their
#: combination the cost changes 1/(1 − ρ²) ≥ 50 times less than along each alone.
STRONG_CORRELATION = 0.99
#: Friction parameters: their cure is excitation in velocity, not more drive periods.
_FRICTION = ("Fc", "Fs", "vs", "delta", "Fv")


def undetermined(run: RunResult) -> dict[str, str]:
    """Parameters the record does not determine, each with the reason in words: on a bound
    of the box, σ above :data:`LOOSE_SIGMA` of its scale, or not determined at all."""
    out: dict[str, str] = {}
    for i, name in enumerate(run.names):
        value, sd = float(run.value[i]), float(run.std[i])
        lo, hi, unit = float(run.lower[i]), float(run.upper[i]), run.units[i]
        reasons = []
        tol = 1e-6 * (hi - lo)
        if value <= lo + tol or value >= hi - tol:
            side = "lower" if value <= lo + tol else "upper"
            reasons.append(f"on its {side} bound ({fmt(value, 4)} {unit}): the box set it")
        scale = 0.5 * (hi - lo) if lo < 0.0 < hi or value == 0.0 else abs(value)
        if not np.isfinite(sd):
            reasons.append("not determined at all (no curvature of the cost along it)")
        elif scale > 0.0 and sd > LOOSE_SIGMA * scale:
            reasons.append(f"±2σ = ±{fmt(2 * sd, 3)} {unit}, {share(2 * sd / scale)}")
        if reasons:
            out[name] = "; ".join(reasons)
    return out


def share(ratio: float) -> str:
    """A ratio to a value ("it") in words a person reads: ``"35 % of it"`` up to 10, then
    ``"4.2e+03 times it"`` (a percentage of sixteen digits says no more than "far larger")."""
    return f"{100 * ratio:.0f} % of it" if ratio < 10 else f"{ratio:.2g} times it"


def correlated_pairs(run: RunResult) -> list[tuple[str, str, float]]:
    """Parameter pairs with |ρ| > :data:`STRONG_CORRELATION`, strongest first."""
    corr = np.asarray(run.corr)
    pairs = [
        (run.names[i], run.names[j], float(corr[i, j]))
        for i in range(len(run.names))
        for j in range(i + 1, len(run.names))
        if np.isfinite(corr[i, j]) and abs(corr[i, j]) > STRONG_CORRELATION
    ]
    return sorted(pairs, key=lambda p: -abs(p[2]))


def misfit(run: RunResult) -> str:
    """Plain words when the fitted model does not explain the record within its noise (cost
    over the noise-only cost above :data:`fricjax.identify.MISFIT_LIMIT`); "" when it does
    or when the run carries no noise model."""
    a = run.attrs
    u = run_units(run)
    if str(a.get("objective", "")).startswith("output error"):
        ratio = float(run.ems)  # E_OE per residual entry, in σ_x²
        rms, sigma = float(a.get("position_rms", np.nan)), float(a.get("x_scale", np.nan))
        if not ratio > MISFIT_LIMIT:
            return ""
        return (
            f"The model does NOT fit this record: simulated, it misses the recorded position "
            f"by {fmt(rms, 3)} {u.position} rms, {rms / sigma:.3g} times the noise "
            f"(σ_x = {fmt(sigma, 3)} {u.position}). The values are the best this model can do, "
            "not the plant's: σ says how well the record pins them under this model, not how "
            "far they are from the truth. Find what the model leaves out with `fricjax "
            "diagnose`."
        )
    phi = float(a.get("dispersion", np.nan))
    if not phi > MISFIT_LIMIT:
        return ""
    return (
        f"The model does NOT fit this record by equation error: its residual is {phi:.3g} "
        "times the cost of the record's noise alone. An equation-error estimate is then "
        "biased (where the body sticks and slips, or where the model lacks physics): these "
        "values are not measured. Refine them by simulation (`--objective simulation`, which "
        "the default `auto` runs by itself) and find what is missing with `fricjax diagnose`."
    )


def determination(run: RunResult) -> str:
    """Plain words: whether the model fits the record (:func:`misfit`), which parameters the
    record does not determine, and what would fix it."""
    wrong = misfit(run)
    loose = undetermined(run)
    pairs = correlated_pairs(run)
    record, subject = (
        ("the joint records", "The joint records do")
        if is_joint(run)
        else ("this record", "This record does")
    )
    if wrong:
        return "\n".join([wrong, *_determination(run, loose, pairs, record, subject, fits=False)])
    return "\n".join(_determination(run, loose, pairs, record, subject, fits=True))


def _determination(
    run: RunResult,
    loose: dict[str, str],
    pairs: list[tuple[str, str, float]],
    record: str,
    subject: str,
    *,
    fits: bool,
) -> list[str]:
    # a table flag measures σ against the value itself; near zero that says nothing of
    # how well the record pins a signed parameter, which ``undetermined`` judges against
    # its box: say so rather than leave the flag and the verdict to contradict each other
    near_zero = [
        n
        for n, f in zip(run.names, run.flags, strict=True)
        if n not in loose and any(x.startswith("weakly determined") for x in f)
    ]
    zero_note = (
        [
            f"{', '.join(near_zero)}: flagged because the value is near zero, not because the "
            "record leaves it loose (σ is small against its box); read it as the value ± σ."
        ]
        if near_zero
        else []
    )
    if not loose and not pairs and not fits:
        return [
            f"Under this model, {record} pins every parameter (±2σ within "
            f"±{200 * LOOSE_SIGMA:.0f} % of its value, none on a bound).",
            *zero_note,
        ]
    if not loose and not pairs:
        return [
            f"Every parameter is determined by {record} (±2σ within ±{200 * LOOSE_SIGMA:.0f} %"
            " of its value, none on a bound).",
            *zero_note,
        ]
    lines = []
    if loose:
        lines.append(
            f"{subject} NOT determine {len(loose)} of {len(run.names)} parameters: "
            f"{', '.join(loose)}. Their values come from the box or the noise, not from the "
            "physics; do not read them as measured."
        )
        width = max(len(n) for n in loose)
        lines += [f"  {n:<{width}}  {why}" for n, why in loose.items()]
    if pairs:
        shown = ", ".join(f"{a}–{b} (ρ = {r:.3f})" for a, b, r in pairs[:8])
        more = f" and {len(pairs) - 8} more" if len(pairs) > 8 else ""
        lines.append(
            f"Traded against each other (|ρ| > {STRONG_CORRELATION}): {shown}{more}; the record "
            "fixes a combination of each pair, not the two apart."
        )
    names = set(loose) | {n for a, b, _ in pairs for n in (a, b)}
    fixes = ["a longer record (σ falls as 1/√duration)"]
    if names & set(_FRICTION):
        fixes.append(
            "richer excitation for the friction terms: more velocity reversals, slow and fast "
            "sliding both"
        )
    if names - set(_FRICTION):
        fixes.append("more periods of the drive, or an input with more frequencies")
    fixes.append(
        "fix a parameter known from elsewhere in the config ({ value = ... }), which also "
        "frees the ones traded against it"
    )
    if any("bound" in why for why in loose.values()):
        fixes.append("widen a box whose bound is not physical")
    lines.append("What would fix it: " + "; ".join(fixes) + ".")
    on_bound = [n for n, why in loose.items() if "bound" in why]
    if len(on_bound) >= max(2, len(run.names) / 2):
        # a record and a box that disagree on scale put nearly everything on a bound
        lines.append(
            f"{len(on_bound)} of {len(run.names)} parameters sit on a bound: the recording's "
            "scale and the config's bounds disagree. Check the units (x in mm instead of m? "
            "mass in g? force in kN?) or write bounds from the recording with "
            "`fricjax init-config`."
        )
    return lines


def _cost_rows(run: RunResult) -> list[tuple[str, str]]:
    a = run.attrs
    u = run_units(run)
    sq = u.force_sq
    if is_joint(run):
        # Σ_k ‖r_k‖²/s_k²: dimensionless, ≈ 1 per residual entry when the weights are right
        return [
            ("objective", str(a.get("objective", ""))),
            ("joint cost after search [1]", fmt(run.cost_search, 7)),
            (
                "joint cost after refine [1]",
                fmt(run.cost, 7) if a.get("refined", True) else "not refined",
            ),
            ("joint cost per residual entry [1] (≈ 1)", fmt(run.ems, 5)),
        ]
    if str(a.get("objective", "")).startswith("output error"):
        # The output-error cost is Σ((x_sim − x)/σ_x)² + defects: not in N², not an EMS.
        return [
            ("objective", str(a["objective"])),
            (f"equation-error EMS of the start [{sq}]", fmt(a.get("equation_ems", np.nan), 7)),
            ("output-error cost [(x/σ_x)²]", fmt(run.cost, 7)),
            (f"position RMS [{u.position}]", fmt(a.get("position_rms", float("nan")), 4)),
        ]
    return [
        (f"cost after search [{sq}]", fmt(run.cost_search, 7)),
        (
            f"cost after refine [{sq}]",
            fmt(run.cost, 7) if a.get("refined", True) else "not refined",
        ),
        (f"EMS [{sq}] (seed Table 4)", fmt(run.ems, 7)),
    ]


def _sigma_rows(a: dict) -> list[tuple[str, str]]:
    """Which σ the run reports (``fricjax.identify.sigma_attrs``); none for older files."""
    if "sigma_method" not in a:
        return []
    rows = [("σ", f"{a['sigma_method']}: {a.get('sigma_noise', '')}")]
    if np.isfinite(float(a.get("dispersion", float("nan")))):
        rows.append(("dispersion (cost / noise-only cost)", f"{float(a['dispersion']):.3g}"))
    return rows


def _cost_unit(run: RunResult) -> str:
    """Unit of a run's cost: the force squared, or 1 for a joint run (Σ_k ‖r_k‖²/s_k²)."""
    return "1" if is_joint(run) else run_units(run).force_sq


def run_summary(run: RunResult, *, recording: str | Path | None = None) -> str:
    """What ``identify`` prints at the end: fit figures, parameters, flags, minima census."""
    a = run.attrs
    head = format_fields(
        [
            ("method", run.method),
            ("search", str(a.get("search_space", "full"))),
            (
                "chains x levels",
                f"{a.get('n_chains')} x {a.get('levels')} ({a.get('n_evals')} cost evaluations)",
            ),
            *_cost_rows(run),
            *(
                [("refined by output error", str(a["refined_by_output_error"]))]
                if "refined_by_output_error" in a
                else []
            ),
            *_sigma_rows(a),
            ("wall time [s]", f"{a.get('wall_time', float('nan')):.2f}"),
            ("interrupted", str(a.get("interrupted", False))),
        ]
    )
    parts = [head, parameter_table(run), determination(run)]
    if is_joint(run):
        parts.append(joint_section(run))
    if len(run.minima_cost):
        rows = [
            (str(i + 1), fmt(float(c), 7), str(int(k)))
            for i, (c, k) in enumerate(zip(run.minima_cost, run.minima_count, strict=True))
        ]
        parts.append(
            "Distinct end points of the chains (before refinement):\n"
            + format_table(rows[:8], ("minimum", f"cost [{_cost_unit(run)}]", "chains"))
        )
    truth = _truth_for(recording)
    if truth:
        parts.append(
            seed_tables(
                {run.label: run.params},
                ems={run.label: run.ems},
                truth=truth,
                ems_unit=run_units(run).force_sq,
            )
        )
    return "\n\n".join(parts)


def _check_domains(path: str | Path, results: ResultsFile) -> None:
    """Refuse a run value outside its parameter's physical domain (a mass of −5 kg), the
    model taken from the config stored in the file; without a usable one, values are
    shown as stored."""
    try:
        cfg = parse_config(tomllib.loads(str(results.attrs.get("config", ""))))
    except (tomllib.TOMLDecodeError, FricjaxError):
        return
    spec = cfg.spec if cfg.mass_in_spec else cfg.spec.extended([MASS])
    for run in results.runs:
        for name, value in run.params.items():
            base = split_name(name)[0]  # a joint run's Fc[2] is an Fc
            if base not in spec:
                field = "params/names" if name in run.names else "params: fixed attrs"
                raise FricjaxError(
                    f"{where(path, f'/runs/{run.label}/{field}')}: {name!r} is not a "
                    f"parameter of the model in the file's config (it takes: "
                    f"{', '.join(spec.names)})"
                )
            check_value(spec[base], value, where(path, f"/runs/{run.label}: {name}"))


def show_results(path: str | Path, *, recording: str | Path | None = None) -> str:
    """Seed Tables 1–4, one column per run, truth/error columns when the recording is a twin."""
    results: ResultsFile = read_results(path)
    _check_domains(path, results)
    rec = recording or results.attrs.get("recording_path") or None
    truth = _truth_for(rec)
    runs = results.runs
    sq = run_units(runs[0]).force_sq if runs else "N²"
    if runs and all(is_joint(r) for r in runs):
        sq = "1"  # a joint cost sums each recording's squared residual over its s_k²
    columns = {r.label: r.params for r in runs}
    ems = {r.label: r.ems for r in runs}
    extra = sorted({n for r in runs for n in r.names} - {n for _, g in SEED_GROUPS for n in g})
    header = (
        f"results: {path}\nrecording: {results.attrs.get('recording_name')} "
        f"(sha256 {str(results.attrs.get('recording_sha256'))[:16]})"
    )
    body = seed_tables(columns, ems=ems, truth=truth, extra_rows=extra, ems_unit=sq)
    ranking = format_table(
        [
            (
                r.label,
                r.method,
                fmt(r.cost, 7),
                fmt(r.ems, 7),
                fmt(r.cost_search, 7),
                f"{r.attrs.get('wall_time', float('nan')):.2f}",
            )
            for r in sorted(runs, key=lambda r: r.cost)
        ],
        ("run", "method", f"cost [{sq}]", f"EMS [{sq}]", "before refine", "time [s]"),
    )
    joint = [joint_section(r) for r in runs if is_joint(r)]
    return "\n\n".join([header, body, f"Runs ranked by final cost\n{ranking}", *joint])


def joint_section(run: RunResult) -> str:
    """A joint run's recordings (residual entries, weight scale s_k, EMS of the own fit
    and at the joint optimum) and its drift check (:func:`drift_lines`)."""
    sq = run_units(run).force_sq
    force = run_units(run).force
    rows = [
        (
            str(k + 1),
            str(m.get("name", "")),
            str(m.get("n", "")),
            fmt(float(m.get("sigma", np.nan)), 4),
            fmt(float(m.get("own_ems", np.nan)), 5),
            fmt(float(m.get("ems", np.nan)), 5),
        )
        for k, m in enumerate(members_of(run))
    ]
    table = format_table(
        rows,
        ("k", "recording", "n", f"s_k [{force}]", f"own EMS [{sq}]", f"joint EMS [{sq}]"),
    )
    return "\n".join(
        [
            "Recordings of the joint fit (NAME[k] is recording k's own value; each residual "
            "is divided by s_k, the residual scale of the recording's own fit):",
            table,
            "",
            *drift_lines(run),
        ]
    )


@dataclass(frozen=True)
class DriftFinding:
    """The drift test of one per-recording parameter of a joint run (:func:`joint_drift`).

    ``name``: the parameter; ``values``, ``stds`` [K]: its value and σ per recording;
    ``z_max``: the largest |z| (NaN: not tested, a σ not finite); ``threshold``: z*;
    ``m``: z-scores in the Bonferroni family; ``drifted``: ``z_max > threshold``."""

    name: str
    values: np.ndarray
    stds: np.ndarray
    z_max: float
    threshold: float
    m: int

    @property
    def drifted(self) -> bool:
        return bool(self.z_max > self.threshold)


def joint_drift(run: RunResult) -> list[DriftFinding]:
    """The drift check of a joint run: per-recording parameters whose values differ
    between the recordings beyond their σ ([] without per-recording parameters).

    The fleet's statistic (:func:`fricjax.report.fleet.drift`): each recording's value
    against the inverse-variance mean of the others, z-scores judged by the Bonferroni
    threshold z* over all of them at family-wise α = 0.05. A parameter drifts when some
    |z| exceeds z*; with two recordings this is |x_1 − x_2|/√(σ_1² + σ_2²) > z*. The z
    ignore the correlation the shared parameters put between the recordings' values (ρ
    in the run's correlation matrix)."""
    from fricjax.report.fleet import drift

    k_count = len(members_of(run))
    bases = list(dict.fromkeys(b for b, k in map(split_name, run.names) if k is not None))
    if not bases or k_count < 2:
        return []
    pos = {name: i for i, name in enumerate(run.names)}
    idx = np.array([[pos[f"{b}[{k + 1}]"] for b in bases] for k in range(k_count)])
    values, stds = np.asarray(run.value)[idx], np.asarray(run.std)[idx]
    test = drift(values, stds)
    out = []
    for j, base in enumerate(bases):
        z = np.abs(test.z[:, j])
        z_max = float(np.nanmax(z)) if np.isfinite(z).any() else float("nan")
        out.append(DriftFinding(base, values[:, j], stds[:, j], z_max, test.threshold, test.m))
    return out


def drift_lines(run: RunResult) -> list[str]:
    """:func:`joint_drift` in words, one line per per-recording parameter."""
    from fricjax.report.fleet import ALPHA

    findings = joint_drift(run)
    if not findings:
        return ["Drift check: no per-recording parameter ([joint].per_recording is empty)."]
    lines = []
    for f in findings:
        shown = ", ".join(
            f"{f.name}[{k + 1}] = {fmt(float(v), 5)} ± {fmt(float(s), 2)}"
            for k, (v, s) in enumerate(zip(f.values, f.stds, strict=True))
        )
        if f.drifted:
            lines.append(
                f"Drift: {f.name} differs between the recordings beyond its σ (max |z| = "
                f"{f.z_max:.3g} > z* = {f.threshold:.3g}): {shown}."
            )
        elif np.isfinite(f.z_max):
            lines.append(
                f"No drift of {f.name} (max |z| = {f.z_max:.3g} ≤ z* = {f.threshold:.3g}): {shown}."
            )
        else:
            lines.append(f"Drift of {f.name} not tested (σ not finite): {shown}.")
    lines.append(
        f"(z of each recording against the others' inverse-variance mean, Bonferroni over "
        f"{findings[0].m} tests at family-wise α = {ALPHA:g}; fricjax.report.fleet.)"
    )
    return lines
