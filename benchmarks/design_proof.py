"""Does a designed test resolve what a record cannot? (issue "Design the next test").

On the concealed benchmark's force-driven cases (a force profile ``/u`` commands the body)
whose diagnosis ends with an ambiguity set, for each case:

1. diagnose the case (``fricjax.api.diagnose_recording``, this checkout);
2. design the next test on its first ambiguity set (``fricjax.api.design_test``, defaults);
3. run that test on the benchmark's *own* plant (``concealed/plant.py``: scipy, no fricjax
   code) with the case's hidden effect, and add the case's noise (a new seed);
4. the same with the standard test of equal duration and peak force: the chirp ``design``
   prints beside its own profile (the issue's standard);
5. diagnose each pair of records as one record (``fricjax.api.diagnose_recording`` with the
   two recordings: ``fricjax diagnose REC NEXT --joined``, the output-error judge with
   every parameter shared) and record whether the hidden effect is then named first, and
   named alone (no alternative).

The test starts at rest at the record's first position, as the design plans it.

Reads the truth only to build the plant and to score. Usage::

    PYTHONPATH=. python benchmarks/design_proof.py --data out/concealed --out out/design_proof \\
        --limit 4 --report benchmarks/results/design_proof.md
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent / "concealed"))

import generate as gen
import plant as pl

from fricjax import api
from fricjax.data.recording import Recording, write_recording

ROOT = Path(__file__).resolve().parents[1]
#: The second test of each pair: the design, the chirp of equal duration and peak force (the
#: issue's standard), and that chirp scaled down until it keeps the travel and speed limits.
ARMS = ("designed", "chirp")


def run_plant(
    truth: dict[str, Any], t: np.ndarray, u: np.ndarray, x0: float, seed: int
) -> np.ndarray:
    """The case's plant (hidden effect included) under the force profile ``u`` [N] at ``t``
    [s], from rest at ``x0`` [m] (where the design starts the test: the record's first
    position), with the case's position noise (a new draw); x [m]."""
    drive = pl.Drive("input", profile=lambda s: np.interp(s, t, u))
    effect = pl.Effect(truth["effect"], truth.get("params", {}))
    x, _, _ = pl.Plant(truth["base"], drive, truth["mass_given_kg"], effect).simulate(t, x0)
    rng = np.random.default_rng(seed)
    return x + rng.normal(0.0, truth["sigma"], t.size)


def first_finding(diag: dict[str, Any]) -> tuple[str, list[str]]:
    """The first named finding and its alternatives, in either diagnosis.json (one layout
    for one recording and several; a run-to-run drift is named ``drift of P``)."""
    for f in diag.get("findings", []):
        if f["effect"] != "unexplained":
            return f.get("name") or f["effect"], [
                a.get("name") or a["effect"] for a in f.get("alternatives", [])
            ]
    return "", []


