"""Fleet throughput: recordings identified per second by the vmapped fleet
(:mod:`fricjax.fleet`) against a Python loop over single-recording ``identify`` and a loop
of ``scipy.optimize.least_squares``, for 1 s recordings of two models:

* ``axis``: the 3-parameter Coulomb + viscous + mass axis with a measured drive input
  (``configs/axis.toml``, recordings from :func:`fricjax.data.twin.axis_twin`): linear in
  its parameters, so the config solves it exactly (``separable``, no search);
* ``axis_search``: the same with the annealing search of ``[search]`` (``separable``
  off), the path of a model with nonlinear parameters;
* ``paper``: the seed's 26-parameter model (``configs/paper.toml``, recordings from
  :func:`fricjax.data.twin.paper_twin`, 1 s instead of 0.272 s).

Recording i of N has noise seed i (the same recordings at every N). For each N:

* fleet: ``run_fleet`` with shards of ``min(N, --shard-size)``; one untimed call on the
  first shard compiles the program (its time is reported as compile time), then the N
  recordings are timed;
* identify loop: ``identify`` per recording, warm (the first recording's call compiles and
  is not timed); for N above ``--loop-max`` the time is extrapolated linearly from the
  ``--loop-max`` recordings measured (each recording costs the same: one fit);
* least-squares loop: ``scipy.optimize.least_squares`` (trf, the box as bounds, the jitted
  residual and forward-mode Jacobian of the same problem) from the config's initial values,
  one start per recording (no search), extrapolated like the identify loop.

Answers: on the recordings both ran, the fraction whose every parameter is within 0.1 σ
(σ of the single fit) of the single fit. Memory: peak resident set of the process (and of
the accelerator where jax reports it) across the N = max run.

Usage: ``PYTHONPATH=. python benchmarks/fleet.py [--sizes 1,10,100,1000] [--out F.md]``;
prints the report's path.
"""

from __future__ import annotations

import argparse
import dataclasses
import resource
import sys
import time
from pathlib import Path

import jax
import numpy as np
import scipy.optimize

import fricjax  # noqa: F401  (float64)
from fricjax.bench.machine import describe
from fricjax.config import load_config
from fricjax.data.twin import DEFAULT_NOISE_STD, axis_twin, paper_twin
from fricjax.fleet import Member, default_shard_size, run_fleet
from fricjax.identify import IdentifySettings, identify
from fricjax.io.atomic import write_text_atomic
from fricjax.problem import build_problem

ROOT = Path(__file__).resolve().parents[1]
MODELS = {
    "axis": (ROOT / "configs" / "axis.toml", axis_twin),
    "axis_search": (ROOT / "configs" / "axis.toml", axis_twin),
    "paper": (ROOT / "configs" / "paper.toml", paper_twin),
}


#: The twins' default noise on x [m].
NOISE = {"axis": 1e-6, "axis_search": 1e-6, "paper": DEFAULT_NOISE_STD}
#: Settings a model overrides in its config.
OVERRIDES: dict[str, dict] = {"axis_search": {"separable": False}}


def members_of(model: str, n: int) -> tuple[list[Member], IdentifySettings]:
    path, twin = MODELS[model]
    cfg = load_config(path)
    settings = IdentifySettings.from_tables(cfg.tables, source=cfg.source)
    settings = dataclasses.replace(settings, **OVERRIDES.get(model, {}))
    # The twins differ only in their noise: simulate once, then add noise seed i exactly as
    # twin(seed=i) does (numpy PCG64, normal(0, noise_std, n) on x).
    clean, _ = twin(duration=1.0, noise_std=0.0)
    out = []
    for i in range(n):
        noise = np.random.default_rng(i).normal(0.0, NOISE[model], clean.n)
        rec = dataclasses.replace(clean, x=clean.x + noise, name=f"{model}{i}")
        out.append(Member(rec.name, "", f"{i:06d}", build_problem(rec, cfg)))
    return out, settings


@jax.jit
def _value_and_jac(residual, x):
    return residual(x), jax.jacfwd(residual)(x)


