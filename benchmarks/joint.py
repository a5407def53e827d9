"""Joint fit (:mod:`fricjax.joint`): what a second recording and a noisy third one do to σ.

Three 1 s axis twins (:func:`fricjax.data.twin.axis_twin`, ``configs/axis_joint.toml``:
Coulomb + viscous shared, one drive offset per recording), the third with 4× the x noise:

* each recording fitted alone (``identify_recording``);
* recordings 1 + 2 jointly, then 1 + 2 + 3 (``identify_recordings``: each residual over
  its own fit's residual scale s_k);
* the same three with equal weights: the least-squares point of the unweighted sum has
  the sandwich covariance ``A⁻¹ (Σ_k s_k² J_kᵀJ_k) A⁻¹``, ``A = Σ_k J_kᵀJ_k``, evaluated
  at the joint optimum (what the noise weighting avoids).

Then the drift check's false findings on one unchanged plant: ``--null`` pairs of
recordings with the same offset (noise seeds 100 + 2i, 101 + 2i), each pair fitted jointly;
a pair counts as a false finding when the drift check (:func:`fricjax.report.show.joint_drift`)
flags the offset (Bonferroni family-wise α = 0.05, so ≤ 5 % expected).

Then the diagnosis across recordings (:mod:`fricjax.diagnose.across`), ``--across`` draws
of each:

* false drift findings on one unchanged plant: three axis twins (offsets 6, −4, 1 N per
  recording, noise seeds 1000 + 3i + j), drift of Fc and Fv tested (no catalogue term);
  with each drift test's W/dof (1 on average under the null when σ is right) and the
  share of uncorrected p < 0.05 (5 % when calibrated);
* false findings on two opposite one-way strokes of one symmetric plant
  (:func:`fricjax.data.twin.stroke_twin`, ``configs/axis_strokes.toml``, seeds
  2000 + 2i + j): ``asymmetric_friction`` and drift of Fc and Fv tested;
* the asymmetry named on two opposite strokes, asym_dFc from 0.1 to 1 N, a few seeds
  each; and on three strokes (two forward, one back), where leaving a forward stroke out
  judges it.

Writes a Markdown table (values ± σ, truth, wall time of each joint fit, cold: its
programs compiled in the call), the false-finding counts, the machine and its load. Usage:
``PYTHONPATH=. nice -n 10 python benchmarks/joint.py [--null 40] [--across 20]
[--out benchmarks/results/joint.md]``.
"""

from __future__ import annotations

import argparse
import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np

from fricjax.api import identify_recording, identify_recordings, load
from fricjax.config import load_config
from fricjax.data.recording import write_recording
from fricjax.data.twin import AXIS_TRUTH, axis_twin, stroke_twin
from fricjax.diagnose.across import DRIFT, LeaveOneOut, diagnose_across
from fricjax.identify import IdentifySettings
from fricjax.io.atomic import write_text_atomic
from fricjax.joint import JointSettings, joint_problem, members_of
from fricjax.problem import build_problem
from fricjax.refine import value_and_jacobian
from fricjax.report.show import joint_drift

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "axis_joint.toml"
STROKES = ROOT / "configs" / "axis_strokes.toml"
#: asym_dFc [N] of the power runs, and seeds per value.
ASYM = (0.1, 0.2, 0.3, 0.5, 1.0)
ASYM_SEEDS = 4
#: (offset [N], x noise [m]) of each recording.
RECORDINGS = ((6.0, 2e-6), (-4.0, 2e-6), (1.0, 8e-6))
SHARED = ("Fc", "Fv")


def pm(run, name: str) -> str:
    i = run.names.index(name)
    return f"{run.value[i]:.4g} ± {run.std[i]:.3g}"


