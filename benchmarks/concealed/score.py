"""Score ``fricjax diagnose`` on the concealed benchmark's two draws (``generate.py``).

Three stages, all by default (``--stage``):

* ``generate``: write the cases of both draws missing from ``--data`` (deterministic by the
  draws' seeds; an existing file is kept);
* ``diagnose``: run ``fricjax diagnose`` (the CLI, this checkout's code, unchanged) on every
  case in its own process, ``--workers`` at a time, each killed after ``--timeout`` s and
  then recorded as ``timeout``. Every case's folder ``RESULTS/draw<X>/CASE/`` gets
  ``diagnosis.json`` (the CLI's) and ``run.json`` (status, exit code, wall time, git commit
  and whether fricjax/ was modified, the config and its SHA-256, the resolved diagnose
  settings, jax version, load average). A case with ``run.json`` is finished and never run
  again; a folder without one (a run killed mid-case) is cleared and run again. The longest
  records go first. ``--start-until S``: start no case after S s (the run then ends
  within S + timeout);
* ``report``: read the truths (only now) and the results, and write Markdown + PNGs:
  detection, top-1, false discoveries, outside-catalogue outcomes, time, each per noise
  level, length and plant family, per draw, beside the oracle.

::

    PYTHONPATH=. python benchmarks/concealed/score.py --workers 2
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from collections import Counter
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import generate as gen

ROOT = gen.ROOT
DEFAULT_DATA = ROOT / "out" / "concealed"
DEFAULT_REPORT = ROOT / "benchmarks" / "results" / "concealed" / "report.md"
DEFAULT_TIMEOUT = 300.0
STATUSES = ("ok", "timeout", "error")


# -- running ---------------------------------------------------------------------------------
def git_state() -> dict[str, Any]:
    """HEAD and whether fricjax/ or the configs differ from it (None outside git)."""

    def run(*args: str) -> str | None:
        try:
            done = subprocess.run(
                ["git", *args], cwd=ROOT, capture_output=True, text=True, check=True
            )
        except (OSError, subprocess.CalledProcessError):
            return None
        return done.stdout.strip()

    status = run("status", "--short", "fricjax", "configs", "benchmarks/concealed/configs")
    return {"commit": run("rev-parse", "HEAD"), "modified": status.splitlines() if status else []}


def settings_of(config: Path) -> dict[str, Any]:
    """The config's SHA-256 and the diagnose settings it resolves to (the CLI's defaults
    under its ``[diagnose]`` table)."""
    import dataclasses

    from fricjax.config import load_config
    from fricjax.diagnose.run import DiagnoseSettings

    cfg = load_config(config)
    settings = DiagnoseSettings.from_dict(dict(cfg.table("diagnose")), source=cfg.source)
    return {
        "config": str(config.relative_to(ROOT)) if config.is_relative_to(ROOT) else str(config),
        "config_sha256": hashlib.sha256(config.read_bytes()).hexdigest(),
        "diagnose_settings": {k: repr(v) for k, v in dataclasses.asdict(settings).items()},
    }


#: Seconds a diagnosis is given, below the scorer's kill, to write what it has when it stops
#: at its own time limit (the report and plots of a 4 s record take ~10 s on a loaded core).
REPORT_MARGIN = 30.0


def case_dir(results: Path, draw: str, case: str) -> Path:
    return results / f"draw{draw}" / case


def finished(folder: Path, sha256: str | None = None) -> bool:
    """Whether the case's diagnosis is finished (its ``run.json`` written) — on the
    recording whose checksum is ``sha256`` where given: a run of other bits is stale."""
    run = folder / "run.json"
    if not run.is_file():
        return False
    return sha256 is None or json.loads(run.read_text()).get("recording_sha256") == sha256


def recording_sha256(path: Path) -> str:
    """The recording's checksum (its numbers, not the file's bytes: the truth is left out)."""
    from fricjax.data.recording import read_recording

    return read_recording(path).sha256()


def run_case(
    recording: Path,
    config: Path,
    folder: Path,
    timeout: float,
    context: dict[str, Any],
    time_limit: float | None = None,
) -> dict[str, Any]:
    """``fricjax diagnose RECORDING --config CONFIG --out FOLDER [--time-limit T]`` in a new
    process group, killed (the whole group) after ``timeout`` s; writes and returns
    ``FOLDER/run.json``."""
    from fricjax.io.atomic import write_text_atomic

    if folder.exists():  # a partial case: cleared, run again
        shutil.rmtree(folder)
    folder.mkdir(parents=True)

    def here(path: Path) -> str:
        # the process runs in ROOT: paths relative to it keep this machine out of the
        # committed run files
        path = Path(path).resolve()
        return str(path.relative_to(ROOT)) if path.is_relative_to(ROOT) else str(path)

    cmd = [
        sys.executable,
        "-c",
        "import sys; from fricjax.cli import main; sys.argv[0] = 'fricjax'; main()",
        "diagnose",
        here(recording),
        "--config",
        here(config),
        "--out",
        here(folder),
        *(["--time-limit", f"{time_limit:g}"] if time_limit else []),
    ]
    env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    load = os.getloadavg()
    t0 = time.perf_counter()
    proc = subprocess.Popen(
        cmd, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        start_new_session=True,
    )  # fmt: skip
    try:
        out, err = proc.communicate(timeout=timeout)
        status = "ok" if proc.returncode == 0 else "error"
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        status = "timeout"
    wall = time.perf_counter() - t0
    if status == "ok" and not (folder / "diagnosis.json").is_file():
        status = "error"
    run = {
        "case": folder.name,
        "status": status,
        "returncode": proc.returncode,
        "wall_s": wall,
        "timeout_s": timeout,
        "command": " ".join(["fricjax", *cmd[3:]]),
        "stdout_tail": out[-2000:],
        "stderr_tail": err[-2000:],
        "load_average_at_start": load,
        "recording_sha256": recording_sha256(recording),
        "finished_at": time.strftime("%Y-%m-%d %H:%M:%S"),
        **context,
    }
    write_text_atomic(folder / "run.json", json.dumps(run, indent=1) + "\n")
    return run


def diagnose_all(
    data: Path,
    results: Path,
    draws: Sequence[str],
    workers: int,
    timeout: float,
    resume: bool = True,
    limit: int = 0,
    start_until: float = 0.0,
    log: Callable[[str], None] = print,
    time_limit: float = 0.0,
    order: str = "long",
) -> list[dict[str, Any]]:
    """Every case of the draws' plans (the first ``limit`` of each where > 0) not finished
    in ``results`` (all of them without ``resume``), longest record first; returns the runs
    made now. Each diagnosis gets its own time limit ``time_limit`` (default: the timeout
    less :data:`REPORT_MARGIN`), so that a slow case ends with what it tested and what it
    skipped instead of being killed with nothing."""
    time_limit = time_limit if time_limit > 0 else max(timeout - REPORT_MARGIN, 1.0)
    import jax

    from fricjax.bench.machine import describe

    state = git_state()
    configs = {f: settings_of(c) for f, c in gen.CONFIGS.items()}
    host = describe()
    machine = f"{host.cpu}, {host.cores} cores, {host.ram_gib:.0f} GiB"
    todo = []
    for draw in draws:
        specs = gen.plan(gen.DRAWS[draw])
        specs = specs[:limit] if limit > 0 else specs
        for s in specs:
            folder = case_dir(results, draw, s.case_id(gen.DRAWS[draw]))
            rec = gen.case_path(data, draw, s)
            if not rec.is_file():
                log(f"{draw} {folder.name}: no recording (generate first)")
                continue
            if resume and finished(folder, recording_sha256(rec)):
                continue
            if finished(folder):
                log(f"{draw} {folder.name}: its run was made on other bits; run again")
            todo.append((s, draw, folder))
    if order == "long":  # many workers: the slowest cases must not start last
        todo.sort(key=lambda q: (-q[0].duration, q[0].index, q[1]))
    else:  # one worker against a deadline: the most cases, the draws taking turns
        rank: Counter[tuple[str, float]] = Counter()
        keyed = []
        for q in sorted(todo, key=lambda q: (q[0].duration, q[1] != draws[0], q[0].index)):
            keyed.append(((q[0].duration, rank[(q[1], q[0].duration)]), q))
            rank[(q[1], q[0].duration)] += 1
        todo = [q for _, q in sorted(keyed, key=lambda kq: (kq[0], kq[1][1] != draws[0]))]
    log(f"diagnosing {len(todo)} cases with {workers} workers, timeout {timeout:g} s")
    t_start = time.monotonic()

    def one(item: tuple[gen.CaseSpec, str, Path]) -> dict[str, Any] | None:
        spec, draw, folder = item
        if start_until and time.monotonic() - t_start > start_until:
            return None
        context = {
            "draw": draw,
            "git": state,
            "jax": jax.__version__,
            "python": sys.version.split()[0],
            "workers": workers,
            "machine": machine,
            "nice": os.nice(0),
            "jax_platforms": os.environ.get("JAX_PLATFORMS", ""),
            "xla_flags": os.environ.get("XLA_FLAGS", ""),
            "diagnose_time_limit_s": time_limit,
            **configs[spec.family],
        }
        rec = gen.case_path(data, draw, spec)
        run = run_case(rec, gen.CONFIGS[spec.family], folder, timeout, context, time_limit)
        log(f"{draw} {folder.name} T={spec.duration:g}s {run['status']} {run['wall_s']:.0f} s")
        return run

    with ThreadPoolExecutor(max_workers=max(1, workers)) as pool:
        return [r for r in pool.map(one, todo) if r is not None]


# -- scoring ---------------------------------------------------------------------------------
def outcome(truth: dict[str, Any], run: dict[str, Any] | None, diag: dict | None) -> dict:
    """One case scored: its status and, where it ran, what was found against the right
    answer (``first``: the first finding's effect, ``none`` for no finding). ``sigma`` is
    the σ_x the record has (``sigma_planned`` the plan's, where the generator lowered it)."""
    row = {
        k: truth[k]
        for k in ("case", "family", "effect", "sigma", "duration", "level", "kind", "right_answer")
    }
    row["sigma_planned"] = truth.get("sigma_planned", truth["sigma"])
    row["run"] = run
    row["c"] = truth.get("concealment", 0.0)
    row["on_level"] = truth["kind"] == "null" or gen.counted(row["c"], truth["level"])
    row["pays"] = truth.get("oracle_pays")
    row["oracle_dbic"] = truth.get("oracle_dbic")
    row["status"] = "not run" if run is None else run["status"]
    row["wall_s"] = None if run is None else run["wall_s"]
    names = [f["effect"] for f in (diag or {}).get("findings", [])]
    row["names"] = names
    row["first"] = names[0] if names else gen.NULL
    ok = row["status"] == "ok"
    row["detected"] = ok and bool(names)
    row["top1"] = ok and row["first"] == truth["right_answer"]
    # the diagnosis' own refits at its first step (every candidate refitted from each of
    # its starts): does the true term pass its rule there, and does it lead by ΔBIC?
    step = ((diag or {}).get("candidates") or [{}])[0]
    tested = {f["effect"]: f for f in step.get("tested", [])}
    own = tested.get(truth["effect"])
    row["own_pays"] = bool(
        ok
        and own is not None
        and own["p_value"] is not None
        and own["p_value"] < step["limit_p"]
        and own["delta_bic"] > step.get("min_delta_bic", 10.0)
    )
    row["own_best"] = bool(
        own is not None and max(tested.values(), key=lambda f: f["delta_bic"] or -math.inf) is own
    )
    first = ((diag or {}).get("findings") or [{}])[0]
    members = [first.get("effect"), *(a["effect"] for a in first.get("alternatives", []))]
    row["in_set2"] = ok and truth["right_answer"] in members and len(members) <= 2
    named = [n for n in names if n != gen.UNEXPLAINED]
    row["outside_outcome"] = (
        None
        if truth["kind"] != "outside" or not ok
        else "wrong name"
        if named
        else "unexplained"
        if names
        else "nothing"
    )
    return row


def load_rows(
    data: Path, results: Path, draws: Sequence[str], labels: Sequence[str] = ()
) -> dict[str, list[dict]]:
    """Per draw, every planned case that has a recording, scored (:func:`outcome`) against
    the diagnoses in ``results/draw<X>``; with ``labels``, against each labelled set
    ``results/LABEL/draw<X>`` in turn, keyed ``"<X> LABEL"`` (the labels of a draw side by
    side). A run made on other bits than the recording's is not counted (stale)."""
    out: dict[str, list[dict]] = {}
    for draw in draws:
        plan_file = data / f"draw{draw}" / "plan.json"
        if not plan_file.is_file():
            continue
        cases = [
            (c["case"], gen.read_truth(data / f"draw{draw}" / c["recording"]))
            for c in json.loads(plan_file.read_text())["cases"]
            if (data / f"draw{draw}" / c["recording"]).is_file()
        ]
        for label in labels or [""]:
            rows = []
            for case, truth in cases:
                folder = case_dir(results / label if label else results, draw, case)
                done = finished(folder, truth.get("recording_sha256"))
                run = json.loads((folder / "run.json").read_text()) if done else None
                diag_path = folder / "diagnosis.json"
                diag = json.loads(diag_path.read_text()) if run and diag_path.is_file() else None
                rows.append({**outcome(truth, run, diag), "draw": draw, "label": label})
            out[f"{draw} {label}" if label else draw] = rows
    return out


def tally(rows: Sequence[dict]) -> dict[str, Any]:
    """Counts of one group of scored cases (finished ones; ``n_*`` the denominators)."""
    done = [r for r in rows if r["status"] != "not run"]
    cat = [r for r in done if r["kind"] == "catalogue" and r["on_level"]]
    pays = [r for r in cat if r["pays"]]
    own = [r for r in cat if r.get("own_pays")]
    nul = [r for r in done if r["kind"] == "null"]
    out_ = [r for r in done if r["kind"] == "outside" and r["on_level"]]
    walls = sorted(r["wall_s"] for r in done if r["status"] == "ok")
    return {
        "cat": len(cat),
        "detected": sum(r["detected"] for r in cat),
        "top1": sum(r["top1"] for r in cat),
        "pays": len(pays),
        "top1_pays": sum(r["top1"] for r in pays),
        "own_pays": len(own),
        "top1_own": sum(r["top1"] for r in own),
        "set_own": sum(r["in_set2"] for r in own),
        "best_own": sum(r["own_best"] for r in own),
        "null": len(nul),
        "false": sum(r["detected"] for r in nul),
        "outside": len(out_),
        "unexplained": sum(r["outside_outcome"] == "unexplained" for r in out_),
        "wrong": sum(r["outside_outcome"] == "wrong name" for r in out_),
        "short": sum(not r["on_level"] for r in done),
        "timeout": sum(r["status"] == "timeout" for r in done),
        "error": sum(r["status"] == "error" for r in done),
        "not_run": len(rows) - len(done),
        "median_s": walls[len(walls) // 2] if walls else None,
    }


def _frac(k: int, n: int) -> str:
    return f"{k}/{n}" if n else "–"


def _cells(t: dict[str, Any]) -> list[str]:
    return [
        _frac(t["detected"], t["cat"]),
        _frac(t["top1"], t["cat"]),
        _frac(t["pays"], t["cat"]),
        _frac(t["top1_pays"], t["pays"]),
        _frac(t["own_pays"], t["cat"]),
        _frac(t["top1_own"], t["own_pays"]),
        _frac(t["set_own"], t["own_pays"]),
        _frac(t["best_own"], t["own_pays"]),
        _frac(t["false"], t["null"]),
        _frac(t["unexplained"], t["outside"]),
        _frac(t["wrong"], t["outside"]),
        f"{t['short']}",
        f"{t['timeout']}" + (f" (+{t['error']} err)" if t["error"] else ""),
        "–" if t["median_s"] is None else f"{t['median_s']:.0f}",
    ]


HEAD = [
    "detected",
    "top-1",
    "oracle pays",
    "top-1 where it pays",
    "own refits pay",
    "top-1 where own pays",
    "in a set of ≤ 2 where own pays",
    "largest ΔBIC where own pays",
    "false discoveries (nulls)",
    "outside → unexplained",
    "outside → wrong name",
    "off level (left out)",
    "timeouts",
    "median s/case",
]


def group_table(by: dict[str, list[dict]], title: str, key: Callable[[dict], Any]) -> list[str]:
    """One Markdown table: a row per (value of ``key``, draw)."""
    lines = [f"### By {title}", "", "| " + " | ".join([title, "draw", *HEAD]) + " |"]
    lines.append("|" + "---|" * (len(HEAD) + 2))

    def order(v: str) -> tuple[int, float, str]:
        try:
            return (0, float(v), v)
        except ValueError:
            return (1, 0.0, v)

    values = sorted({key(r) for rows in by.values() for r in rows}, key=order)
    for v in [*values, "all"]:
        for draw, rows in by.items():
            sel = rows if v == "all" else [r for r in rows if key(r) == v]
            label = f"**{v}**" if v == "all" else f"{v}"
            lines.append("| " + " | ".join([label, draw, *_cells(tally(sel))]) + " |")
    return [*lines, ""]


def confusion(rows: Sequence[dict]) -> tuple[list[str], list[str], list[list[int]]]:
    done = [r for r in rows if r["status"] == "ok" and r["on_level"]]
    truths = [e for e in (*gen.CATALOGUE_EFFECTS, *gen.OUTSIDE_EFFECTS, gen.NULL)
              if any(r["effect"] == e for r in done)]  # fmt: skip
    found = sorted({r["first"] for r in done})
    mat = [[sum(r["effect"] == t and r["first"] == f for r in done) for f in found] for t in truths]
    return truths, found, mat


def report(by: dict[str, list[dict]], out: Path, header: dict[str, str], machine_md: str) -> str:
    """Markdown report (and PNGs beside it); returns the text."""
    from fricjax.io.atomic import write_text_atomic

    labels = list(dict.fromkeys(r["label"] for rows in by.values() for r in rows if r["label"]))
    title = " beside ".join(f"`{lb}`" for lb in labels) if labels else "`fricjax diagnose`"
    lines = [f"# Concealed benchmark: {title}", ""]
    lines += [f"- **{k}**: {v}" for k, v in header.items()]
    lines += ["", "## Machine (report assembled on)", "", machine_md, ""]
    lines += [
        "## How to read",
        "",
        "Effect cases count where their concealment is within a factor "
        f"{gen.REACHED:g} of their level either way (the others are *off level*, listed "
        "below; σ_x is the record's, lowered by the generator where no record at the "
        "planned noise shows the effect at its level: see *Reach*). *detected*: any finding; "
        "*top-1*: the first finding is the hidden effect; *oracle pays*: the true term, "
        "refitted with the base in output error on the noisy record, lowers BIC by more "
        "than the diagnosis' bar (docs/concealed-benchmark.md); *false discoveries*: nulls "
        "with any finding; outside-catalogue effects should end `unexplained` (*wrong name*: "
        "any catalogue name among the findings). Draw A may be looked at when choosing a "
        "threshold, draw B never. With several labels (diagnosis versions), each draw has "
        "a row per label.",
        "",
    ]
    lines += group_table(by, "noise σ_x [µm]", lambda r: f"{r['sigma'] * 1e6:g}")
    lines += group_table(by, "length [s]", lambda r: f"{r['duration']:g}")
    lines += group_table(by, "family", lambda r: r["family"])
    lines += group_table(by, "level c", lambda r: f"{r['level']:g}" if r["level"] else "null")
    lines += group_table(by, "effect", lambda r: r["effect"])
    for draw, rows in by.items():
        truths, found, mat = confusion(rows)
        lines += [f"### Confusion, draw {draw} (hidden effect × first finding)", ""]
        lines += ["| hidden \\ first | " + " | ".join(found) + " |"]
        lines += ["|" + "---|" * (len(found) + 1)]
        lines += [
            f"| {t} | " + " | ".join(str(v) if v else "" for v in row) + " |"
            for t, row in zip(truths, mat, strict=True)
        ]
        lines.append("")
    lines += reach_table(by)
    lines += ["## Every case", ""]
    lines += [
        "| draw | case | family | effect | σ_x µm | T s | level | c | oracle ΔBIC | status "
        "| s | findings |",
        "|" + "---|" * 12,
    ]
    for draw, rows in by.items():
        for r in rows:
            dbic, wall = r["oracle_dbic"], r["wall_s"]
            planned = (
                ""
                if r["sigma"] == r["sigma_planned"]
                else f" (planned {r['sigma_planned'] * 1e6:g})"
            )
            lines.append(
                f"| {draw} | {r['case']} | {r['family']} | {r['effect']} | "
                f"{r['sigma'] * 1e6:g}{planned} | {r['duration']:g} | {r['level']:g} | {r['c']:.2f}"
                f"{'' if r['on_level'] else ' (off level)'} | "
                f"{'–' if dbic is None else f'{dbic:.3g}'} | {r['status']} | "
                f"{'–' if wall is None else f'{wall:.0f}'} | "
                f"{', '.join(r['names']) or '–'} |"
            )
    lines.append("")
    plots = make_plots(by, out)
    lines += ["## Plots", ""] + [f"![{p.stem}]({p.name})" for p in plots] + [""]
    text = "\n".join(lines)
    write_text_atomic(out, text)
    return text


def make_plots(by: dict[str, list[dict]], out: Path) -> list[Path]:
    """Top-1 (catalogue) per noise level and family with the oracle's share (black ticks),
    time per case against length, and the confusion matrices."""
    import numpy as np

    from fricjax.report.plots import plt, save

    paths = []
    fig, axes = plt.subplots(1, len(by), figsize=(5.5 * max(len(by), 1), 4), squeeze=False)
    for ax, (draw, rows) in zip(axes[0], by.items(), strict=False):
        for j, fam in enumerate(gen.FAMILIES):
            rates, pays = [], []
            for s in gen.SIGMAS:
                t = tally([r for r in rows if r["family"] == fam and r["sigma"] == s])
                rates.append(t["top1"] / t["cat"] if t["cat"] else np.nan)
                pays.append(t["pays"] / t["cat"] if t["cat"] else np.nan)
            at = np.arange(len(gen.SIGMAS)) + 0.25 * (j - 1)
            ax.bar(at, rates, 0.25, label=fam, color=f"C{j}")
            ax.plot(at, pays, "_", ms=14, mew=2, color="k", label="oracle pays" if j == 0 else None)
        ax.set_xticks(range(len(gen.SIGMAS)), [f"{s * 1e6:g}" for s in gen.SIGMAS])
        ax.set_xlabel("σ_x [µm]")
        ax.set_ylabel("top-1 (catalogue cases)")
        ax.set_ylim(0, 1.05)
        ax.set_title(f"draw {draw}")
        ax.legend(fontsize=8)
    fig.tight_layout()
    paths.append(save(fig, out.with_name(f"{out.stem}_top1.png")))
    fig, ax = plt.subplots(figsize=(6, 4))
    for draw, rows in by.items():
        pts = [(r["duration"], r["wall_s"], r["status"]) for r in rows if r["wall_s"] is not None]
        for status, marker in (("ok", "o"), ("timeout", "x"), ("error", "^")):
            sel = [(d, w) for d, w, s in pts if s == status]
            if sel:
                ax.scatter(*zip(*sel, strict=True), marker=marker, label=f"{draw} {status}")
    ax.set_xscale("log")
    ax.set_xlabel("record length [s]")
    ax.set_ylabel("diagnose wall time [s]")
    ax.legend(fontsize=8)
    fig.tight_layout()
    paths.append(save(fig, out.with_name(f"{out.stem}_time.png")))
    for draw, rows in by.items():
        truths, found, mat = confusion(rows)
        if not truths or not found:
            continue
        fig, ax = plt.subplots(figsize=(1.5 + 0.6 * len(found), 1.2 + 0.4 * len(truths)))
        ax.imshow(np.array(mat), cmap="Blues", aspect="auto")
        for i, row in enumerate(mat):
            for j, v in enumerate(row):
                if v:
                    ax.text(j, i, str(v), ha="center", va="center", fontsize=8)
        ax.set_xticks(range(len(found)), found, rotation=60, ha="right", fontsize=8)
        ax.set_yticks(range(len(truths)), truths, fontsize=8)
        ax.set_title(f"draw {draw}: hidden effect × first finding")
        fig.tight_layout()
        paths.append(save(fig, out.with_name(f"{out.stem}_confusion_{draw.replace(' ', '_')}.png")))
    return paths


def header_of(by: dict[str, list[dict]]) -> dict[str, str]:
    """What made the diagnoses, per label: commits, configs, settings, machine, workers,
    nice, jax, timeouts and load (tallied over the cases' run.json)."""
    out: dict[str, str] = {}
    labels = list(dict.fromkeys(r["label"] for rows in by.values() for r in rows))
    n_cases: dict[str, int] = {}
    for rows in by.values():
        for r in rows:
            n_cases[r["draw"]] = n_cases.get(r["draw"], 0) + (r["label"] == labels[0])
    out["cases"] = ", ".join(f"draw {d}: {n} (seed {gen.DRAWS[d]})" for d, n in n_cases.items())
    for label in labels:
        runs = [r["run"] for rows in by.values() for r in rows if r["label"] == label and r["run"]]

        def tallied(key: Callable[[dict], Any], runs: list[dict] = runs) -> str:
            n = Counter(key(r) for r in runs).most_common()
            return ", ".join(f"{k}: {c}" for k, c in n) or "–"

        loads = sorted(r["load_average_at_start"][0] for r in runs)
        pre = f"[{label}] " if label else ""
        out |= {
            f"{pre}diagnosed": f"{len(runs)} of {sum(n_cases.values())}",
            f"{pre}git commit (modified files)": tallied(
                lambda r: f"{r['git']['commit']} ({len(r['git']['modified'])} modified)"
            ),
            f"{pre}configs (sha256)": tallied(
                lambda r: f"{r['config']} ({r['config_sha256'][:12]})"
            ),
            f"{pre}diagnose settings": tallied(
                lambda r: ", ".join(f"{k}={v}" for k, v in sorted(r["diagnose_settings"].items()))
            ),
            f"{pre}machine, jax, python, workers, nice, timeout, time limit": tallied(
                lambda r: (
                    f"{r.get('machine', 'machine not recorded')}, jax {r['jax']}, "
                    f"Python {r['python']}, {r['workers']} workers, nice {r.get('nice', '?')}, "
                    f"{r['timeout_s']:g} s, limit {r.get('diagnose_time_limit_s', '?')} s"
                )
            ),
            f"{pre}load average (1 min) when cases started": (
                "–" if not runs else f"median {loads[len(loads) // 2]:.1f}, max {loads[-1]:.1f}"
            ),
            f"{pre}finished": (
                "–"
                if not runs
                else " to ".join(
                    (min(r["finished_at"] for r in runs), max(r["finished_at"] for r in runs))
                )
            ),
        }
    return out


def reach_table(by: dict[str, list[dict]]) -> list[str]:
    """Whether the generator put each effect case at its level, per family × effect, with
    its length and σ_x (planned → used where lowered) and c/level, one column per draw."""
    first = {}
    for rows in by.values():
        for r in rows:
            if r["kind"] != "null":
                first.setdefault(r["draw"], {}).setdefault((r["family"], r["effect"]), r)
    draws = list(first)
    lines = [
        "## Reach: each effect case at its level?",
        "",
        "Per case: length, σ_x [µm] (planned → used where no record at the planned noise "
        "shows the effect at its level), c / level; ✗: short of the level (left out of "
        "the rates).",
        "",
        "| family | effect | " + " | ".join(f"draw {d}" for d in draws) + " |",
        "|" + "---|" * (2 + len(draws)),
    ]

    def cell(r: dict | None) -> str:
        if r is None:
            return "–"
        sig = f"{r['sigma'] * 1e6:g}"
        if r["sigma_planned"] != r["sigma"]:
            sig = f"{r['sigma_planned'] * 1e6:g} → {sig}"
        mark = "" if r["on_level"] else " ✗"
        return f"{r['duration']:g} s, {sig} µm, {r['c']:.2f}/{r['level']:g}{mark}"

    keys = sorted({k for d in draws for k in first[d]})
    for fam, eff in keys:
        cells = [cell(first[d].get((fam, eff))) for d in draws]
        lines.append(f"| {fam} | {eff} | " + " | ".join(cells) + " |")
    lines += ["", "| family | length [s] | " + " | ".join(f"at level, draw {d}" for d in draws)
              + " | " + " | ".join(f"σ_x lowered, draw {d}" for d in draws) + " |"]  # fmt: skip
    lines.append("|" + "---|" * (2 + 2 * len(draws)))
    for fam in gen.FAMILIES:
        for T in gen.LENGTHS:
            sel = {d: [r for r in first[d].values() if r["family"] == fam and r["duration"] == T]
                   for d in draws}  # fmt: skip
            if not any(sel.values()):
                continue
            on = [f"{sum(r['on_level'] for r in sel[d])}/{len(sel[d])}" for d in draws]
            low = [f"{sum(r['sigma_planned'] != r['sigma'] for r in sel[d])}" for d in draws]
            lines.append(f"| {fam} | {T:g} | " + " | ".join(on + low) + " |")
    return [*lines, ""]


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--stage", choices=("all", "generate", "diagnose", "report"), default="all")
    ap.add_argument("--data", default=str(DEFAULT_DATA), help="cases (generate.py writes)")
    ap.add_argument("--results", default="", help="diagnoses (default DATA/results)")
    ap.add_argument(
        "--label",
        default="baseline",
        help="the diagnosis version: its runs go to RESULTS/LABEL; the report takes a "
        "comma list (e.g. baseline,redesign) and shows them side by side",
    )
    ap.add_argument("--report", default=str(DEFAULT_REPORT), help="Markdown (PNGs beside)")
    ap.add_argument("--draws", default="A,B")
    ap.add_argument("--workers", type=int, default=2, help="cases at a time")
    ap.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT, help="s per case")
    ap.add_argument(
        "--resume",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="keep finished cases (default); --no-resume runs every case again",
    )
    ap.add_argument(
        "--time-limit",
        type=float,
        default=0.0,
        help="diagnose --time-limit per case (default: --timeout less 30 s)",
    )
    ap.add_argument("--limit", type=int, default=0, help="only the first N cases of each draw")
    ap.add_argument(
        "--start-until",
        type=float,
        default=0.0,
        help="start no case (generation or diagnosis) after this many s of the stage",
    )
    ap.add_argument(
        "--order",
        choices=("long", "short"),
        default="long",
        help="diagnose the longest records first (many workers) or the shortest first, the "
        "draws taking turns (one worker against a deadline)",
    )
    args = ap.parse_args(argv)
    draws = [d.strip() for d in args.draws.split(",") if d.strip()]
    unknown = [d for d in draws if d not in gen.DRAWS]
    if unknown or args.workers < 1 or args.timeout <= 0:
        what = f"--draws: unknown draw {unknown[0]!r}" if unknown else "--workers/--timeout: > 0"
        print(f"error: {what}", file=sys.stderr)
        return 2
    data = Path(args.data)
    results = Path(args.results) if args.results else data / "results"
    labels = [lb.strip() for lb in args.label.split(",") if lb.strip()]
    if not labels or (args.stage in ("all", "diagnose") and len(labels) != 1):
        print("error: --label: one label to diagnose, one or more to report", file=sys.stderr)
        return 2
    for d in draws:
        print(f"draw {d} (seed {gen.DRAWS[d]}): " + gen.plan_table(gen.plan(gen.DRAWS[d])))
    if args.stage in ("all", "generate"):
        gen.generate(data, draws, args.workers, args.limit, args.start_until)
    if args.stage in ("all", "diagnose"):
        diagnose_all(
            data, results / labels[0], draws, args.workers, args.timeout, args.resume, args.limit,
            args.start_until, time_limit=args.time_limit, order=args.order,
        )  # fmt: skip
    if args.stage in ("all", "report"):
        from fricjax.bench.machine import describe

        by = load_rows(data, results, draws, labels)
        out = Path(args.report)
        out.parent.mkdir(parents=True, exist_ok=True)
        report(by, out, header_of(by), describe().markdown())
        print(f"report: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
