"""How long ``fricjax diagnose`` takes, and where the time goes, cold and warm.

Run from the repository root (CPU-heavy: give it the machine, or ``nice`` it)::

    python benchmarks/diagnose_speed.py                      # every case, cold and warm
    python benchmarks/diagnose_speed.py --cases twin_0.272,twin_1s --minutes 15
    python benchmarks/diagnose_speed.py --cases twin_4s --no-warm

Each run is a new process (``python benchmarks/diagnose_speed.py --child ...``) that
diagnoses one recording through :func:`fricjax.api.diagnose_recording`, as the CLI does:

- **cold**: jax's persistent compilation cache pointed at a new, empty folder
  (:func:`fricjax.api.enable_compilation_cache`), so every program is compiled;
- **warm**: a new process on the cache the cold run filled (a user's second diagnosis of a
  record of the same length and config).

Cases: the seed model on fricjax's twin (``data/paper_twin.h5``, 0.272 s; and 1 s and 4 s
twins, ``paper_twin(seed=11)``, null records), and a measured-input axis (EMPS, drive input
``u``, ``configs/emps.toml``: its first 4 s and the whole 24.8 s estimation file, imported
as ``fricjax import-mat`` does; skipped with a message when ``../shared/data/real/emps/`` is
absent). The diagnoses run without a time limit unless ``--time-limit`` is given, so their
findings are the diagnosis' own; each run's findings are listed so a later speed change can
show they are unchanged. Time per stage comes from diagnosis.json's ``timing`` section
(:mod:`fricjax.diagnose.stages`); cold minus warm is mostly compilation. ``--minutes``:
no run starts after that much time has passed (the report says which were left out).

Writes ``benchmarks/results/diagnose_speed.md`` (atomically, after every run).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
EMPS = ROOT.parent / "shared" / "data" / "real" / "emps"
OUT = ROOT / "benchmarks" / "results" / "diagnose_speed.md"

# case: (what it is, config, record length [s])
CASES: dict[str, tuple[str, str, float]] = {
    "twin_0.272": ("seed model, bundled twin data/paper_twin.h5", "configs/paper.toml", 0.272),
    "twin_1s": (
        "seed model, twin paper_twin(duration=1, seed=11), null",
        "configs/paper.toml",
        1.0,
    ),
    "twin_4s": (
        "seed model, twin paper_twin(duration=4, seed=11), null",
        "configs/paper.toml",
        4.0,
    ),
    "emps_4s": ("measured-input axis: EMPS estimation file, first 4 s", "configs/emps.toml", 4.0),
    "emps_24.8s": ("measured-input axis: EMPS estimation file, whole", "configs/emps.toml", 24.8),
}


def make_recording(case: str, work: Path, emps: Path = EMPS) -> Path | None:
    """The case's recording as a .h5 file in ``work`` (None: its data are absent)."""
    from fricjax.data.recording import Recording, write_recording

    if case == "twin_0.272":
        return ROOT / "data" / "paper_twin.h5"
    if case.startswith("twin_"):
        from fricjax.data.twin import paper_twin

        rec, truth = paper_twin(duration=CASES[case][2], seed=11)
        return write_recording(rec, work / f"{case}.h5", truth=truth)
    if not (emps / "DATA_EMPS.mat").is_file():
        return None
    from fricjax.data.importers import import_mat

    rec = import_mat(
        emps / "DATA_EMPS.mat",
        mapping={"t": "t", "x": "qm", "u": "vir", "r": "qg"},
        u_unit="V",
        name="DATA_EMPS",
    )
    if case == "emps_4s":
        k = round(4.0 / float(rec.t[1] - rec.t[0]))
        rec = Recording(
            t=rec.t[:k],
            x=rec.x[:k],
            u=None if rec.u is None else rec.u[:k],
            r=None if rec.r is None else rec.r[:k],
            mass=rec.mass,
            name=f"{rec.name}_first_4s",
            u_unit=rec.u_unit,
        )
    return write_recording(rec, work / f"{case}.h5")


