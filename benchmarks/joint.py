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

Writes a Markdown table (values ± σ, truth, wall time of each joint fit, cold: its
programs compiled in the call) and the false-finding count. Usage:
``PYTHONPATH=. python benchmarks/joint.py [--null 40] [--out benchmarks/results/joint.md]``.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from fricjax.api import identify_recording, identify_recordings, load
from fricjax.config import load_config
from fricjax.data.recording import write_recording
from fricjax.data.twin import AXIS_TRUTH, axis_twin
from fricjax.io.atomic import write_text_atomic
from fricjax.joint import joint_problem, members_of
from fricjax.refine import value_and_jacobian
from fricjax.report.show import joint_drift

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "axis_joint.toml"
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "benchmarks/results/joint.md")
    parser.add_argument("--null", type=int, default=40, help="pairs of one unchanged plant")
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
    ]
    write_text_atomic(args.out, "\n".join(lines))
    print(args.out)


if __name__ == "__main__":
    main()
