"""Do the diagnosis' output-error fits reach the minimum? Cost reached against a reference.

Run from the repository root (CPU-heavy: ``nice`` it on a shared machine)::

    python benchmarks/fit_convergence.py                          # every case
    python benchmarks/fit_convergence.py --cases twin_0.272,force_1s

Each case is a record and its config. Two fits, each exactly as ``fricjax diagnose`` runs
it (:mod:`fricjax.diagnose.judge`, the settings of :class:`~fricjax.diagnose.run.
DiagnoseSettings`: segments of 0.05 s, the residual in units of the record's own σ̂_x):

- **base**: ``identify`` (equation error), then :func:`~fricjax.diagnose.judge.fit_base`
  on the superset model (every catalogue term pinned), restarted until a round gains less
  than ``CONVERGED``;
- **base + term**: :func:`~fricjax.diagnose.judge.fit_candidates` for one catalogue term
  (``quadratic_drag``: one amplitude, defined on every model) from the base's optimum.

Each fit runs twice in the process: cold (compilation included) and warm; the warm run's
rounds, LM steps and wall time are reported.

**Reference minimum.** The same residual (the same parameters and segment states free, the
same box) minimised by scipy's ``least_squares(method="trf", x_scale="jac")``, a
trust-region reflective method that shares no code with fricjax's Levenberg–Marquardt, with
its tolerances at 1e-15 and up to ``--nfev`` evaluations, from the fit's own end point and
independently from the fit's start. The reference is the lowest of the three costs; the
table gives each fit's cost − reference [σ_x²]. A gap ≤ 0.5 σ_x² is converged for the
judge, whose bar is ΔBIC 10 beyond k·ln n.

Cases: the seed model's twins (``data/paper_twin.h5``, 0.272 s; ``paper_twin(duration=1|4,
seed=11)``) on ``configs/paper.toml``; a force-driven axis and a stick-slip rig of the
concealed benchmark (draw A's 1 s nulls at σ_x = 5 µm, read from ``--data``, written by
``benchmarks/concealed/score.py --stage generate``) on its ``force_axis.toml``; EMPS's first
4 s and the whole 24.8 s estimation file on ``configs/emps.toml`` (``../shared/data/real/
emps/``). A case whose data are absent is skipped with a message.

Writes ``benchmarks/results/fit_convergence.md`` (atomically; ``--report`` for another
path).
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from diagnose_speed import EMPS, make_recording  # noqa: E402

OUT = ROOT / "benchmarks" / "results" / "fit_convergence.md"
CONCEALED = ROOT / "out" / "concealed"
FORCE_CONFIG = ROOT / "benchmarks" / "concealed" / "configs" / "force_axis.toml"
TERM = "quadratic_drag"
# case: (what it is, config)
CASES: dict[str, tuple[str, str]] = {
    "twin_0.272": ("seed model, bundled twin (0.272 s)", "configs/paper.toml"),
    "twin_1s": ("seed model, twin paper_twin(duration=1, seed=11)", "configs/paper.toml"),
    "twin_4s": ("seed model, twin paper_twin(duration=4, seed=11)", "configs/paper.toml"),
    "force_1s": ("force-driven axis, concealed draw A null, 1 s, 5 µm", str(FORCE_CONFIG)),
    "slow_1s": ("stick-slip rig, concealed draw A null, 1 s, 5 µm", str(FORCE_CONFIG)),
    "emps_4s": ("EMPS estimation file, first 4 s", "configs/emps.toml"),
    "emps_24.8s": ("EMPS estimation file, whole", "configs/emps.toml"),
}


def concealed_null(family: str, data: Path) -> Path | None:
    """Draw A's 1 s null of ``family`` at σ_x = 5 µm, or None when not generated."""
    plan = data / "drawA" / "plan.json"
    if not plan.is_file():
        return None
    for c in json.loads(plan.read_text())["cases"]:
        if (c["family"], c["effect"], c["duration"], c["sigma"]) == (family, "none", 1.0, 5e-6):
            path = data / "drawA" / c["recording"]
            return path if path.is_file() else None
    return None


