"""Plain-text tables, including the layout of the seed's Tables 1–4.

Seed layout: Table 1 (F0, Fc, Fv, Fs, vs), Table 2 (Fp_1..Fp_10), Table 3 (phi_1..phi_10),
Table 4 (EMS), one column per method/run; we add omega, truth and error columns.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

#: The seed's published values (Tables 1-4), by method, for side-by-side reports.
SEED_TABLES: dict[str, dict[str, float]] = {
    "RDSA": {
        "F0": 444.2,
        "Fc": 35.71,
        "Fv": 3763.9,
        "Fs": 186.16,
        "vs": 0.119,
        **{
            f"Fp_{i}": v
            for i, v in enumerate(
                (678.1, 996.5, 1113, 876.3, 546.1, 44.80, 268.5, 133.5, 411.0, 9.39), 1
            )
        },
        **{
            f"phi_{i}": v
            for i, v in enumerate(
                (0.74, 0.98, 1.26, 1.51, 1.57, 0.454, 0.001, 0.005, 0.002, 1.19), 1
            )
        },
        "EMS": 59209,
    },
    "CSAA": {
        "F0": 432.7,
        "Fc": 30.00,
        "Fv": 3749.9,
        "Fs": 189.99,
        "vs": 0.121,
        **{
            f"Fp_{i}": v
            for i, v in enumerate(
                (667.5, 998.1, 1118.9, 879.9, 559.9, 49.99, 279.9, 139.9, 413.0, 9.99), 1
            )
        },
        **{
            f"phi_{i}": v
            for i, v in enumerate(
                (0.71, 0.96, 1.24, 1.49, 1.57, 0.499, 0.001, 0.001, 0.001, 1.00), 1
            )
        },
        "EMS": 58322,
    },
    "DSAA": {
        "F0": 430,
        "Fc": 30,
        "Fv": 3750,
        "Fs": 190,
        "vs": 0.125,
        **{
            f"Fp_{i}": v
            for i, v in enumerate((664.3, 996.2, 1114.9, 880, 560, 50, 280, 140, 414.9, 10.00), 1)
        },
        **{
            f"phi_{i}": v
            for i, v in enumerate(
                (0.69, 0.95, 1.23, 1.48, 1.55, 0.500, 0.001, 0.001, 0.001, 1.00), 1
            )
        },
        "EMS": 58335,
    },
}

SEED_GROUPS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("Table 1. Friction and mean drive", ("F0", "Fc", "Fv", "Fs", "vs", "delta", "omega")),
    ("Table 2. Harmonic amplitudes", tuple(f"Fp_{i}" for i in range(1, 11))),
    ("Table 3. Harmonic phases", tuple(f"phi_{i}" for i in range(1, 11))),
)


def fmt(value: float | None, digits: int = 5) -> str:
    if value is None:
        return "-"
    if value != value:  # NaN
        return "nan"
    return f"{value:.{digits}g}"


def p_text(p: float) -> str:
    """``"p = 0.0012"``, or ``"p < 1e-300"`` where the p-value underflows a double (it is
    then no more zero than any other tiny probability)."""
    return f"p = {p:.2g}" if p >= 1e-300 or math.isnan(p) else "p < 1e-300"


def format_table(rows: Sequence[Sequence[str]], header: Sequence[str] | None = None) -> str:
    """Left-aligned first column, right-aligned others, a rule under the header."""
    all_rows = [tuple(header)] if header else []
    all_rows += [tuple(str(c) for c in r) for r in rows]
    if not all_rows:
        return ""
    widths = [max(len(r[i]) for r in all_rows if i < len(r)) for i in range(len(all_rows[0]))]
    lines = []
    for k, r in enumerate(all_rows):
        cells = [r[0].ljust(widths[0])] + [
            c.rjust(w) for c, w in zip(r[1:], widths[1:], strict=False)
        ]
        lines.append("  ".join(cells).rstrip())
        if header and k == 0:
            lines.append("  ".join("-" * w for w in widths))
    return "\n".join(lines)


def format_fields(rows: Sequence[tuple[str, str]]) -> str:
    """``name  value`` lines, both left-aligned: a summary whose values are sentences of any
    length stays as wide as its longest line, not as its longest value right-aligned."""
    width = max((len(k) for k, _ in rows), default=0)
    return "\n".join(f"{k.ljust(width)}  {v}".rstrip() for k, v in rows)


def seed_tables(
    columns: Mapping[str, Mapping[str, float]],
    *,
    ems: Mapping[str, float],
    truth: Mapping[str, float] | None = None,
    extra_rows: Sequence[str] = (),
    ems_unit: str = "N²",
) -> str:
    """Seed Tables 1–4 with one column per run (+ truth and relative-error columns).

    ``columns``: run label -> {parameter: value}; ``ems``: run label -> EMS [``ems_unit``,
    N² or (N·m)² on a rotary axis].
    With ``truth``, each run gets an error column: relative error in % for forces and
    amplitudes, absolute error (rad) for phases.
    """
    labels = list(columns)
    out = []
    groups = list(SEED_GROUPS)
    if extra_rows:
        groups.append(("Other parameters", tuple(extra_rows)))
    for title, names in groups:
        names = tuple(n for n in names if any(n in columns[lb] for lb in labels))
        if not names:
            continue
        header = ["parameter", *labels]
        if truth:
            header = ["parameter", "truth", *[h for lb in labels for h in (lb, "err")]]
        rows = []
        for name in names:
            row = [name]
            if truth:
                row.append(fmt(truth.get(name)))
            for lb in labels:
                value = columns[lb].get(name)
                row.append(fmt(value))
                if truth:
                    row.append(_err(name, value, truth.get(name)))
            rows.append(row)
        out.append(f"{title}\n{format_table(rows, header)}")
    ems_rows = [
        [
            f"EMS [{ems_unit}]",
            *([""] if truth else []),
            *[c for lb in labels for c in ((fmt(ems[lb], 6), "") if truth else (fmt(ems[lb], 6),))],
        ]
    ]
    header = (
        ["method", *labels]
        if not truth
        else ["method", "", *[h for lb in labels for h in (lb, "")]]
    )
    out.append(f"Table 4. Error mean square\n{format_table(ems_rows, header)}")
    return "\n\n".join(out)


def _err(name: str, value: float | None, truth: float | None) -> str:
    if value is None or truth is None:
        return "-"
    if name.startswith("phi_"):
        import math

        d = (value - truth + math.pi) % (2 * math.pi) - math.pi
        return f"{d:+.3f}rad"
    if truth == 0:
        return fmt(value - truth, 3)
    return f"{100 * (value - truth) / abs(truth):+.2f}%"