def equal_weight_sigma(paths: list[Path], joint_run) -> np.ndarray:
    """Sandwich σ of the shared parameters for the unweighted joint sum (module docstring)."""
    cfg = load_config(CONFIG)
    problems = [load(p, cfg)[2] for p in paths]
    jp = joint_problem(problems, ("offset",), np.ones(len(problems)))
    _, jac = value_and_jacobian(jp.residual_fn, np.asarray(joint_run.value))
    s = np.array([m["sigma"] for m in members_of(joint_run)])
    edges = np.cumsum([0] + [p.n_residual for p in problems])
    a_inv = np.linalg.inv(jac.T @ jac)
    blocks = [jac[edges[k] : edges[k + 1]] for k in range(len(problems))]
    meat = sum(s[k] ** 2 * b.T @ b for k, b in enumerate(blocks))
    return np.sqrt(np.diag(a_inv @ meat @ a_inv))


def null_findings(folder: Path, pairs: int) -> tuple[int, list[float], float, float]:
    """False drift findings over ``pairs`` joint fits of two recordings of one plant; also
    every pair's largest |z|, the threshold z* and the wall time per joint fit [s] (warm
    after the first)."""
    hits, zs, threshold = 0, [], float("nan")
    start = time.perf_counter()
    for i in range(pairs):
        paths = []
        for j in range(2):
            seed = 100 + 2 * i + j
            truth = {**AXIS_TRUTH, "offset": 2.0}
            rec, _ = axis_twin(seed=seed, noise_std=RECORDINGS[0][1], truth=truth)
            paths.append(write_recording(rec, folder / f"null{seed}.h5"))
        run, _ = identify_recordings(paths, CONFIG, out=folder / f"null{i}.results.h5")
        (finding,) = joint_drift(run)
        hits += finding.drifted
        zs.append(finding.z_max)
        threshold = finding.threshold
    return hits, zs, threshold, (time.perf_counter() - start) / max(pairs, 1)


def _across(recs, config: Path, effects: list[str]):
    cfg = load_config(config)
    problems = [build_problem(r, cfg) for r in recs]
    settings = IdentifySettings.from_tables(cfg.tables, source=cfg.source)
    joint = JointSettings.from_config(cfg)
    return diagnose_across(problems, settings, joint, effects=effects)


def _first_round(diag, kind: str) -> list:
    """The first step's fits of one kind (``drift`` or ``term``), against the plain joint
    model; a test the recordings cannot make left out."""
    if not diag.steps:
        return []
    return [
        f
        for f in diag.steps[0].fits
        if (f.effect == DRIFT) == (kind == "drift") and f.test.determined
    ]


def _kinds(diag) -> set[str]:
    """The kinds of the named findings, each ambiguity set's members included."""
    out = set()
    for f in diag.findings:
        for e in [f, *f.alternatives]:
            if e.named:
                out.add("drift" if e.effect == DRIFT else "term")
    return out


def across_null_axis(draws: int) -> dict:
    """False drift findings over ``draws`` triples of one unchanged axis."""
    hits, ratios, small, walls = 0, [], 0, []
    for i in range(draws):
        recs = [
            axis_twin(
                seed=1000 + 3 * i + j,
                noise_std=RECORDINGS[0][1],
                truth={**AXIS_TRUTH, "offset": off},
                name=f"null{i}_{j}",
            )[0]
            for j, off in enumerate((6.0, -4.0, 1.0))
        ]
        start = time.perf_counter()
        diag = _across(recs, CONFIG, [])
        walls.append(time.perf_counter() - start)
        hits += "drift" in _kinds(diag)
        for t in _first_round(diag, "drift"):
            ratios.append(t.test.statistic / t.test.dof)
            small += t.test.p_value < 0.05
    return {"hits": hits, "ratios": ratios, "small": small, "walls": walls}


