"""Output-error fits of eight model structures: one call per structure against one batch.

Run from the repository root (CPU-heavy: ``nice`` it on a shared machine)::

    python benchmarks/output_error_speed.py                 # every case
    python benchmarks/output_error_speed.py --cases twin_0.272
    python benchmarks/output_error_speed.py --cases tangents

What the diagnosis asks of output error: the base model and base + each of several
catalogue terms, fitted by multiple shooting (segments of 0.05 s, as its simulation test
uses) from the same start, their costs compared. Eight fits per record, two ways:

- **loop**: :func:`fricjax.output_error.fit_output_error` once per structure (the base and
  base + one of seven terms), each a different model, so each compiles its own program;
- **batch**: one :func:`fricjax.output_error.fit_output_error_batch` call on the superset
  model (base + all seven terms), row 0 with every term pinned at its start (amplitudes at
  their null 0, shapes mid-grid), row k with term k free: one program, the same eight fits
  (the largest relative cost difference between the two ways is reported).

Case ``tangents``: the Jacobian's tangents. The diagnosis' base fit on the bundled twin is a
fit of the superset model (``Superset.build(problem).model(())``, as
:mod:`fricjax.diagnose.judge` builds it: P = 48 parameters, 26 of them the base's) with
every term pinned. Three ways of that fit, B = 1:

- **all P**: the base's 26 parameters fitted (the terms masked), ``n_directions = P``: a
  tangent for each of the 48 parameters (22 of them zero rows), as many as the residual's
  default directions (the identity) propagate;
- **free only**: the same fit with the default K = 26 tangents: the same fit, to rounding;
- **judge today**: :func:`~fricjax.output_error.fit_output_error` on the superset base as
  ``judge.fit_base`` calls it (the terms pinned by a collapsed box, so free in the spec:
  K = 46), for comparison.

For each: the fit cold, its LM steps, the fit warm and the warm time per LM step, and the
Jacobian alone (:func:`~fricjax.output_error.jacobian_at` at the start, mean of 20 calls);
the warm figures are the best of ``--rounds`` (3) rounds that interleave the three ways.
Case ``tangents_1s``: the same on the 1 s twin.

Each is timed cold (the first call in this process: tracing and XLA compilation included;
no persistent compilation cache) and warm (the same call again). Wall and process CPU
seconds are both given: on a shared machine the wall time moves with the others' load,
the CPU time much less; compare ratios taken in the same run. Cases: the bundled twin
(``data/paper_twin.h5``, 0.272 s) and a 1 s twin (``paper_twin(duration=1, seed=11)``),
both on ``configs/paper.toml``, starting from the truth with every parameter moved ±5 %.

Writes ``benchmarks/results/output_error_speed.md`` (atomically; ``--report`` for another
path).
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
#: the tangents' comparison (module docstring), by case: the record it runs on
TANGENTS = {"tangents": "twin_0.272", "tangents_1s": "twin_1s"}
JACOBIAN_CALLS = 20
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


def run_tangents(case: str, timer: Timer, rounds: int) -> dict[str, Any]:
    """The twin's superset base fitted three ways (module docstring, case ``tangents``)."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from fricjax.diagnose.judge import Superset
    from fricjax.output_error import (
        OutputErrorSettings,
        fit_output_error,
        fit_output_error_batch,
        jacobian_at,
        output_error_residual,
    )

    record = problems(TANGENTS[case])[0]
    problem = Superset.build(record).model(())
    spec = problem.spec
    settings = OutputErrorSettings(segment_s=SEGMENT_S)
    start = {**spec.as_dict(), **start_of(record)}
    x0 = spec.flatten({k: v for k, v in start.items() if k in spec})[None]
    free = np.array([[q in record.spec.free_names for q in spec.free_names]])
    P, K = len(spec.names), int(free.sum())
    ways: dict[str, tuple[int, Callable[[], Any]]] = {
        "all P": (P, lambda: fit_output_error_batch(problem, x0, free, settings, None, P)[0]),
        "free only": (K, lambda: fit_output_error_batch(problem, x0, free, settings)[0]),
        "judge today": (spec.n_free, lambda: fit_output_error(problem, start, settings)),
    }
    setup = output_error_residual(problem, start, settings)
    theta = jnp.asarray(setup.x0)
    keep = {"all P": free[0], "free only": free[0], "judge today": np.ones(spec.n_free, bool)}
    out: dict[str, Any] = {"n": problem.n, "P": P, "segments": setup.seg.S, "ways": {}}
    out["rounds"] = rounds
    jacobians: dict[str, Callable[[], None]] = {}
    for way, (k, fit) in ways.items():
        print(f"  {way} (K = {k}), cold ...", file=sys.stderr, flush=True)
        r: dict[str, Any] = {"K": k}
        result, r["cold"] = timer.time(fit)
        r["steps"], r["cost"] = result.n_steps, result.cost
        # the Jacobian alone, along the way's directions (the spec's free parameters first)
        idx = np.flatnonzero(setup.free[:P])[np.flatnonzero(keep[way])]
        dirs = np.zeros((k, P))
        dirs[np.arange(idx.size), idx] = 1.0
        res = eqx.tree_at(lambda m: m.directions, setup.residual, jnp.asarray(dirs))
        jax.block_until_ready(jacobian_at(res, theta))

        def calls(res: Any = res) -> None:
            for _ in range(JACOBIAN_CALLS):
                jax.block_until_ready(jacobian_at(res, theta))

        jacobians[way] = calls
        out["ways"][way] = r
    # warm: the ways interleaved, best of the rounds, so that a burst of the others' load on the
    # shared cores does not land on one way only
    for i in range(rounds):
        print(f"  warm round {i + 1} of {rounds} ...", file=sys.stderr, flush=True)
        for way, (_, fit) in ways.items():
            r = out["ways"][way]
            for key, run in (("warm", fit), ("jacobian", jacobians[way])):
                _, t = timer.time(run)
                best = r.setdefault(key, t)
                r[key] = {m: min(best[m], t[m]) for m in ("wall", "cpu")}
    return out


