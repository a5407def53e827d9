"""Output-error fits of eight model structures: one call per structure against one batch.

Run from the repository root (CPU-heavy: ``nice`` it on a shared machine)::

    python benchmarks/output_error_speed.py                 # both twins
    python benchmarks/output_error_speed.py --cases twin_0.272

What the diagnosis asks of output error: the base model and base + each of several
catalogue terms, fitted by multiple shooting (segments of 0.05 s, as its simulation test
uses) from the same start, their costs compared. Eight fits per record, two ways:

- **loop**: :func:`fricjax.output_error.fit_output_error` once per structure (the base and
  base + one of seven terms), each a different model, so each compiles its own program;
- **batch**: one :func:`fricjax.output_error.fit_output_error_batch` call on the superset
  model (base + all seven terms), row 0 with every term pinned at its start (amplitudes at
  their null 0, shapes mid-grid), row k with term k free: one program, the same eight fits
  (the largest relative cost difference between the two ways is reported).

Each is timed cold (the first call in this process: tracing and XLA compilation included;
no persistent compilation cache) and warm (the same call again). Wall and process CPU
seconds are both given: on a shared machine the wall time moves with the others' load,
the CPU time much less; compare ratios taken in the same run. Cases: the bundled twin
(``data/paper_twin.h5``, 0.272 s) and a 1 s twin (``paper_twin(duration=1, seed=11)``),
both on ``configs/paper.toml``, starting from the truth with every parameter moved ±5 %.

Writes ``benchmarks/results/output_error_speed.md`` (atomically).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results" / "output_error_speed.md"
CASES = {"twin_0.272": 0.272, "twin_1s": 1.0}
#: Seven catalogue terms the simulator can integrate (pointwise forces, no state).
TERMS = (
    "stribeck",
    "asymmetric_friction",
    "quadratic_drag",
    "position_bump",
    "position_periodic",
    "extra_harmonic",
    "friction_drift",
)
SEGMENT_S = 0.05


def problems(case: str) -> tuple[Any, list[Any], Any]:
    """(base problem, the eight single-structure problems, the superset problem)."""
    import fricjax  # noqa: F401  (float64)
    from fricjax.config import load_config
    from fricjax.data.recording import read_recording
    from fricjax.data.twin import paper_twin
    from fricjax.diagnose.catalogue import candidate
    from fricjax.problem import build_problem

    cfg = load_config(ROOT / "configs" / "paper.toml")
    if case == "twin_0.272":
        rec = read_recording(ROOT / "data" / "paper_twin.h5")
    else:
        rec, _ = paper_twin(duration=CASES[case], seed=11)
    base = build_problem(rec, cfg)
    singles = [base, *(candidate(e).extend_problem(base) for e in TERMS)]
    superset = base
    for e in TERMS:
        superset = candidate(e).extend_problem(superset)
    return base, singles, superset


def start_of(base: Any) -> dict[str, float]:
    """The twin's truth with every free parameter moved by ±5 % (fixed signs), in the box."""
    from fricjax.data.twin import PAPER_TRUTH

    spec = base.spec
    truth = spec.flatten({k: v for k, v in PAPER_TRUTH.items() if k in spec})
    signs = np.random.default_rng(1).choice([-1.0, 1.0], truth.size)
    return spec.as_dict(np.clip(truth * (1.0 + 0.05 * signs), spec.lower, spec.upper))


class Timer:
    """Wall and process-CPU seconds of a block, and the XLA compilations inside it."""

    def __init__(self) -> None:
        import jax

        self.compile_s = 0.0
        self.compiles = 0

        def listen(event: str, duration: float, **_: object) -> None:
            if event == "/jax/core/compile/backend_compile_duration":
                self.compile_s += duration
                self.compiles += 1

        jax.monitoring.register_event_duration_secs_listener(listen)

    def time(self, fn: Callable[[], Any]) -> tuple[Any, dict[str, float]]:
        c0, n0 = self.compile_s, self.compiles
        w0, p0 = time.perf_counter(), time.process_time()
        out = fn()
        return out, {
            "wall": time.perf_counter() - w0,
            "cpu": time.process_time() - p0,
            "xla_compile": self.compile_s - c0,
            "compiles": self.compiles - n0,
        }