def recording(case: str, work: Path, data: Path, emps: Path) -> Path | None:
    if case in ("force_1s", "slow_1s"):
        return concealed_null(case.split("_")[0], data)
    return make_recording(case, work, emps)


@dataclass
class Outcome:
    """One fit: its cost, rounds and LM steps (warm run), wall time cold and warm, and the
    scipy reference runs (cost, evaluations, seconds) from its end and from its start."""

    cost: float
    rounds: int
    steps: int
    cold_s: float
    warm_s: float
    ref_end: tuple[float, int, float]
    ref_start: tuple[float, int, float]

    @property
    def reference(self) -> float:
        return min(self.cost, self.ref_end[0], self.ref_start[0])


@functools.cache
def _jitted():
    import jax

    return jax.jit(lambda res, theta_aug: res.value(theta_aug))


def _value(res, theta_aug):
    return _jitted()(res, theta_aug)


def reference(problem, free, fit, start: dict[str, float], states, oe, nfev: int):
    """scipy least_squares (TRF, Jacobian scaling) on ``problem``'s output-error residual
    with the fit's free components, from ``fit``'s end and from ``start``: two (cost
    [σ_x²], evaluations, seconds)."""
    from scipy.optimize import least_squares

    from fricjax.output_error import jacobian_at, output_error_residual

    spec = problem.spec
    movable = dict(zip(spec.free_names, free, strict=True))
    out = []
    for named, st in ((fit.params, (fit.states_x, fit.states_v)), (start, states)):
        setup = output_error_residual(problem, named, oe, st)
        P = len(spec.names)
        keep = setup.free.copy()
        keep[:P] = [p.free and movable.get(p.name, False) for p in spec.params]
        idx = np.flatnonzero(keep)
        base = setup.x0.copy()

        def full(z: np.ndarray, base=base, idx=idx) -> np.ndarray:
            th = base.copy()
            th[idx] = z
            return th

        def fun(z: np.ndarray, res=setup.residual, full=full) -> np.ndarray:
            return np.asarray(_value(res, full(z)))

        def jac(z: np.ndarray, res=setup.residual, full=full, idx=idx) -> np.ndarray:
            return np.asarray(jacobian_at(res, full(z))[1])[:, idx]

        lo, hi = setup.lower[idx], setup.upper[idx]
        z0 = np.clip(setup.x0[idx], lo + 1e-12 * (hi - lo), hi - 1e-12 * (hi - lo))
        began = time.perf_counter()
        sol = least_squares(
            fun, z0, jac=jac, bounds=(lo, hi), method="trf", x_scale="jac",
            ftol=1e-15, xtol=1e-15, gtol=1e-15, max_nfev=nfev,
        )  # fmt: skip
        out.append((float(2.0 * sol.cost), int(sol.nfev), time.perf_counter() - began))
    return out[0], out[1]


def run_case(path: Path, config: str, nfev: int) -> dict[str, Outcome]:
    from fricjax.api import load
    from fricjax.diagnose.evidence import near_rest_band, record_noise
    from fricjax.diagnose.judge import Superset, converged, fit_candidates, starts
    from fricjax.diagnose.run import DiagnoseSettings
    from fricjax.identify import IdentifySettings, identify

    _, cfg, problem = load(path, ROOT / config)
    ident = IdentifySettings.from_tables(cfg.tables, source=cfg.source)
    run = identify(problem, ident.__class__(**{**ident.__dict__, "objective": "equation"}))
    settings = DiagnoseSettings()
    evidence = record_noise(problem)
    oe = settings.output_error(evidence)
    sup = Superset.build(problem)
    full = {**sup.problem.spec.as_dict(), **run.params}
    base_pb, base_free, k = sup.problem, sup.moving(()), sup.n_directions(())
    out: dict[str, Outcome] = {}

    def timed(fn):
        began = time.perf_counter()
        value = fn()
        return value, time.perf_counter() - began

    _, cold = timed(lambda: converged(base_pb, base_free, full, oe, n_directions=k))
    rounds: list = []
    base_fit, warm = timed(
        lambda: converged(base_pb, base_free, full, oe, n_directions=k, rounds=rounds)
    )
    ref_end, ref_start = reference(base_pb, base_free, base_fit, full, None, oe, nfev)
    out["base"] = Outcome(
        base_fit.cost, len(rounds), sum(r[1] for r in rounds), cold, warm, ref_end, ref_start
    )

    from fricjax.diagnose.judge import Fitted

    base = Fitted(sup, (), base_fit)
    band = near_rest_band(problem, evidence.sigma_x)
    todo = [(TERM, starts(base, TERM, band, settings.n_starts)[:1])]
    _, cold = timed(lambda: fit_candidates(base, todo, oe, evidence.nu))
    (cf,), warm = timed(lambda: fit_candidates(base, todo, oe, evidence.nu))
    start = {**base_fit.params, **todo[0][1][0]}
    ref_end, ref_start = reference(
        sup.problem,
        sup.moving((TERM,)),
        cf.fitted.fit,
        start,
        (base_fit.states_x, base_fit.states_v),
        oe,
        nfev,
    )
    out["base + " + TERM] = Outcome(
        cf.fitted.cost, 0, cf.fitted.fit.n_steps, cold, warm, ref_end, ref_start
    )
    return out