def one_case(path: Path, out: Path, time_limit: float) -> dict[str, Any] | None:
    truth = gen.read_truth(path)
    if truth["drive"]["kind"] != "input" or truth["kind"] != "catalogue":
        return None
    config = ROOT / truth["config"]
    folder = out / path.stem
    folder.mkdir(parents=True, exist_ok=True)
    limit = {"time_limit": time_limit}
    t0 = time.perf_counter()
    diag_dir = folder / "diagnosis"
    if not (diag_dir / "diagnosis.json").is_file():
        api.diagnose_recording(path, config, out=diag_dir, overrides=limit)
    diag = json.loads((diag_dir / "diagnosis.json").read_text(encoding="utf-8"))
    named, alternatives = first_finding(diag)
    row: dict[str, Any] = {
        "case": path.stem,
        "duration_s": truth["duration"],
        "truth": truth["effect"],
        "named": named,
        "alternatives": alternatives,
        "diagnose_s": time.perf_counter() - t0,
    }
    if not alternatives:
        row["skipped"] = "no ambiguity set"
        return row
    timing = folder / "design_s.json"
    if timing.is_file() and all((folder / f"{label}.h5").is_file() for label in ARMS):
        # the tests were designed and run on the plant before: judge the pairs again only
        # (a change of the pair's judge); the design's own numbers are read back
        earlier = json.loads((folder / "next.json").read_text(encoding="utf-8"))
        row["design_s"] = json.loads(timing.read_text(encoding="utf-8"))["design_s"]
        row["design_separation"] = earlier["separation"]
        row["chirp_separation"] = earlier["standard_tests"]["chirp"]["separation"]
        row["chirp_violation"] = earlier["standard_tests"]["chirp"]["limit_violation"]
        recorded = {label: folder / f"{label}.h5" for label in ARMS}
        for label in ARMS:
            row[label] = _judge_pair(
                path, recorded[label], folder / f"pair_{label}", config, limit, truth
            )
        return row
    t1 = time.perf_counter()
    result, _ = api.design_test(path, config, diag_dir, out=folder / "next.csv")
    row["design_s"] = time.perf_counter() - t1
    timing.write_text(json.dumps({"design_s": row["design_s"]}), encoding="utf-8")
    row["design_separation"] = result.separation
    row["chirp_separation"] = result.standard["chirp"]["separation"]
    row["chirp_violation"] = result.standard["chirp"]["limit_violation"]
    arms = {
        "designed": result.u,
        "chirp": result.standard_u["chirp"],
    }
    for label, u in arms.items():
        try:
            x = run_plant(truth, result.t, u, result.plan.x0, seed=7)
        except RuntimeError as e:  # the plant chatters under this input
            row[label] = {
                "named": "",
                "alternatives": [],
                "truth_first": False,
                "truth_alone": False,
                "plant_error": str(e),
            }
            continue
        rec = Recording(t=result.t, x=x, u=u, mass=truth["mass_given_kg"], name=label, u_unit="N")
        second = write_recording(rec, folder / f"{label}.h5")
        row[label] = _judge_pair(path, second, folder / f"pair_{label}", config, limit, truth)
    return row


def _judge_pair(
    path: Path, second: Path, pair_dir: Path, config: Path, limit: dict, truth: dict[str, Any]
) -> dict[str, Any]:
    """The record and the new test diagnosed as one record (``--joined``), and the score."""
    t2 = time.perf_counter()
    if not (pair_dir / "diagnosis.json").is_file():
        api.diagnose_recording([path, second], config, out=pair_dir, overrides=limit)
    pair = json.loads((pair_dir / "diagnosis.json").read_text(encoding="utf-8"))
    first, alts = first_finding(pair)
    return {
        "named": first,
        "alternatives": alts,
        "truth_first": first == truth["effect"],
        "truth_alone": first == truth["effect"] and not alts,
        "pair_diagnose_s": time.perf_counter() - t2,
    }


def rescore(row: dict[str, Any], out: Path, data: Path) -> None:
    """``row``'s record length, pair outcomes and the chirp's excess read again from its
    case file and its folder."""
    for case in data.glob(f"draw*/{row['case']}.h5"):
        row["duration_s"] = gen.read_truth(case)["duration"]
    folder = out / row["case"]
    if (folder / "next.json").is_file():
        chirp = json.loads((folder / "next.json").read_text(encoding="utf-8"))
        row["chirp_violation"] = chirp["standard_tests"]["chirp"]["limit_violation"]
    for label in ARMS:
        pair = folder / f"pair_{label}" / "diagnosis.json"
        if pair.is_file():
            row.setdefault(label, {})
            first, alts = first_finding(json.loads(pair.read_text(encoding="utf-8")))
            row[label].update(
                named=first,
                alternatives=alts,
                truth_first=first == row["truth"],
                truth_alone=first == row["truth"] and not alts,
            )