def across_null_strokes(draws: int) -> dict:
    """False findings (asymmetry or drift) over ``draws`` pairs of opposite strokes of one
    symmetric plant."""
    hits, asym, drift, ratios, small, walls = 0, 0, 0, [], 0, []
    for i in range(draws):
        recs = [
            stroke_twin(d, noise_std=2e-6, seed=2000 + 2 * i + j, name=f"s{i}_{j}")
            for j, d in enumerate((1.0, -1.0))
        ]
        start = time.perf_counter()
        diag = _across(recs, STROKES, ["asymmetric_friction"])
        walls.append(time.perf_counter() - start)
        hits += bool(diag.findings)
        asym += "term" in _kinds(diag)
        drift += "drift" in _kinds(diag)
        for t in _first_round(diag, "drift") + _first_round(diag, "term"):
            ratios.append(t.test.statistic / t.test.dof)
            small += t.test.p_value < 0.05
    return {
        "hits": hits,
        "asym": asym,
        "drift": drift,
        "ratios": ratios,
        "small": small,
        "walls": walls,
    }


def across_power() -> list[tuple[str, float, int, int, float, str]]:
    """(layout, asym_dFc, named, draws, median W of the term, what the held-out folds
    said) per row."""
    rows = []
    layouts = {"fwd + back": (1.0, -1.0), "fwd + fwd + back": (1.0, 1.0, -1.0)}
    for label, dirs in layouts.items():
        for dfc in ASYM if label == "fwd + back" else (1.0,):
            named, judged, gains, ws = 0, [], [], []
            for s in range(ASYM_SEEDS):
                recs = [
                    stroke_twin(d, asym_dfc=dfc, noise_std=2e-6, seed=3000 + 10 * s + j)
                    for j, d in enumerate(dirs)
                ]
                diag = _across(recs, STROKES, ["asymmetric_friction"])
                ws += [t.test.statistic for t in _first_round(diag, "term")]
                named += "term" in _kinds(diag)
                # the term's own held-out check, whether it leads its set or not
                for t in _first_round(diag, "term"):
                    held = LeaveOneOut(tuple(t.base.fit.jp.sigma)).judge(t.base, t.fitted, {})
                    judged.append(sum(p.judged for p in held.parts))
                    if held.judged:
                        gains.append(held.cost_base - held.cost_term)
            held = (
                f"folds judged {min(judged)}–{max(judged)} of {len(dirs)}"
                + (f", gain {min(gains):.3g}–{max(gains):.3g}" if gains else "")
                if judged
                else ""
            )
            rows.append((label, dfc, named, ASYM_SEEDS, float(np.median(ws)), held))
    return rows


def machine() -> str:
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    return (
        f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores visible, "
        f"load average {load} (1, 5, 15 min) at the end of the run"
    )


