"""How much of a concealed case's c the hidden term itself explains (scoring only).

A case's concealment ``c = min_θ ‖W·(r_e(θ) − r_floor)‖/σ_x`` (:func:`generate.refit_concealment`)
counts everything the base model cannot absorb of the effect's equation-error signature.
Where the effect moves the plant's stops, part of that is the stick/slip rule's bias at the
samples at rest, which the true term does not explain either: no namer can attribute that
part to the effect. This script refits base + the hidden term (its shape and amplitude free
in their boxes, from the truth) on the same noise-free record and splits c in two:

    c_left      = min_{θ, φ} ‖W·(r_{e+term}(θ, φ) − r_floor)‖/σ_x     [1]
    c_explained = √(c² − c_left²)                                        [1]

``c_explained`` is what a namer with the right term can gain (its square is the
noncentrality of the true term's likelihood ratio on the noisy record); ``c_left`` is
structure the catalogue's right answer leaves behind. Both are recomputed from the record
itself (its noise regenerated from the case's seed and subtracted), with the samples at rest
its recording marks, so ``c`` recomputed here is checked against the truth file's.

Where the true term has ``k`` parameters and the record ``M`` whitened dimensions, its
likelihood ratio on the noisy record, at its true shape and with σ_x known, is noncentral
χ²_k with noncentrality ``c_explained²`` (to first order), and the diagnosis' selection
asks ``ΔBIC = LR − k·ln M > 10`` (:func:`fricjax.diagnose.select.bic_known`; the profile
form ``M·ln(RSS_w/M)`` agrees where ``RSS_w ≈ M·σ_x²``). So

    P(pays) = P(χ'²_k(c_explained²) > 10 + k·ln M)                        [2]

and its sum over the cases of a level is how many of them any namer that keeps that bar can
expect to name: an upper bound, as a namer must also find the shape (a search whose
look-elsewhere its significance pays for) and rank the term first.

The bar is not the only test: the selection also asks the term's score to be significant at
the family-wise level, ``p < α/K`` over its ``K`` candidates (α = 0.01, K = 11: 0.00091).
At the true shape, with no search to pay for, that is ``LR > χ²_k⁻¹(1 − α/K)`` (11.0 for
one parameter, 16.5 for three), so whatever its bar a namer that keeps the significance
can expect at most

    P(pays, bar b) = P(χ'²_k(c_explained²) > max(b + k·ln M, χ²_k⁻¹(1 − α/K)))   [3]

and the report sums [3] over a level for a few bars (10, the diagnosis'; 6 and 2, where
Kass and Raftery's "strong" and "positive" evidence begin; 0, BIC's own preference).

Reads the truth files (this is scoring, never diagnosis) and, where present, the
diagnosis of each case, and writes one Markdown table: per case at its level, c,
c_explained, c_left, P(pays) and the first finding; then top-1 naming split by whether the
true term explains at least 75 % of the level; then, per level, the sum of [2] against the
diagnosis' top-1, and the sums of [2] and [3] for each bar of ``BARS``.

    python benchmarks/concealed/explained.py --data DIR --out REPORT.md [--cases ID,ID]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import generate as gen
import score

from fricjax.config import Config, load_config
from fricjax.data.recording import Recording, read_recording

# the lower end of the scorer's level band also splits "the true term explains the level"
# from "it does not"
EXPLAINS = score.LEVEL_BAND[0]


class Explained(NamedTuple):
    """The split of one case's concealment, all in noise standard deviations [1], and the
    dimensions the bar's penalty counts."""

    c: float  # recomputed from the record (the truth file's, if the record is its own)
    c_left: float  # what base + the true term, refitted, still leave
    c_explained: float  # √(c² − c_left²)
    k: int  # the true term's free parameters
    m: int  # whitened dimensions of the record (the diagnosis' M)


def pays_probability(
    c: float, k: int, m: int, bar: float = score.ORACLE_DBIC, gate: float | None = None
) -> float:
    """Equation [2] of the module docstring: the chance that a term of ``k`` parameters
    whose signature is ``c`` noise standard deviations lowers the known-variance BIC of a
    record of ``m`` whitened dimensions by more than ``bar``; with ``gate`` (a p-value
    limit), [3]: its likelihood ratio must also be significant at that level."""
    from scipy.stats import chi2, ncx2

    need = bar + k * math.log(m)
    if gate is not None:
        need = max(need, float(chi2.isf(gate, k)))
    return float(ncx2.sf(need, k, c * c))