def report(rows: list[tuple[str, str, dict[str, Outcome] | str]], path: Path) -> Path:
    from fricjax.bench.machine import describe
    from fricjax.io.atomic import write_text_atomic

    lines = [
        "# Output-error fits against a reference minimum",
        "",
        "`python benchmarks/fit_convergence.py` (docstring: what each fit is, how the "
        "reference is found). Costs in σ_x² (the record's own noise); gap = cost − "
        "reference, where the reference is the lowest of the fit, scipy TRF from the fit's "
        "end and scipy TRF from the fit's start. Rounds and steps of the warm run.",
        "",
        describe().markdown(),
        "",
        "| case | fit | cost | gap | rounds | LM steps | cold [s] | warm [s] "
        "| TRF from end: cost, nfev, s | TRF from start: cost, nfev, s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for case, what, res in rows:
        if isinstance(res, str):
            lines.append(f"| {case} | {res} | | | | | | | | |")
            continue
        for fit, o in res.items():
            e, s = o.ref_end, o.ref_start
            lines.append(
                f"| {case} ({what}) | {fit} | {o.cost:.6g} | {o.cost - o.reference:.3g} | "
                f"{o.rounds or '–'} | {o.steps} | {o.cold_s:.1f} | {o.warm_s:.1f} | "
                f"{e[0]:.6g}, {e[1]}, {e[2]:.0f} | {s[0]:.6g}, {s[1]}, {s[2]:.0f} |"
            )
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_text_atomic(path, "\n".join(lines) + "\n")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--report", type=Path, default=OUT)
    ap.add_argument("--data", type=Path, default=CONCEALED, help="concealed benchmark cases")
    ap.add_argument("--emps", type=Path, default=EMPS, help="folder of DATA_EMPS.mat")
    ap.add_argument("--nfev", type=int, default=400, help="most evaluations of each TRF run")
    args = ap.parse_args()
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    cases = [c.strip() for c in args.cases.split(",") if c.strip()]
    unknown = [c for c in cases if c not in CASES]
    if unknown:
        print(f"error: --cases: unknown {unknown[0]!r} (known: {', '.join(CASES)})")
        return 2
    rows: list[tuple[str, str, dict[str, Outcome] | str]] = []
    with tempfile.TemporaryDirectory() as work:
        for case in cases:
            what, config = CASES[case]
            path = recording(case, Path(work), args.data, args.emps)
            if path is None:
                msg = f"skipped: data absent ({what})"
                print(f"{case}: {msg}", flush=True)
                rows.append((case, what, msg))
                continue
            print(f"{case}: {what}", flush=True)
            res = run_case(path, config, args.nfev)
            for fit, o in res.items():
                print(
                    f"  {fit}: cost {o.cost:.6g}, gap {o.cost - o.reference:.3g}, "
                    f"steps {o.steps}, warm {o.warm_s:.1f} s (TRF end {o.ref_end[0]:.6g}, "
                    f"start {o.ref_start[0]:.6g})",
                    flush=True,
                )
            rows.append((case, what, res))
    print(f"report: {report(rows, args.report)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