def child(args: argparse.Namespace) -> int:
    """One diagnosis in this process; its timing and findings to ``args.result``."""
    started = time.perf_counter()
    from fricjax.api import diagnose_recording, enable_compilation_cache

    enable_compilation_cache(args.cache)
    imported = time.perf_counter() - started
    overrides = {"time_limit": args.time_limit}
    _, paths = diagnose_recording(
        args.recording, ROOT / args.config, out=args.out, overrides=overrides
    )
    doc = json.loads(Path(paths["json"]).read_text())
    result = {
        "process_s": time.perf_counter() - started,
        "import_s": imported,
        "timing": doc["timing"],
        "not_tested": doc["not_tested"],
        "findings": [
            {
                "effect": f["effect"],
                "delta_bic": f["delta_bic"],
                "p_value": f["p_value"],
                "location": f["location"],
            }
            for f in doc["findings"]
        ],
        "sigma_x_m": doc["data"].get("sigma_x_m"),
    }
    Path(args.result).write_text(json.dumps(result, indent=1) + "\n")
    return 0


def run_one(
    case: str, mode: str, recording: Path, cache: Path, work: Path, timeout: float, limit: float
) -> dict[str, Any]:
    result = work / f"{case}_{mode}.json"
    cmd = [
        sys.executable,
        str(Path(__file__).resolve()),
        "--child",
        "--recording",
        str(recording),
        "--config",
        CASES[case][1],
        "--cache",
        str(cache),
        "--out",
        str(work / f"{case}_{mode}"),
        "--result",
        str(result),
        "--time-limit",
        str(limit),
    ]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(
            cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout
        )
    except subprocess.TimeoutExpired:
        return {"error": f"killed after {timeout:.0f} s (the benchmark's own time ran out)"}
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        tail = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
        return {"error": f"exit {proc.returncode}: {tail}"}
    out = json.loads(result.read_text())
    out["wall_s"] = wall
    return out


def _findings(r: dict[str, Any]) -> str:
    if "error" in r:
        return r["error"]
    named = [
        f"{f['effect']} (ΔBIC {f['delta_bic']:.1f}, p {f['p_value']:.2g})" for f in r["findings"]
    ]
    text = "; ".join(named) or "none"
    if r["not_tested"]:
        text += f"; not tested (time limit): {', '.join(r['not_tested'])}"
    return text