# the bars of the report's sensitivity table [3]: the diagnosis', then where Kass and
# Raftery's "strong" and "positive" evidence begin, then BIC's bare preference
BARS = (score.ORACLE_DBIC, 6.0, 2.0, 0.0)


def significance_gate(config: Config) -> float:
    """α/K of the selection's first step: the config's family-wise level over the
    catalogue's candidates (:func:`fricjax.diagnose.select.forward_select`)."""
    from fricjax.diagnose.catalogue import CATALOGUE
    from fricjax.diagnose.run import DiagnoseSettings

    alpha = DiagnoseSettings.from_dict(dict(config.table("diagnose")), source=config.source).alpha
    return alpha / len(CATALOGUE)


def explained_concealment(truth: dict[str, Any], recording: Recording, config: Config) -> Explained:
    """:class:`Explained` of one generated case (``truth``: its truth file's contents;
    ``recording``: its record as written; ``config``: the one it was generated with)."""
    c, theta_base, view, clean, floor = gen.record_concealment(truth, recording, config)
    ext, theta_true = gen.with_true_term(clean, truth["effect"], truth["base"], truth["params"])
    # base + term nests the base (the term's amplitudes at their null values), so it is also
    # refitted from the base's own refit, and the better end counts: from the truth alone the
    # refit can stop in a worse local minimum than the base's (a 0.272 s Stribeck drop: 7.74
    # left where c = 4.95), and from the nested start alone it can stay at the base's (a
    # 0.272 s asymmetry at c = 9.67: 9.67 left, 8.32 from the truth)
    refitted = {k: float(v) for k, v in clean.spec.unflatten(theta_base).items()}
    nulls = {
        p.name: p.null
        for p in ext.spec.params
        if p.name in truth["params"] and not math.isnan(p.null)
    }
    theta_nested = ext.spec.flatten({**truth["params"], **refitted, **nulls})
    c_left = min(gen.bounded_refit(view, ext, floor, [x])[0] for x in (theta_true, theta_nested))
    # the nested start makes c_left <= c up to the optimiser's tolerance
    k = ext.spec.n_free - clean.spec.n_free
    return Explained(c, c_left, math.sqrt(max(c * c - c_left * c_left, 0.0)), k, view.wh.dof)


def at_level(truth: dict[str, Any]) -> bool:
    return truth["effect"] != gen.NULL and score.on_level(truth)


def first_finding(data: Path, case: str) -> str | None:
    """The diagnosis' first finding ('none' when it found nothing; None: not diagnosed)."""
    path = data / "diagnosis" / f"{case}.json"
    if not path.exists():
        return None
    findings = json.loads(path.read_text())["findings"]
    return findings[0]["effect"] if findings else "none"


def expected_to_pay(
    rows: Sequence[dict[str, Any]],
    c: str = "c_explained",
    bar: float = score.ORACLE_DBIC,
    gate: float | None = None,
) -> float:
    """Sum of [2] (or [3], with ``gate``) over ``rows``, each at its own ``c`` column."""
    return sum(pays_probability(r[c], r["k"], r["m"], bar, gate) for r in rows)


def _share(x: float, n: int) -> str:
    return f"{x:.1f} ({x / n:.0%})"