def tangents_report(case: str, r: dict[str, Any]) -> list[str]:
    ways = r["ways"]
    lines = [
        f"## Tangents: every parameter against the fitted ones ({TANGENTS[case]}'s superset base)",
        "",
        f"n = {r['n']}, {r['segments']} segments of {SEGMENT_S} s, P = {r['P']} parameters. "
        "Seconds, wall / process CPU; warm: best of "
        f"{r['rounds']} interleaved rounds; per LM step = the warm fit's time over its steps; "
        f"Jacobian = one `jacobian_at` call, warm, mean of {JACOBIAN_CALLS}.",
        "",
        "| way | K | cold fit | warm fit | LM steps | per LM step | Jacobian | cost [σ_x²] |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for way, w in ways.items():
        c, h, j, n = w["cold"], w["warm"], w["jacobian"], max(w["steps"], 1)
        lines.append(
            f"| {way} | {w['K']} | {c['wall']:.1f} / {c['cpu']:.1f} | "
            f"{h['wall']:.2f} / {h['cpu']:.2f} | {w['steps']} | "
            f"{1e3 * h['wall'] / n:.1f} / {1e3 * h['cpu'] / n:.1f} ms | "
            f"{1e3 * j['wall'] / JACOBIAN_CALLS:.1f} / {1e3 * j['cpu'] / JACOBIAN_CALLS:.1f} ms | "
            f"{w['cost']:.6f} |"
        )
    a, f = ways["all P"], ways["free only"]

    def ratio(key: str, per: int = 1, per_f: int = 1) -> str:
        wall = a[key]["wall"] / per / (f[key]["wall"] / per_f)
        return f"{wall:.2f}x / {a[key]['cpu'] / per / (f[key]['cpu'] / per_f):.2f}x"

    lines += [
        "",
        "Ratios all P / free only (same run), wall / CPU: per LM step "
        f"{ratio('warm', a['steps'], f['steps'])}; warm fit {ratio('warm')}; cold fit "
        f"{ratio('cold')}; Jacobian {ratio('jacobian')}. Relative cost difference "
        f"{abs(a['cost'] - f['cost']) / a['cost']:.1e}.",
    ]
    return lines


def report(
    results: dict[str, dict[str, Any]],
    tangents: dict[str, dict[str, Any]],
    machine: str,
    end_load: str,
    argv: str,
) -> str:
    lines = [
        "# Output-error fits: a loop of single fits against one batch; the Jacobian's tangents",
        "",
        f"Command: `{argv}`. Cold: the first call in the process (trace and XLA compilation",
        "included, no persistent cache); warm: the same call again. Segments of",
        f"{SEGMENT_S} s (the diagnosis' simulation test), LM at most 100 steps.",
        "",
        "## Machine",
        "",
        machine,
        f"- load average at the end (1/5/15 min): {end_load}",
        "",
    ]
    if results:
        lines += loop_batch_report(results)
    for case, r in tangents.items():
        lines += tangents_report(case, r)
    return "\n".join(lines) + "\n"


def loop_batch_report(results: dict[str, dict[str, Any]]) -> list[str]:
    lines = [
        "## Eight structures: a loop against one batch",
        "",
        f"The base model and base + each of {', '.join(TERMS)}; the batch fits them as rows of",
        "the superset model (every term, pinned at its start where not fitted).",
        "",
        "Times [s] (wall / process CPU; XLA compile: its share of the wall time):",
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
    lines += ["", "Ratios (loop / batch, same run):", ""]
    lines += ["| case | cold wall | cold CPU | warm wall | warm CPU |", "|---|---|---|---|---|"]
    for case, r in results.items():
        lc, bc, lw, bw = r["loop_cold"], r["batch_cold"], r["loop_warm"], r["batch_warm"]
        lines.append(
            f"| {case} | {lc['wall'] / bc['wall']:.2f}x | {lc['cpu'] / bc['cpu']:.2f}x | "
            f"{lw['wall'] / bw['wall']:.2f}x | {lw['cpu'] / bw['cpu']:.2f}x |"
        )
    lines += ["", "The same fits:", ""]
    for case, r in results.items():
        lines.append(
            f"- {case}: {r['segments']} segments, superset {r['superset_d']} free parameters; "
            f"largest relative cost difference loop vs batch {r['cost_rel_diff']:.1e}; "
            f"LM steps {r['steps']}; costs [σ_x²] "
            f"{', '.join(f'{c:.1f}' for c in r['costs'])}"
        )
    return [*lines, ""]


def main() -> int:
    known = [*CASES, *TANGENTS]
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument(
        "--cases", default=",".join(known), help="comma-separated, from: " + ", ".join(known)
    )
    ap.add_argument("--report", type=Path, default=OUT)
    ap.add_argument("--rounds", type=int, default=3, help="warm rounds of the tangents' cases")
    args = ap.parse_args()
    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    unknown = [c for c in cases if c not in known]
    if unknown:
        print(
            f"error: unknown case: {', '.join(unknown)} (known: {', '.join(known)})",
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
    tangents: dict[str, dict[str, Any]] = {}
    argv = " ".join(["python", "benchmarks/output_error_speed.py", *sys.argv[1:]])
    for case in cases:
        print(f"{case} ...", file=sys.stderr, flush=True)
        if case in TANGENTS:
            tangents[case] = run_tangents(case, timer, max(args.rounds, 1))
        else:
            results[case] = run_case(case, timer)
            cold = {way: results[case][f"{way}_cold"]["wall"] for way in ("loop", "batch")}
            print(
                f"  loop cold {cold['loop']:.1f} s, batch cold {cold['batch']:.1f} s",
                file=sys.stderr,
                flush=True,
            )
        load = " / ".join(f"{x:.2f}" for x in os.getloadavg())
        write_text_atomic(args.report, report(results, tangents, machine, load, argv))
    print(f"report: {args.report}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