def report(
    runs: dict[tuple[str, str], dict[str, Any]],
    left_out: list[str],
    machine: str,
    started: float,
    argv: list[str],
) -> str:
    from fricjax.diagnose.stages import STAGES

    done = [(k, r) for k, r in runs.items() if "error" not in r]
    lines = [
        "# Diagnosis speed: cold and warm, where the time goes",
        "",
        f"Command: `{' '.join(argv)}` "
        f"({(time.perf_counter() - started) / 60:.1f} min in all). Each run is a new process; "
        "cold: empty compilation cache, warm: the cache the cold run filled. Times are wall "
        "seconds; the stages are those of diagnosis.json's `timing` section.",
        "",
        "## Machine",
        "",
        machine,
        "",
        "## Cases",
        "",
        *(f"- `{c}`: {what} (`{cfg}`)" for c, (what, cfg, _) in CASES.items()),
        "",
    ]
    if done:
        head = "| stage | " + " | ".join(f"{c} {m}" for (c, m), _ in done) + " |"
        lines += ["## Where the time goes [s]", "", head, "|---" * (len(done) + 1) + "|"]
        for stage in STAGES:
            cells = [f"{r['timing']['stages_s'].get(stage, 0.0):.1f}" for _, r in done]
            lines.append(f"| {stage} | " + " | ".join(cells) + " |")
        rows = {
            "diagnosis (sum of stages and glue)": lambda r: r["timing"]["total_s"],
            "import, read, config, compile cache setup": lambda r: (
                r["process_s"] - r["timing"]["total_s"]
            ),
            "**process wall**": lambda r: r["wall_s"],
        }
        for label, value in rows.items():
            lines.append(f"| {label} | " + " | ".join(f"{value(r):.1f}" for _, r in done) + " |")
        lines.append("")
        pairs = [
            (c, runs[(c, "cold")], runs[(c, "warm")])
            for c in CASES
            if "error" not in runs.get((c, "cold"), {"error": 1})
            and "error" not in runs.get((c, "warm"), {"error": 1})
        ]
        if pairs:
            lines += [
                "Cold over warm (process wall): "
                + "; ".join(f"{c} {a['wall_s'] / b['wall_s']:.2f}x" for c, a, b in pairs)
                + ". Findings of cold and warm runs of a case are "
                + (
                    "identical."
                    if all(a["findings"] == b["findings"] for _, a, b in pairs)
                    else "NOT identical (see below)."
                ),
                "",
            ]
    lines += ["## Findings of each run", ""]
    lines += [f"- {c} {m}: {_findings(r)}" for (c, m), r in runs.items()]
    if left_out:
        lines += ["", "## Left out", "", *(f"- {x}" for x in left_out)]
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=",".join(CASES), help="comma-separated case names")
    ap.add_argument("--no-warm", action="store_true", help="cold runs only")
    ap.add_argument("--minutes", type=float, default=math.inf, help="start no run after this")
    ap.add_argument("--time-limit", type=float, default=math.inf, help="[diagnose] time_limit")
    ap.add_argument("--report", type=Path, default=OUT)
    ap.add_argument("--emps", type=Path, default=EMPS, help="folder of DATA_EMPS.mat")
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--recording", help=argparse.SUPPRESS)
    ap.add_argument("--config", help=argparse.SUPPRESS)
    ap.add_argument("--cache", help=argparse.SUPPRESS)
    ap.add_argument("--out", help=argparse.SUPPRESS)
    ap.add_argument("--result", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        return child(args)

    from fricjax.bench.machine import describe
    from fricjax.io.atomic import write_text_atomic

    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    unknown = [c for c in cases if c not in CASES]
    if unknown:
        print(
            f"error: unknown case: {', '.join(unknown)} (known: {', '.join(CASES)})",
            file=sys.stderr,
        )
        return 2
    started = time.perf_counter()
    deadline = started + 60 * args.minutes
    machine = describe().markdown()
    runs: dict[tuple[str, str], dict[str, Any]] = {}
    left_out = [f"{c}: not asked for (--cases)" for c in CASES if c not in cases]
    argv = ["python", "benchmarks/diagnose_speed.py", *sys.argv[1:]]
    with tempfile.TemporaryDirectory(prefix="diagnose_speed_") as tmp:
        work = Path(tmp)
        for case in cases:
            recording = make_recording(case, work, args.emps)
            if recording is None:
                msg = f"{case}: skipped, EMPS data absent (expected in {args.emps}; see its README)"
                print(msg, file=sys.stderr)
                left_out.append(msg)
                continue
            cache = work / f"cache_{case}"  # new and empty: the cold run fills it
            for mode in ("cold", "warm"):
                if mode == "warm" and args.no_warm:
                    left_out.append(f"{case} warm: not asked for (--no-warm)")
                    continue
                left = deadline - time.perf_counter()
                if left <= 0:
                    left_out.append(f"{case} {mode}: not run, --minutes {args.minutes:g} spent")
                    continue
                print(f"{case} {mode} ...", file=sys.stderr, flush=True)
                runs[(case, mode)] = run_one(
                    case, mode, recording, cache, work, min(left + 60.0, 3600.0), args.time_limit
                )
                r = runs[(case, mode)]
                print(f"  {r.get('wall_s', math.nan):.1f} s: {_findings(r)}", file=sys.stderr)
                write_text_atomic(args.report, report(runs, left_out, machine, started, argv))
    write_text_atomic(args.report, report(runs, left_out, machine, started, argv))
    print(f"report: {args.report}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