def report(rows: Sequence[dict[str, Any]], data: Path, gate: float) -> str:
    """Markdown: one row per case, then top-1 by whether c_explained reaches 0.75× level."""
    lines = [
        "# How much of c the hidden term explains",
        "",
        f"Records: `{data}`. c recomputed from each noise-free record (samples at rest as its",
        "recording marks them); c_left: what base + the true term, refitted in their boxes,",
        "leave of it; c_explained = √(c² − c_left²): what the right name can gain",
        "(`benchmarks/concealed/explained.py`). Cases at their level only.",
        "",
        "k: the true term's parameters; M: the record's whitened dimensions; P(pays): the",
        "chance that the true term, at its true shape, lowers the BIC by more than "
        f"{score.ORACLE_DBIC:g} on a",
        f"noisy record, P(χ'²_k(c_explained²) > {score.ORACLE_DBIC:g} + k·ln M) (module "
        "docstring, [2]).",
        "",
        "| case | length [s] | hidden | level | c (truth file) | c (record) | c_explained"
        " | c_left | k | M | P(pays) | first finding | top-1 |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        top1 = "–" if r["first"] is None else ("yes" if r["first"] == r["effect"] else "no")
        lines.append(
            f"| {r['case']} | {r['duration']:g} | {r['effect']} | {r['level']:g} "
            f"| {r['c_truth']:.2f} | {r['c']:.2f} | {r['c_explained']:.2f} "
            f"| {r['c_left']:.2f} | {r['k']} | {r['m']} "
            f"| {pays_probability(r['c_explained'], r['k'], r['m']):.2f} "
            f"| {r['first'] or 'not diagnosed'} | {top1} |"
        )
    lines += [
        "",
        "Top-1 naming by level and by whether the true term explains at least 0.75× the level:",
        "",
        "| level | c_explained ≥ 0.75× level | c_explained < 0.75× level |",
        "|---|---|---|",
    ]
    for level in sorted({r["level"] for r in rows}):
        cells = []
        for explains in (True, False):
            rs = [
                r
                for r in rows
                if r["level"] == level
                and r["first"] is not None
                and (r["c_explained"] >= EXPLAINS * level) == explains
            ]
            named = sum(r["first"] == r["effect"] for r in rs)
            cells.append(f"{named}/{len(rs)}" if rs else "–")
        lines.append(f"| {level:g} | {cells[0]} | {cells[1]} |")
    lines += [
        "",
        "What any namer that keeps the bar can expect to name first, against what the",
        "diagnosis named: the sum of P(pays) over the cases of a level (an upper bound, [2]),",
        "and the same if the true term explained all of c (c_left = 0):",
        "",
        "| level | cases | expected to pay | if the term explained all of c | top-1 |",
        "|---|---|---|---|---|",
    ]
    levels = {
        lv: [r for r in rows if r["level"] == lv] for lv in sorted({r["level"] for r in rows})
    }
    for level, rs in levels.items():
        named = [r for r in rs if r["first"] is not None]
        top1 = sum(r["first"] == r["effect"] for r in named)
        lines.append(
            f"| {level:g} | {len(rs)} | {_share(expected_to_pay(rs), len(rs))} "
            f"| {_share(expected_to_pay(rs, 'c'), len(rs))} "
            f"| {top1}/{len(named)} ({top1 / max(len(named), 1):.0%}) |"
        )
    lines += [
        "",
        "The same sum for other bars, by the bar alone ([2]) and with the selection's",
        f"significance too, p < α/K = {gate:.2g} at the true shape ([3]):",
        "",
        "| level | cases | ΔBIC bar | expected to pay, bar alone | with the significance |",
        "|---|---|---|---|---|",
    ]
    for level, rs in levels.items():
        for bar in BARS:
            lines.append(
                f"| {level:g} | {len(rs)} | {bar:g} "
                f"| {_share(expected_to_pay(rs, bar=bar), len(rs))} "
                f"| {_share(expected_to_pay(rs, bar=bar, gate=gate), len(rs))} |"
            )
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, required=True, help="generated case directory")
    parser.add_argument("--out", type=Path, required=True, help="Markdown report")
    parser.add_argument("--cases", default="", help="case ids, comma-separated (default: all)")
    args = parser.parse_args(argv)
    from fricjax.api import enable_compilation_cache

    enable_compilation_cache()
    truth_dir = args.data / "truth"
    if not truth_dir.is_dir():
        print(f"error: {truth_dir}: no truth folder (not a generated case directory)")
        return 2
    wanted = {c for c in args.cases.split(",") if c}
    truths = [json.loads(p.read_text()) for p in sorted(truth_dir.glob("*.json"))]
    unknown = wanted - {t["case"] for t in truths}
    if unknown:
        print(f"error: --cases: not in {truth_dir}: {', '.join(sorted(unknown))}")
        return 2
    truths = [t for t in truths if at_level(t) and (not wanted or t["case"] in wanted)]
    truths.sort(key=lambda t: (t["duration_s"], t["level"], t["effect"], t["case"]))
    config = load_config(gen.CONFIG)
    rows = []
    for truth in truths:
        t0 = time.perf_counter()
        rec = read_recording(args.data / f"{truth['case']}.h5")
        e = explained_concealment(truth, rec, config)
        rows.append(
            {
                "case": truth["case"],
                "duration": truth["duration_s"],
                "effect": truth["effect"],
                "level": truth["level"],
                "c_truth": truth["concealment"],
                **e._asdict(),
                "first": first_finding(args.data, truth["case"]),
            }
        )
        print(
            f"{truth['case']} {truth['effect']}: c {e.c:.2f} (truth file "
            f"{truth['concealment']:.2f}), explained {e.c_explained:.2f}, left {e.c_left:.2f}"
            f" ({time.perf_counter() - t0:.0f} s)",
            flush=True,
        )
    from fricjax.io.atomic import write_text_atomic

    write_text_atomic(args.out, report(rows, args.data, significance_gate(config)))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