def run_case(case: str, timer: Timer) -> dict[str, Any]:
    from fricjax.output_error import OutputErrorSettings, fit_output_error, fit_output_error_batch

    base, singles, superset = problems(case)
    settings = OutputErrorSettings(segment_s=SEGMENT_S)
    start = start_of(base)
    spec = superset.spec
    x0 = spec.flatten({k: v for k, v in start.items() if k in spec})
    starts = np.repeat(x0[None], len(singles), axis=0)
    # row 0: the base's parameters; row k: the base's and term k's
    free = np.array([[q in p.spec.names for q in spec.free_names] for p in singles])

    def loop() -> list[Any]:
        return [fit_output_error(p, start, settings) for p in singles]

    def batch() -> list[Any]:
        return fit_output_error_batch(superset, starts, free, settings)

    out: dict[str, Any] = {"n": base.n, "B": len(singles), "superset_d": spec.n_free}
    out["loop_fits"], out["loop_cold"] = timer.time(loop)
    _, out["loop_warm"] = timer.time(loop)
    out["batch_fits"], out["batch_cold"] = timer.time(batch)
    _, out["batch_warm"] = timer.time(batch)
    a, b = out.pop("loop_fits"), out.pop("batch_fits")
    out["cost_rel_diff"] = max(abs(x.cost - y.cost) / x.cost for x, y in zip(a, b, strict=True))
    out["segments"] = a[0].n_segments
    out["steps"] = [f.n_steps for f in b]
    out["costs"] = [f.cost for f in b]
    return out


def report(results: dict[str, dict[str, Any]], machine: str, end_load: str, argv: str) -> str:
    lines = [
        "# Output-error fits of eight structures: a loop of single fits against one batch",
        "",
        f"Command: `{argv}`. Cold: the first call in the process (trace and XLA compilation",
        "included, no persistent cache); warm: the same call again. The eight fits: the base",
        f"model and base + each of {', '.join(TERMS)}; the batch fits them as rows of the",
        "superset model (every term, pinned at its start where not fitted). Segments of",
        f"{SEGMENT_S} s (the diagnosis' simulation test), LM at most 100 steps.",
        "",
        "## Machine",
        "",
        machine,
        f"- load average at the end (1/5/15 min): {end_load}",
        "",
        "## Times [s] (wall / process CPU; XLA compile: its share of the wall time)",
        "",
        "| case | n | way | cold wall | cold CPU | cold XLA compile (programs) | warm wall "
        "| warm CPU |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for case, r in results.items():
        for way in ("loop", "batch"):
            c, w = r[f"{way}_cold"], r[f"{way}_warm"]
            lines.append(
                f"| {case} | {r['n']} | {way} | {c['wall']:.1f} | {c['cpu']:.1f} | "
                f"{c['xla_compile']:.1f} ({c['compiles']}) | {w['wall']:.2f} | {w['cpu']:.2f} |"
            )
    lines += ["", "## Ratios (loop / batch, same run)", ""]
    lines += ["| case | cold wall | cold CPU | warm wall | warm CPU |", "|---|---|---|---|---|"]
    for case, r in results.items():
        lc, bc, lw, bw = r["loop_cold"], r["batch_cold"], r["loop_warm"], r["batch_warm"]
        lines.append(
            f"| {case} | {lc['wall'] / bc['wall']:.2f}x | {lc['cpu'] / bc['cpu']:.2f}x | "
            f"{lw['wall'] / bw['wall']:.2f}x | {lw['cpu'] / bw['cpu']:.2f}x |"
        )
    lines += ["", "## The same fits", ""]
    for case, r in results.items():
        lines.append(
            f"- {case}: {r['segments']} segments, superset {r['superset_d']} free parameters; "
            f"largest relative cost difference loop vs batch {r['cost_rel_diff']:.1e}; "
            f"LM steps {r['steps']}; costs [σ_x²] "
            f"{', '.join(f'{c:.1f}' for c in r['costs'])}"
        )
    return "\n".join(lines) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--cases", default=",".join(CASES), help="comma-separated, from: " + ", ".join(CASES)
    )
    ap.add_argument("--report", type=Path, default=OUT)
    args = ap.parse_args()
    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    unknown = [c for c in cases if c not in CASES]
    if unknown:
        print(
            f"error: unknown case: {', '.join(unknown)} (known: {', '.join(CASES)})",
            file=sys.stderr,
        )
        return 2
    import jax.numpy as jnp

    import fricjax  # noqa: F401
    from fricjax.bench.machine import describe
    from fricjax.io.atomic import write_text_atomic

    machine = describe().markdown()
    float(jnp.ones(3).sum())  # start the backend before the first timed call
    timer = Timer()
    results: dict[str, dict[str, Any]] = {}
    argv = " ".join(["python", "benchmarks/output_error_speed.py", *sys.argv[1:]])
    for case in cases:
        print(f"{case} ...", file=sys.stderr, flush=True)
        results[case] = run_case(case, timer)
        cold = {way: results[case][f"{way}_cold"]["wall"] for way in ("loop", "batch")}
        print(
            f"  loop cold {cold['loop']:.1f} s, batch cold {cold['batch']:.1f} s",
            file=sys.stderr,
            flush=True,
        )
        load = " / ".join(f"{x:.2f}" for x in os.getloadavg())
        write_text_atomic(args.report, report(results, machine, load, argv))
    print(f"report: {args.report}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
