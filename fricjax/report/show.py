"""Text reports of identification results (``fricjax identify`` / ``fricjax show``)."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np

from fricjax.config import parse_config
from fricjax.errors import FricjaxError, where
from fricjax.io.results import ResultsFile, RunResult, read_results
from fricjax.model.system import MASS
from fricjax.params import check_value
from fricjax.report.tables import SEED_GROUPS, fmt, format_table, seed_tables


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


def _cost_rows(run: RunResult) -> list[tuple[str, str]]:
    a = run.attrs
    if str(a.get("objective", "")).startswith("output error"):
        # The output-error cost is Σ((x_sim − x)/σ_x)² + defects: not in N², not an EMS.
        return [
            ("objective", str(a["objective"])),
            ("equation-error EMS of the start [N²]", fmt(a.get("equation_ems", float("nan")), 7)),
            ("output-error cost [(x/σ_x)²]", fmt(run.cost, 7)),
            ("position RMS [m]", fmt(a.get("position_rms", float("nan")), 4)),
        ]
    return [
        ("cost after search [N²]", fmt(run.cost_search, 7)),
        (
            "cost after refine [N²]",
            fmt(run.cost, 7) if a.get("refined", True) else "not refined",
        ),
        ("EMS [N²] (seed Table 4)", fmt(run.ems, 7)),
    ]


def run_summary(run: RunResult, *, recording: str | Path | None = None) -> str:
    """What ``identify`` prints at the end: fit figures, parameters, flags, minima census."""
    a = run.attrs
    head = format_table(
        [
            ("method", run.method),
            ("search", str(a.get("search_space", "full"))),
            (
                "chains x levels",
                f"{a.get('n_chains')} x {a.get('levels')} ({a.get('n_evals')} cost evaluations)",
            ),
            *_cost_rows(run),
            ("wall time [s]", f"{a.get('wall_time', float('nan')):.2f}"),
            ("interrupted", str(a.get("interrupted", False))),
        ]
    )
    parts = [head, parameter_table(run)]
    flagged = [f"{n}: {f}" for n, f in zip(run.names, run.flags, strict=True) if f]
    if flagged:
        parts.append("Not pinned down by this recording:\n  " + "\n  ".join(flagged))
    if len(run.minima_cost):
        rows = [
            (str(i + 1), fmt(float(c), 7), str(int(k)))
            for i, (c, k) in enumerate(zip(run.minima_cost, run.minima_count, strict=True))
        ]
        parts.append(
            "Distinct end points of the chains (before refinement):\n"
            + format_table(rows[:8], ("minimum", "cost [N²]", "chains"))
        )
    truth = _truth_for(recording)
    if truth:
        parts.append(seed_tables({run.label: run.params}, ems={run.label: run.ems}, truth=truth))
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
            if name in spec:
                check_value(spec[name], value, where(path, f"/runs/{run.label}: {name}"))


def show_results(path: str | Path, *, recording: str | Path | None = None) -> str:
    """Seed Tables 1–4, one column per run, truth/error columns when the recording is a twin."""
    results: ResultsFile = read_results(path)
    _check_domains(path, results)
    rec = recording or results.attrs.get("recording_path") or None
    truth = _truth_for(rec)
    runs = results.runs
    columns = {r.label: r.params for r in runs}
    ems = {r.label: r.ems for r in runs}
    extra = sorted({n for r in runs for n in r.names} - {n for _, g in SEED_GROUPS for n in g})
    header = (
        f"results: {path}\nrecording: {results.attrs.get('recording_name')} "
        f"(sha256 {str(results.attrs.get('recording_sha256'))[:16]})"
    )
    body = seed_tables(columns, ems=ems, truth=truth, extra_rows=extra)
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
        ("run", "method", "cost [N²]", "EMS [N²]", "before refine", "time [s]"),
    )
    return f"{header}\n\n{body}\n\nRuns ranked by final cost\n{ranking}"