def across_lines(draws: int) -> list[str]:
    start = time.perf_counter()
    axis = across_null_axis(draws)
    strokes = across_null_strokes(draws)
    power = across_power()
    wall = time.perf_counter() - start

    def calib(d: dict) -> str:
        r = np.asarray(d["ratios"])
        return (
            f"W/dof mean {r.mean():.2f}, median {np.median(r):.2f} over {r.size} tests; "
            f"uncorrected p < 0.05 in {d['small']} of {r.size}"
        )

    lines = [
        "## Diagnosis across recordings (`fricjax diagnose REC1 REC2 ...`)",
        "",
        "Family-wise α = 0.01 (Bonferroni over each step's candidates, terms and drifts "
        "together), ΔBIC > 10 (the defaults); a finding counts with its ambiguity set.",
        "",
        f"- One unchanged axis, three recordings (offsets per recording; drift of Fc, Fv "
        f"tested): **{axis['hits']} false drift findings in {draws} draws**; {calib(axis)}; "
        f"median {np.median(axis['walls']):.1f} s per diagnosis.",
        f"- One symmetric axis, two opposite one-way strokes (asymmetric_friction, drift of "
        f"Fc, Fv tested): **{strokes['hits']} draws with a false finding in {draws}** "
        f"({strokes['asym']} asymmetry, {strokes['drift']} drift); {calib(strokes)}; "
        f"median {np.median(strokes['walls']):.1f} s per diagnosis.",
        "",
        "Asymmetry named on 1 s strokes, 2 µm x noise (the bars need W > 10 + 2 ln n ≈ 25 "
        "on (asym_dFc, asym_dFv); each alone has σ ≈ 0.5 N, but they are correlated along "
        "a stroke, and what the strokes see, the friction forward minus backward at their "
        "speeds, is determined far better):",
        "",
        "| strokes | asym_dFc [N] | found (alone or in a set) | median W "
        "| held-out check of the term |",
        "| --- | --- | --- | --- | --- |",
        *(
            f"| {lab} | {dfc:g} | {k} of {n} | {w:.1f} | {held} |"
            for lab, dfc, k, n, w, held in power
        ),
        "",
        f"{wall:.0f} s for this section; {machine()}.",
        "",
    ]
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/joint.md")
    parser.add_argument("--null", type=int, default=40, help="pairs of one unchanged plant")
    parser.add_argument("--across", type=int, default=20, help="null draws of the diagnosis")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        paths = []
        for seed, (offset, noise) in enumerate(RECORDINGS):
            truth = {**AXIS_TRUTH, "offset": offset}
            rec, _ = axis_twin(seed=seed, noise_std=noise, truth=truth, name=f"rec{seed + 1}")
            paths.append(write_recording(rec, folder / f"rec{seed + 1}.h5"))
        rows = []
        for k, path in enumerate(paths):
            run, _ = identify_recording(path, CONFIG, out=folder / f"single{k}.h5")
            cells = [pm(run, n) for n in SHARED]
            rows.append((f"recording {k + 1} alone", *cells, pm(run, "offset"), "", ""))
        for count in (2, 3):
            start = time.perf_counter()
            run, _ = identify_recordings(paths[:count], CONFIG, out=folder / f"joint{count}.h5")
            wall = time.perf_counter() - start
            offsets = ", ".join(pm(run, f"offset[{k + 1}]") for k in range(count))
            label = " + ".join(str(k + 1) for k in range(count))
            cells = [pm(run, n) for n in SHARED]
            rows.append((f"joint {label}", *cells, offsets, f"{run.ems:.4f}", f"{wall:.1f}"))
        sigma = equal_weight_sigma(paths, run)
        hits, zs, threshold, per_fit = null_findings(folder, args.null)
        rows.append(
            (
                "joint 1 + 2 + 3, equal weights (sandwich σ)",
                *(f"± {s:.3g}" for s in sigma[:2]),
                "",
                "",
                "",
            )
        )
    header = (
        "fit",
        "Fc [N]",
        "Fv [N·s/m]",
        "offset(s) [N]",
        "cost per entry [1]",
        "wall [s]",
    )
    lines = [
        "# Joint fit: σ with a second and a noisy third recording",
        "",
        f"Generated by `benchmarks/joint.py` (config `configs/axis_joint.toml`). Truth: "
        f"Fc = {AXIS_TRUTH['Fc']:g} N, Fv = {AXIS_TRUTH['Fv']:g} N·s/m, offsets "
        f"{', '.join(f'{o:g}' for o, _ in RECORDINGS)} N; x noise "
        f"{', '.join(f'{n * 1e6:g}' for _, n in RECORDINGS)} µm.",
        "",
        "| " + " | ".join(header) + " |",
        "| " + " | ".join("---" for _ in header) + " |",
        *("| " + " | ".join(r) + " |" for r in rows),
        "",
        f"Drift check on one unchanged plant: {hits} false findings in {args.null} joint fits "
        f"of two recordings with the same offset (family-wise α = 0.05 per fit); largest |z| "
        f"{max(zs, default=float('nan')):.2f}, median {np.median(zs) if zs else float('nan'):.2f}"
        f" (z* = {threshold:.3g}); {per_fit:.1f} s per joint fit.",
        "",
        *(across_lines(args.across) if args.across > 0 else []),
    ]
    write_text_atomic(args.out, "\n".join(lines))
    print(args.out)


if __name__ == "__main__":
    main()