def least_squares_fit(problem) -> np.ndarray:
    """scipy's trust-region reflective least squares from the config's initial values."""
    residual, spec = problem.residual_fn, problem.spec
    cache: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}

    def both(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = x.tobytes()
        if key not in cache:
            r, j = _value_and_jac(residual, x)
            cache.clear()
            cache[key] = (np.asarray(r), np.asarray(j))
        return cache[key]

    fit = scipy.optimize.least_squares(
        lambda x: both(x)[0],
        np.asarray(spec.init, np.float64),
        jac=lambda x: both(x)[1],
        bounds=(np.asarray(spec.lower), np.asarray(spec.upper)),
        method="trf",
    )
    return fit.x


def peak_rss_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def device_peak_mib() -> float | None:
    stats = jax.devices()[0].memory_stats() or {}
    peak = stats.get("peak_bytes_in_use")
    return None if peak is None else peak / 2**20


def bench_model(model: str, sizes: list[int], loop_max: int, shard_size: int, log) -> dict:
    n_max = max(sizes)
    members, settings = members_of(model, n_max)
    log(f"{model}: {n_max} recordings of {members[0].problem.n} samples generated")
    n_loop = min(loop_max, n_max)
    # loops, warm: the first call compiles
    identify(members[0].problem, settings)
    t = time.perf_counter()
    singles = [identify(m.problem, settings) for m in members[:n_loop]]
    loop_s = (time.perf_counter() - t) / n_loop
    log(f"{model}: identify loop {1 / loop_s:.3g} rec/s over {n_loop}")
    least_squares_fit(members[0].problem)
    t = time.perf_counter()
    lsq = [least_squares_fit(m.problem) for m in members[:n_loop]]
    lsq_s = (time.perf_counter() - t) / n_loop
    log(f"{model}: least_squares loop {1 / lsq_s:.3g} rec/s over {n_loop}")
    rows = []
    memory = {}
    for n in sizes:
        width = min(n, shard_size)
        t = time.perf_counter()
        run_fleet(members[:width], settings, shard_size=width)
        first = time.perf_counter() - t
        rss0 = peak_rss_mib()
        t = time.perf_counter()
        fits = run_fleet(members[:n], settings, shard_size=width)
        wall = time.perf_counter() - t
        compile_s = max(first - wall * width / n, 0.0)
        if n == n_max:
            memory = {"rss_before": rss0, "rss_peak": peak_rss_mib(), "device": device_peak_mib()}
        k = min(n, n_loop)
        agree = [
            f.ok and bool(np.all(np.abs(f.value - s.value) <= 0.1 * s.std))
            for f, s in zip(fits[:k], singles[:k], strict=True)
        ]
        lsq_agree = [
            bool(np.all(np.abs(x - s.value) <= 0.1 * s.std))
            for x, s in zip(lsq[:k], singles[:k], strict=True)
        ]
        rows.append(
            {
                "n": n,
                "width": width,
                "fleet_rps": n / wall,
                "compile_s": compile_s,
                "loop_rps": 1 / loop_s,
                "lsq_rps": 1 / lsq_s,
                "extrapolated": n > n_loop,
                "agree": f"{sum(agree)}/{k}",
                "lsq_agree": f"{sum(lsq_agree)}/{k}",
                "failed": sum(not f.ok for f in fits),
            }
        )
        log(f"{model}: N={n} fleet {n / wall:.3g} rec/s (x{loop_s * n / wall:.3g} the loop)")
    return {"rows": rows, "memory": memory, "n_samples": members[0].problem.n}


def report(results: dict, command: str, loop_max: int, machine_md: str, elapsed: float) -> str:
    lines = [
        "# Fleet throughput (benchmarks/fleet.py)",
        "",
        f"Command: `{command}`; {elapsed:.0f} s in all. Device: {jax.devices()[0]}.",
        "",
        "Recordings per second, warm (compile time reported apart). The loops are measured on "
        f"at most {loop_max} recordings; where N is larger their rate is that measured one "
        "(a loop's time is linear in N), marked *extrapolated*. *same answers*: recordings "
        "whose every parameter is within 0.1 σ of the single `identify` fit (on the "
        "recordings the loop ran). least_squares starts from the config's initial values "
        "(no search).",
        "",
    ]
    for model, res in results.items():
        lines += [
            f"## {model} ({res['n_samples']} samples per recording after preprocessing)",
            "",
            "| N | shard | fleet rec/s | compile s | identify loop rec/s | fleet / loop | "
            "least_squares rec/s | fleet / lsq | same answers (fleet) | lsq within 0.1 σ | "
            "failed |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in res["rows"]:
            ext = " (extrapolated)" if r["extrapolated"] else ""
            lines.append(
                f"| {r['n']} | {r['width']} | {r['fleet_rps']:.3g} | {r['compile_s']:.1f} | "
                f"{r['loop_rps']:.3g}{ext} | {r['fleet_rps'] / r['loop_rps']:.3g} | "
                f"{r['lsq_rps']:.3g}{ext} | {r['fleet_rps'] / r['lsq_rps']:.3g} | "
                f"{r['agree']} | {r['lsq_agree']} | {r['failed']} |"
            )
        mem = res["memory"]
        if mem:
            dev = f", device peak {mem['device']:.0f} MiB" if mem.get("device") else ""
            lines += [
                "",
                f"Memory at N = {res['rows'][-1]['n']}: process peak RSS {mem['rss_peak']:.0f} MiB "
                f"(peak before the run {mem['rss_before']:.0f} MiB){dev}.",
            ]
        lines.append("")
    lines += ["## Machine", "", machine_md, ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> Path:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="1,10,100,1000", help="fleet sizes N, comma-separated")
    ap.add_argument("--models", default="axis,axis_search,paper", help="axis, axis_search, paper")
    ap.add_argument(
        "--paper-sizes", default=None, help="sizes for the paper model (default: --sizes)"
    )
    ap.add_argument("--loop-max", type=int, default=100, help="most recordings per loop")
    ap.add_argument(
        "--shard-size", type=int, default=None, help="fleet shard size (default: the fleet's)"
    )
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "fleet.md")
    args = ap.parse_args(argv)
    sizes = sorted({int(s) for s in args.sizes.split(",")})
    start = time.perf_counter()

    def log(msg: str) -> None:
        print(f"[{time.perf_counter() - start:7.1f}s] {msg}", file=sys.stderr, flush=True)

    machine_before = describe()
    shard_size = args.shard_size or default_shard_size()
    per_model = {m: sizes for m in args.models.split(",")}
    if args.paper_sizes and "paper" in per_model:
        per_model["paper"] = sorted({int(s) for s in args.paper_sizes.split(",")})
    command = "PYTHONPATH=. python benchmarks/fleet.py " + " ".join(argv or sys.argv[1:])
    results: dict = {}
    for m, n in per_model.items():
        results[m] = bench_model(m, n, args.loop_max, shard_size, log)
        # the report is rewritten after every model: a run cut short keeps what it measured
        load = f"Load after the run: {describe().load}"
        machine_md = f"{machine_before.markdown()}\n\n{load}"
        text = report(results, command, args.loop_max, machine_md, time.perf_counter() - start)
        write_text_atomic(args.out, text)
    print(args.out)
    return args.out


if __name__ == "__main__":
    main()