def report(rows: list[dict[str, Any]], machine: str) -> str:
    tried = [r for r in rows if "designed" in r]
    lines = [
        "# Designed next test on the concealed benchmark",
        "",
        f"Machine: {machine}. Command: `PYTHONPATH=. python benchmarks/design_proof.py` "
        "(module docstring). Force-driven catalogue cases whose diagnosis ends with an "
        "ambiguity set; the pair (record + new test run on the benchmark's own plant) "
        "diagnosed as one record (`fricjax diagnose REC NEXT --joined`).",
        "",
        "D is the design's least separation of any pair (expected LR, `fricjax.design`); the "
        "chirp has the same duration and peak force but is not held to the record's travel "
        "and speed: its excess is given.",
        "",
        "| case | record s | truth | named (alternatives) | design D / chirp D (chirp's "
        "excess) | pair, designed | pair, chirp | design s |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]

    def cell(p: dict[str, Any] | None) -> str:
        if p is None:
            return "not run"
        alts = f" ({', '.join(p['alternatives'])})" if p["alternatives"] else ""
        return f"{p['named'] or '—'}{alts}"

    for r in rows:
        if "designed" not in r:
            lines.append(
                f"| {r['case']} | {r.get('duration_s', '')} | {r['truth']} | "
                f"{r['named'] or '—'} | {r.get('skipped', '')} | | | |"
            )
            continue
        lines.append(
            f"| {r['case']} | {r.get('duration_s', '')} | {r['truth']} | {r['named']} "
            f"({', '.join(r['alternatives'])}) | "
            f"{r['design_separation']:.3g} / {r['chirp_separation']:.3g} "
            f"({100 * r.get('chirp_violation', float('nan')):.0f} %) | "
            + " | ".join(cell(r.get(label)) for label in ARMS)
            + f" | {r['design_s']:.0f} |"
        )
    for label in ARMS:
        done = [r for r in tried if label in r]
        first = sum(r[label]["truth_first"] for r in done)
        alone = sum(r[label]["truth_alone"] for r in done)
        lines.append(
            f"\n{label}: truth named first {first}/{len(done)}, named alone {alone}/{len(done)}"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=ROOT / "out" / "concealed")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "design_proof")
    ap.add_argument("--draws", default="A,B")
    ap.add_argument("--limit", type=int, default=4, help="cases with an ambiguity set to try")
    ap.add_argument("--time-limit", type=float, default=300.0)
    ap.add_argument("--report", type=Path, default=None)
    ap.add_argument(
        "--prior",
        type=Path,
        default=None,
        help="results of an earlier score.py run (RESULTS/draw<X>/CASE/diagnosis.json): "
        "try only the cases whose diagnosis there ended with an ambiguity set",
    )
    ap.add_argument(
        "--rows",
        type=Path,
        default=None,
        help="only write the report, from the JSON rows an earlier run printed (one a line)",
    )
    args = ap.parse_args()
    machine = f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f} at the end"
    if args.rows is not None:
        rows = [json.loads(line) for line in args.rows.read_text().splitlines() if line[:1] == "{"]
        for r in rows:  # rescored from the files, so a change of the scoring applies
            rescore(r, args.out, args.data)
        text = report(rows, machine)
        print(text)
        if args.report is not None:
            args.report.write_text(text, encoding="utf-8")
        return
    api.enable_compilation_cache()
    rows: list[dict[str, Any]] = []
    paths = sorted(p for d in args.draws.split(",") for p in (args.data / f"draw{d}").glob("*.h5"))
    if args.prior is not None:

        def ambiguous(path: Path) -> bool:
            earlier = args.prior / path.parent.name / path.stem / "diagnosis.json"
            return earlier.is_file() and bool(
                first_finding(json.loads(earlier.read_text(encoding="utf-8")))[1]
            )

        paths = [p for p in paths if ambiguous(p)]
    for path in paths:
        if sum("designed" in r for r in rows) >= args.limit:
            break
        row = one_case(path, args.out, args.time_limit)
        # each case compiles programs of its own shapes; kept, they exhaust the memory
        # within a few cases ("LLVM compilation error: Cannot allocate memory")
        jax.clear_caches()
        if row is not None:
            rows.append(row)
            print(json.dumps(row), flush=True)
    text = report(rows, machine)
    print(text)
    if args.report is not None:
        args.report.write_text(text, encoding="utf-8")


if __name__ == "__main__":
    main()
