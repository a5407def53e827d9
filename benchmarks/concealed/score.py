"""Score ``fricjax diagnose`` on recordings with one concealed effect each.

Generates the cases it needs (``generate.py``, deterministic by seed; existing files with the
expected checksum are reused), diagnoses every case in one process with the Python API
(:func:`fricjax.diagnose.run.diagnose` on ``build_problem(read_recording(path),
load_config("configs/paper.toml"))``, identify and diagnose settings from that config), so
same-length cases share their JIT compilations, and only then reads the truth files.

Measured (``benchmarks/results/concealed.md`` + PNGs):

* detection rate (any finding) and top-1 naming accuracy (first finding's effect = the hidden
  one) per effect and per concealment level c = ‖(I − P_J)·s‖/σ_x;
* confusion matrix: hidden effect (or none) × first finding (an effect, ``unexplained`` or
  ``none``), as a table and a heat map;
* false discoveries on null recordings (any finding);
* location error |found − true| of the shape parameter of the named effect (impact t0, bump
  x0, harmonic f, period λ, vst, ε) and the amplitude ratio found/true;
* fit improvement: EMS before/after, held-out improvement of every named finding;
* diagnose wall time per case (median; the first case of each length includes compilation).

Usage (reference run, see the report's header for what was run)::

    python benchmarks/concealed/score.py --lengths 1 --levels 5,10 --reps 1 --nulls 6
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import os
import platform
import subprocess
import sys
import time
import traceback
from collections import Counter
from collections.abc import Iterable, Sequence
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import generate as gen
import numpy as np

from fricjax.diagnose.catalogue import CATALOGUE
from fricjax.diagnose.run import NEAR_REST_CAVEAT, NEAR_REST_LAWS, DiagnoseSettings
from fricjax.errors import FricjaxError

ROOT = gen.ROOT
DEFAULT_DATA = ROOT / "out" / "concealed"
DEFAULT_OUT = ROOT / "benchmarks" / "results" / "concealed.md"
UNEXPLAINED = "unexplained"
# Targets of the issue ("Missing physics", item 6).
TARGET_TOP1_HIGH = 0.90  # at c >= 7
TARGET_TOP1_MID = 0.70  # at c = 5
TARGET_FDR = 0.05
TARGET_WALL_1S = 60.0  # s, diagnose on a 1 s recording
# Shape parameter that locates each effect, and its unit.
LOCATION_KEY: dict[str, tuple[str, str]] = {
    "impact": ("impact_t0", "s"),
    "position_bump": ("bump_x0", "m"),
    "extra_harmonic": ("harm_f", "Hz"),
    "position_periodic": ("per_lambda", "m"),
    "stribeck": ("stribeck_vst", "m/s"),
    "presliding_hysteresis": ("presl_eps", "m"),
}
# Amplitude of each effect: one parameter, or the modulus of a (sin, cos) pair.
AMPLITUDE_KEYS: dict[str, tuple[str, ...]] = {
    "stribeck": ("stribeck_A",),
    "stribeck_shape": ("shape_ddelta",),
    "asymmetric_friction": ("asym_dFc",),
    "quadratic_drag": ("drag_Cd",),
    "presliding_hysteresis": ("presl_A",),
    "position_bump": ("bump_A",),
    "position_periodic": ("per_A", "per_B"),
    "impact": ("impact_A",),
    "extra_harmonic": ("harm_A", "harm_B"),
    "friction_drift": ("drift_beta",),
    "mass_error": ("mass_eps",),
}


# -- running ---------------------------------------------------------------------------------
# a case counts at its level when its achieved c is within this factor range of the target
# (the secant may stop short when the signature is not linear in the amplitude or the
# amplitude bound is hit)
LEVEL_BAND = (0.75, 4.0 / 3.0)


def on_level(truth: dict[str, Any]) -> bool:
    """Whether a case with an effect reached its concealment level (:data:`LEVEL_BAND`)."""
    lo, hi = LEVEL_BAND
    return lo <= truth["concealment"] / truth["level"] <= hi


def ensure_cases(
    data: Path, specs: Sequence[gen.CaseSpec], seed: int, measure: str, log: Any
) -> list[dict[str, Any]]:
    """Manifest rows of ``specs``, generating the cases missing from ``data``."""
    config = gen.load_config(gen.CONFIG)
    rows = []
    for i, spec in enumerate(specs):
        cid = spec.case_id(seed, measure)
        rec_path, truth_path = data / f"{cid}.h5", data / "truth" / f"{cid}.json"
        if rec_path.is_file() and truth_path.is_file():
            truth = json.loads(truth_path.read_text())
            rows.append(
                {
                    "case": cid,
                    "recording": rec_path.name,
                    "truth": f"truth/{cid}.json",
                    "duration_s": spec.duration,
                    "sha256": truth["recording_sha256"],
                }
            )
            continue
        case = gen.make_case(spec, seed, config, measure=measure)
        rows.append(gen.write_case(case, data))
        log(
            f"generated [{i + 1}/{len(specs)}] {cid} ({case.truth['generate_s']:.1f} s, "
            f"c = {case.truth['concealment']:.2f})"
        )
    manifest = {
        "format": gen.FORMAT,
        "seed": seed,
        "noise_std_m": gen.DEFAULT_NOISE_STD,
        "rate_hz": gen.RATE,
        "substeps": gen.SUBSTEPS,
        "measure": measure,
        "config": str(gen.CONFIG),
        "cases": rows,
    }
    gen.write_json_atomic(data / "manifest.json", manifest)
    return rows


def run_order(specs: Sequence[gen.CaseSpec]) -> list[gen.CaseSpec]:
    """The order cases are diagnosed in: by length; within a length, replicate by replicate,
    the highest level first, effects in catalogue order, nulls spread evenly among them — so
    an interrupted run has covered every effect at the highest level, and some nulls."""
    out: list[gen.CaseSpec] = []
    for duration in sorted({s.duration for s in specs}):
        group = [s for s in specs if s.duration == duration]
        eff = sorted(
            (s for s in group if s.effect != gen.NULL),
            key=lambda s: (s.rep, -s.level, gen.EFFECTS.index(s.effect)),
        )
        nul = sorted((s for s in group if s.effect == gen.NULL), key=lambda s: s.rep)
        at = [round((i + 0.5) * len(eff) / len(nul)) for i in range(len(nul))]
        merged: list[gen.CaseSpec] = []
        for i, s in enumerate(eff):
            merged += [nul[j] for j, a in enumerate(at) if a == i]
            merged.append(s)
        merged += [nul[j] for j, a in enumerate(at) if a >= len(eff)]
        out += merged
    return out


def _judged_gain(f: dict[str, Any]) -> float | None:
    """The smallest held-out gain among the checks that judged finding ``f``
    (:func:`fricjax.diagnose.run.heldout_judged`); its primary gain where none did."""
    from fricjax.diagnose.run import heldout_judged

    judged = heldout_judged(f)
    return min(judged.values()) if judged else f.get("heldout_improvement")


def _finding_row(f: dict[str, Any]) -> dict[str, Any]:
    keys = (
        "effect",
        "test",
        "params",
        "location",
        "delta_bic",
        "p_value",
        "heldout_improvement",
        "heldout_untestable",
        "heldout_split_improvement",
        "heldout_split_untestable",
        "heldout_cv_improvement",
        "heldout_cv_folds",
        "heldout_confirmed",
        "heldout_frozen",
        "near_rest_caveat",
        "rejected_candidate",
    )
    return {k: f.get(k) for k in keys if k in f}


def diagnose_rows(
    rows: Sequence[dict[str, Any]],
    data: str,
    results: str,
    skip_existing: bool = True,
    repeat: bool = False,
    sources: str = "",
    overrides: dict[str, Any] | None = None,
) -> list[dict]:
    """Diagnose each case in this process; one JSON per case in ``results`` (cases with one
    already are skipped when ``skip_existing``; a case another live process has claimed is
    left to it). ``repeat``: the held-out check scores on the case's second recording
    (``DATA/repeat/CASE.h5``, :func:`generate.write_repeat`). ``sources``: the run's
    :func:`generate.source_digest`, checked before and after each diagnosis (workers are
    spawned and import the package from disk); each result records it. ``overrides``:
    ``[diagnose]`` keys set over the benchmark config's (:func:`parse_overrides`); each
    result records them. Never reads the truth files."""
    import fricjax.diagnose.catalogue  # noqa: F401  (registers the catalogue terms)
    from fricjax.config import load_config
    from fricjax.data.recording import read_recording
    from fricjax.diagnose.run import diagnose
    from fricjax.identify import IdentifySettings
    from fricjax.problem import build_problem

    cfg = load_config(gen.CONFIG)
    ident = IdentifySettings.from_tables(cfg.tables, source=cfg.source)
    overrides = dict(overrides or {})
    settings = diagnose_settings(overrides)
    out = []
    for row in rows:
        result_path = Path(results) / f"{row['case']}.json"
        if skip_existing and result_path.is_file():  # e.g. another run finished it
            out.append(json.loads(result_path.read_text()))
            continue
        if sources:
            gen.check_sources(sources, row["case"])
        lock = _claim(result_path.with_suffix(".lock"))
        if lock is None:  # another live process is diagnosing it
            continue
        path = Path(data) / row["recording"]
        t0 = time.perf_counter()
        try:
            problem = build_problem(read_recording(path), cfg)
            validation = (
                build_problem(read_recording(gen.repeat_path(Path(data), row["case"])), cfg)
                if repeat
                else None
            )
            diag = diagnose(
                problem,
                identify_settings=ident,
                settings=settings,
                validation=validation,
                recording=row["case"],
            )
            js = diag.as_json()
            steps = diag.selection.steps
            first_scores = (
                sorted(
                    (
                        {"effect": s.effect, "stat": s.stat, "p_value": s.p_value}
                        for s in steps[0].scores
                    ),
                    key=lambda d: d["p_value"],
                )
                if steps
                else []
            )
            result = {
                "case": row["case"],
                "duration_s": row["duration_s"],
                "wall_s": time.perf_counter() - t0,
                "findings": [_finding_row(f) for f in js["findings"]],
                "fit": js["fit"],
                "heldout": js["heldout"],
                "first_step_scores": first_scores,
                "first_step_refits": [
                    {"effect": r.effect, "delta_bic": r.delta_bic} for r in steps[0].refits
                ]
                if steps
                else [],
                "sigma_x_m": diag.extra.get("sigma_x_m"),
                "near_rest_fraction": diag.extra.get("near_rest_fraction"),
                # the output-error stage, where it ran (None: equation error decided)
                "simulation_test": js.get("simulation_test"),
                "sources": sources or gen.source_digest(),
                "diagnose_overrides": overrides,
            }
        except Exception as err:  # one broken case must not lose the others
            result = {
                "case": row["case"],
                "duration_s": row["duration_s"],
                "wall_s": time.perf_counter() - t0,
                "error": f"{type(err).__name__}: {err}",
                "traceback": traceback.format_exc(limit=6),
            }
        if sources:
            try:  # a result of two source states is not written
                gen.check_sources(sources, row["case"])
            finally:
                lock.unlink(missing_ok=True)
        gen.write_json_atomic(result_path, _plain(result))
        lock.unlink(missing_ok=True)
        print(
            f"diagnosed {row['case']} in {result['wall_s']:.1f} s: "
            f"{[f['effect'] for f in result.get('findings', [])] or result.get('error', 'none')}",
            flush=True,
        )
        out.append(_plain(result))
    return out


def _tally(digests: Iterable[str | None]) -> str:
    """``digest: count`` per source state, most frequent first (None: not recorded, a
    record or diagnosis from before they carried it)."""
    counts = Counter(d or "not recorded" for d in digests)
    return ", ".join(f"{d}: {k}" for d, k in counts.most_common()) or "–"


def _claim(lock: Path) -> Path | None:
    """Create ``lock`` (holding this pid) exclusively; None if a live process holds it. Lets
    several independent runs on one case folder share the work without doing a case twice."""
    lock.parent.mkdir(parents=True, exist_ok=True)
    for _ in range(2):
        try:
            fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            try:
                pid = int(lock.read_text() or "0")
                os.kill(pid, 0)  # raises if no such process
                return None
            except (ValueError, ProcessLookupError, FileNotFoundError):
                lock.unlink(missing_ok=True)  # stale: its process is gone
                continue
            except PermissionError:
                return None
        with os.fdopen(fd, "w") as fh:
            fh.write(str(os.getpid()))
        return lock
    return None


def _plain(obj: Any) -> Any:
    """JSON-safe copy: numpy scalars to Python, non-finite floats to None."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj


def run_all(
    rows: Sequence[dict[str, Any]],
    data: Path,
    results: Path,
    jobs: int,
    resume: bool,
    reverse: bool = False,
    per_process: int = 0,
    repeat: bool = False,
    sources: str = "",
    overrides: dict[str, Any] | None = None,
) -> dict[str, dict]:
    """Diagnose every row (skipping those already in ``results`` when ``resume``).

    Order: the rows' (:func:`run_order`). ``jobs`` > 1 deals the cases out round robin to
    worker processes (each compiles once per length). ``per_process`` > 0: consecutive
    batches of that many cases, each in a fresh worker process (``jobs`` at a time) — XLA's
    CPU backend keeps every compiled program's code, and one process diagnosing ~25 cases
    ran out of it ("LLVM ERROR: Unable to allocate section memory", twice).
    ``overrides``: as :func:`diagnose_rows`; a diagnosis in ``results`` made with other
    ones is not reused (one :class:`FricjaxError` line)."""
    results.mkdir(parents=True, exist_ok=True)
    done: dict[str, dict] = {}
    todo = []
    for row in rows:
        path = results / f"{row['case']}.json"
        if resume and path.is_file():
            done[row["case"]] = json.loads(path.read_text())
            had = done[row["case"]].get("diagnose_overrides") or {}
            if had != (overrides or {}):
                raise FricjaxError(
                    f"{path}: diagnosed with [diagnose] overrides {had or 'none'}, this run "
                    f"sets {overrides or 'none'}: use another --data folder"
                )
        else:
            todo.append(row)
    todo.sort(key=lambda r: r["duration_s"])  # stable: keeps run_order within a length
    if reverse:  # a second run on the same folder works from the other end
        todo.reverse()
    if per_process > 0 and len(todo) > per_process:
        batches = [todo[i : i + per_process] for i in range(0, len(todo), per_process)]
        with ProcessPoolExecutor(
            max_workers=max(jobs, 1), mp_context=get_context("spawn"), max_tasks_per_child=1
        ) as pool:
            futures = [
                pool.submit(
                    diagnose_rows,
                    batch,
                    str(data),
                    str(results),
                    resume,
                    repeat,
                    sources,
                    overrides,
                )
                for batch in batches
            ]
            for fut in futures:
                for res in fut.result():
                    done[res["case"]] = res
        return done
    if jobs <= 1 or len(todo) <= 1:
        for res in diagnose_rows(todo, str(data), str(results), resume, repeat, sources, overrides):
            done[res["case"]] = res
        return done
    # round robin: every worker walks the list in run order, lengths stay together
    chunks: list[list[dict]] = [todo[i::jobs] for i in range(jobs)]
    with ProcessPoolExecutor(max_workers=jobs, mp_context=get_context("spawn")) as pool:
        futures = [
            pool.submit(
                diagnose_rows, chunk, str(data), str(results), resume, repeat, sources, overrides
            )
            for chunk in chunks
            if chunk
        ]
        for fut in futures:
            for res in fut.result():
                done[res["case"]] = res
    return done


def parse_overrides(items: Sequence[str]) -> dict[str, Any]:
    """``KEY=VALUE`` strings (``--set``) as ``[diagnose]`` keys over the benchmark
    config's, each VALUE read as a TOML value (a bare word as a string) and checked by
    :meth:`DiagnoseSettings.from_dict`; a mistake is one :class:`FricjaxError` line."""
    import tomllib

    out: dict[str, Any] = {}
    for item in items:
        key, sep, text = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise FricjaxError(f"--set {item!r}: expected KEY=VALUE")
        try:
            value = tomllib.loads(f"v = {text.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = text.strip()
        out[key] = value
    diagnose_settings(out, source="--set")
    return out


def diagnose_settings(
    overrides: dict[str, Any] | None = None, source: str = ""
) -> DiagnoseSettings:
    """The benchmark config's :class:`DiagnoseSettings` with ``overrides`` set over its
    ``[diagnose]`` table (errors name ``source``, the config file by default)."""
    from fricjax.config import load_config

    cfg = load_config(gen.CONFIG)
    return DiagnoseSettings.from_dict(
        {**cfg.table("diagnose"), **(overrides or {})}, source=source or cfg.source
    )


# -- scoring ---------------------------------------------------------------------------------
def first_effect(result: dict[str, Any]) -> str:
    if "error" in result:
        return "error"
    findings = result.get("findings") or []
    return findings[0]["effect"] if findings else gen.NULL


def amplitude(effect: str, params: dict[str, Any]) -> float | None:
    keys = AMPLITUDE_KEYS.get(effect, ())
    if not keys or any(k not in params or params[k] is None for k in keys):
        return None
    if len(keys) == 1:
        return float(params[keys[0]])
    return float(math.hypot(*(float(params[k]) for k in keys)))


def score_case(truth: dict[str, Any], result: dict[str, Any]) -> dict[str, Any]:
    """One case's scores (plain dict)."""
    effect = truth["effect"]
    findings = result.get("findings") or []
    names = [f["effect"] for f in findings]
    first = first_effect(result)
    row: dict[str, Any] = {
        "case": truth["case"],
        "effect": effect,
        "level": truth["level"],
        "c": truth["concealment"],  # of the measure the amplitude was scaled to
        "c_out": truth.get("concealment_output", truth["concealment"]),
        "reached": truth.get("reached", True),
        "raw_rms": truth.get("raw_rms_over_sigma", 0.0),
        "absorbed": truth.get("absorbed_fraction"),
        "c_refit": truth.get("concealment_refit", 0.0),
        "c_ee_refit": truth.get("concealment_ee_refit"),
        "on_level": effect == gen.NULL or on_level(truth),
        "duration": truth["duration_s"],
        "first": first,
        "names": names,
        "truth_params": ", ".join(f"{k}={v:.3g}" for k, v in sorted(truth["params"].items())),
        "detected": bool(findings),
        "top1": first == effect,
        "named_any": effect in names,
        "error": result.get("error"),
        "wall_s": result.get("wall_s"),
        "near_rest": result.get("near_rest_fraction"),
        # every candidate's p-value at the first step (before any term is added): on a null
        # record these must be uniform (null_calibration_section)
        "step1_p": {s["effect"]: s["p_value"] for s in result.get("first_step_scores") or []},
    }
    fit = result.get("fit") or {}
    sigma_hat = result.get("sigma_x_m")
    if fit and sigma_hat and fit["before"].get("rss_whitened"):
        # excess of the base fit's whitened RSS over pure noise, in σ_x: what the
        # diagnosis was left with (rss/σ̂² = dof − d, so rss/σ² − rss/σ̂² ≈ ‖excess‖²/σ²)
        rss = float(fit["before"]["rss_whitened"])
        sigma = float(truth["noise_std_m"])
        row["c_fit"] = math.sqrt(max(rss / sigma**2 - rss / float(sigma_hat) ** 2, 0.0))
        row["sigma_ratio"] = float(sigma_hat) / sigma
    if fit:
        row["ems_before"] = fit["before"]["ems"]
        row["ems_after"] = fit["after"]["ems"]
        row["sim_before"] = fit["before"].get("simulation_rms_m")
        row["sim_after"] = fit["after"].get("simulation_rms_m")
    named = [f for f in findings if f["effect"] != UNEXPLAINED]
    row["named_findings"] = len(named)
    # the gain of the check that decided (the smallest of those that judged: a record's
    # split that could fit only the term's parameters is reported but does not judge)
    row["heldout"] = [_judged_gain(f) for f in named]
    # confirmed: a gain in every held-out check that reaches the finding's place (the
    # record's last part, and the second recording under --repeat); None: not reported
    row["confirmed"] = [f.get("heldout_confirmed") for f in named]
    # the cross-validation's gain, where no time split reached the finding (None otherwise)
    row["cv"] = [f.get("heldout_cv_improvement") for f in named]
    # candidates the held-out check did not confirm (reported unexplained at their place)
    row["rejected"] = [
        f["rejected_candidate"]["effect"] for f in findings if f.get("rejected_candidate")
    ]
    if effect in names:
        found = findings[names.index(effect)]
        params = found.get("params") or {}
        if effect in LOCATION_KEY:
            key, unit = LOCATION_KEY[effect]
            if key in params and params[key] is not None:
                row["loc_key"], row["loc_unit"] = key, unit
                row["loc_true"] = float(truth["params"][key])
                row["loc_found"] = float(params[key])
                row["loc_err"] = abs(row["loc_found"] - row["loc_true"])
        a_true, a_found = amplitude(effect, truth["params"]), amplitude(effect, params)
        if a_true and a_found is not None:
            row["amp_ratio"] = a_found / a_true
    if first != gen.NULL and findings:
        row["first_delta_bic"] = findings[0].get("delta_bic")
        row["first_p"] = findings[0].get("p_value")
    return row


@functools.lru_cache(maxsize=1)
def _kept_problem(path: Path) -> Any:
    """The recording at ``path`` bound to the benchmark config, undecimated as the diagnosis
    sees it (one build per case for the truth-free checks below)."""
    from fricjax.config import load_config
    from fricjax.data.recording import read_recording
    from fricjax.diagnose.run import _undecimated
    from fricjax.problem import build_problem

    return _undecimated(build_problem(read_recording(path), load_config(gen.CONFIG)))


def near_rest_fraction(path: Path) -> float:
    """Share of the samples at or near rest (``|v| < 4σ_v``, the diagnosis' reversal mask)
    of the recording at ``path``, with σ_x from its third difference instead of the
    diagnosis' fitted residual: for diagnoses written before they reported it."""
    from fricjax.data.recording import read_recording
    from fricjax.diagnose.whiten import reversal_mask
    from fricjax.output_error import noise_scale

    sigma = noise_scale(np.asarray(read_recording(path).x))
    return float(np.mean(reversal_mask(_kept_problem(path), sigma)))


def untestable(result: dict[str, Any], path: Path) -> list[str]:
    """For each named finding of ``result``, why the held-out part of the recording at
    ``path`` cannot judge it (:func:`fricjax.diagnose.run.untested_place`), or ``""``;
    computed here for every diagnosis, whether or not it reported the field itself."""
    from fricjax.config import load_config
    from fricjax.diagnose.run import DiagnoseSettings, heldout_parts, untested_place

    cfg = load_config(gen.CONFIG)
    fraction = DiagnoseSettings.from_dict(dict(cfg.table("diagnose")), source=cfg.source).heldout
    _, test = heldout_parts(_kept_problem(path), fraction)
    named = [f for f in result.get("findings") or [] if f["effect"] != UNEXPLAINED]
    return [untested_place(f.get("location") or {}, test) for f in named]


def equation_error_concealment(truth: dict[str, Any], path: Path) -> float | None:
    """``c_ee`` of the hidden effect on the recording at ``path``
    (:class:`generate.EquationErrorView`: what the diagnosis' score test can see, in noise
    standard deviations). Scoring only: reads the truth."""
    from fricjax.config import load_config
    from fricjax.data.recording import read_recording
    from fricjax.problem import build_problem

    if truth["effect"] == gen.NULL:
        return 0.0
    if truth.get("concealment_ee") is not None:
        return float(truth["concealment_ee"])
    problem = build_problem(read_recording(path), load_config(gen.CONFIG))
    view = gen.EquationErrorView(problem, truth["base"], truth["noise_std_m"])
    return view.concealment(truth["effect"], truth["params"])


# a term pays on the recording when it lowers BIC by more than this (the diagnosis' own
# ``min_delta_bic``)
ORACLE_DBIC = 10.0


def oracle_gain(truth: dict[str, Any], path: Path) -> dict[str, float] | None:
    """What the TRUE term buys on the noisy recording at ``path``, in the diagnosis' metric.

    Base and base + the hidden catalogue term at its true shape are both GLS-fitted
    (:func:`fricjax.diagnose.select.gls_fit`), the samples at rest marked and the whitener
    built at the true base parameters as the diagnosis does at its own fit:
    ``oracle_lr = (RSS_w(base) − RSS_w(base + term))/σ_x²`` and ``oracle_dbic`` its BIC
    gain. Where ``oracle_dbic`` ≤ ``ORACLE_DBIC`` no fit-based namer can name the effect on
    this recording, whatever c says: c is measured on the noise-free record, where the
    regressors (v, a) carry no noise. Scoring only: reads the truth.

    Two things keep it from overstating what the record holds:

    * the base is fitted from the truth AND from where the term's fit ended, the lower kept
      (LM from the truth alone can stop short of the base's minimum, and the term then
      takes credit for the base's unfinished descent; the diagnosis' simulation test keeps
      the same rule since b439251);
    * the BIC is the one the diagnosis' selection uses on that record: with a known
      variance, ``RSS_w/σ_x² + k·ln M``, where the whitened residual leaves no more
      dimensions than the base has parameters (short records; ``oracle_known`` is then
      1), else the profile form ``M·ln(RSS_w/M) + k·ln M``, which on ~30 whitened
      dimensions with 26 base parameters turns a likelihood ratio of 20 into a BIC gain of
      40 or more.
    """
    from fricjax.diagnose.locate import compiled_jacfwd, default_whitener
    from fricjax.diagnose.run import with_rest
    from fricjax.diagnose.select import (
        base_range,
        bic,
        bic_known,
        gls_fit,
        variance_known,
        whitened_residual,
    )

    effect = truth["effect"]
    if effect == gen.NULL:
        return None
    problem = _kept_problem(path)
    theta0 = problem.theta(truth["base"])
    problem = with_rest(problem, theta0)
    model, spec = problem.model, problem.spec
    wh = default_whitener(problem, theta0)
    theta_b, rss_b = gls_fit(problem, model, spec, theta0, wh)
    ext, start = gen.with_true_term(problem, effect, truth["base"], truth["params"])
    named = {**truth["base"], **truth["params"]}
    # also from the base's own optimum, with the term at its true size and at its null
    # (LM never ends above its start, so the nested fit is never worse than the base)
    polished = dict(zip(spec.free_names, theta_b, strict=True))
    nulls = {
        q.name: q.null for q in ext.spec.free if q.name not in polished and np.isfinite(q.null)
    }
    starts = [
        ext.spec.flatten({k: v for k, v in {**named, **polished, **extra}.items() if k in ext.spec})
        for extra in ({}, nulls)
    ]
    theta_e, rss_e = min(
        (gls_fit(ext, ext.model, ext.spec, th, wh) for th in (start, *starts)),
        key=lambda f: f[1],
    )
    ended = dict(zip(ext.spec.free_names, theta_e, strict=True))
    theta_b2, rss_b2 = gls_fit(
        problem, model, spec, spec.flatten({k: v for k, v in ended.items() if k in spec}), wh
    )
    if rss_b2 < rss_b:
        theta_b, rss_b = theta_b2, rss_b2
    sigma2 = float(truth["noise_std_m"]) ** 2
    # the selection's own rule (select.forward_select), at the base's optimum
    j_w = np.asarray(compiled_jacfwd(whitened_residual(problem, model, spec, wh), theta_b))
    known = variance_known(max(wh.dof - base_range(j_w).shape[1], 1), spec.n_free)
    if known:
        dbic = bic_known(rss_b, wh.dof, spec.n_free, sigma2) - bic_known(
            rss_e, wh.dof, ext.spec.n_free, sigma2
        )
    else:
        dbic = bic(rss_b, wh.dof, spec.n_free) - bic(rss_e, wh.dof, ext.spec.n_free)
    return {
        "oracle_lr": (rss_b - rss_e) / sigma2,
        "oracle_dbic": dbic,
        "oracle_known": float(known),
    }


def oracle_section(
    eff_rows: Sequence[dict[str, Any]], levels: Sequence[float], bar: float = ORACLE_DBIC
) -> list[str]:
    """Report lines: per effect and level, how many cases' true term pays on the noisy
    recording (:func:`oracle_gain`: BIC gain above ``bar``, the bar the diagnoses ran with)
    and top-1 among those."""
    rows = [r for r in eff_rows if r.get("oracle_dbic") is not None]
    if not rows:
        return []

    def cell(rs: list[dict[str, Any]]) -> str:
        if not rs:
            return "–"
        pays = [r for r in rs if r["oracle_dbic"] > bar]
        med = float(np.median([r["oracle_dbic"] for r in rs]))
        return f"{len(pays)}/{len(rs)} · {sum(r['top1'] for r in pays)}/{len(pays)} · {med:.3g}"

    effects = sorted({r["effect"] for r in rows}, key=lambda e: gen.EFFECTS.index(e))
    body = [
        [e, *(cell([r for r in rows if r["effect"] == e and r["level"] == lv]) for lv in levels)]
        for e in effects
    ]
    body.append(
        ["**all effects**", *(cell([r for r in rows if r["level"] == lv]) for lv in levels)]
    )
    return [
        "## Does the true term pay on the noisy recording? (oracle, scoring only)",
        "",
        "For each case at its level: base and base + the hidden term at its true shape, both "
        "GLS-fitted on the noisy recording in the diagnosis' metric (samples at rest marked, "
        "whitener at the true base; `score.oracle_gain`), the term from the truth and from the "
        "base's optimum, the base from the truth and from where the term's fit ended (the "
        "lower kept: a base fit that stops short would credit the term with its unfinished "
        "descent). It pays when it lowers BIC by more than "
        f"{bar:g} (the diagnosis' own bar), the BIC in the form the selection uses on "
        "that record: a known variance, LR − k·ln M, where the base leaves no more whitened "
        "dimensions than it has parameters (the short records), else M·ln(RSS_w/M) + k·ln M. "
        "Cells: cases where it "
        "pays / cases · top-1 among those · median BIC gain. Where the true term does not pay, "
        "no namer that judges by the fit can name it on that recording, whatever c says (c is "
        "measured on the noise-free record). Not a target figure: the targets above count "
        "every case at its level.",
        "",
        _table(["effect", *(f"c = {lv:g}" for lv in levels)], body),
        "",
    ]


# record lengths up to this are "short": their residual leaves no more degrees of freedom
# than the base has parameters, so the friction-law terms keep the score test there
SHORT_S = 0.5


# the candidates whose p-value comes from their refit's likelihood ratio on long records
BY_REFIT = frozenset(c.effect for c in CATALOGUE if c.by_refit)


def _test_kind(effect: str, duration: float) -> str:
    """Which test gave ``effect``'s p-value on a record of ``duration`` s (select module)."""
    return "likelihood ratio" if effect in BY_REFIT and duration > SHORT_S else "score"


def _span(durations: set[float]) -> str:
    """``0.272 s`` or ``1-2 s``: the record lengths of a group."""
    lo, hi = min(durations), max(durations)
    return f"{lo:g} s" if lo == hi else f"{lo:g}-{hi:g} s"


def null_calibration(null_rows: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per test kind and record length group: the first step's p-values of every candidate
    on the null recordings, where each must be uniform on (0, 1)."""
    from scipy import stats

    groups: dict[tuple[str, bool], list[float]] = {}
    lengths: dict[bool, set[float]] = {}
    for r in null_rows:
        short = r["duration"] <= SHORT_S
        lengths.setdefault(short, set()).add(float(r["duration"]))
        for effect, p in (r.get("step1_p") or {}).items():
            groups.setdefault((_test_kind(effect, r["duration"]), short), []).append(float(p))
    out = []
    for (kind, short), ps in sorted(groups.items(), key=lambda g: (g[0][0], not g[0][1])):
        v = np.asarray(ps)
        out.append(
            {
                "kind": kind,
                "span": _span(lengths[short]),
                "p": np.sort(v),
                "n": v.size,
                "median": float(np.median(v)),
                "below_05": float(np.mean(v < 0.05)),
                "below_01": float(np.mean(v < 0.01)),
                "ks_p": float(stats.kstest(v, "uniform").pvalue),
            }
        )
    return out


def null_calibration_section(null_rows: Sequence[dict[str, Any]]) -> list[str]:
    """Report lines: are the p-values of the tests uniform on the null recordings?"""
    cal = null_calibration(null_rows)
    if not cal:
        return []
    rows = [
        [
            c["kind"],
            c["span"],
            c["n"],
            _g(c["median"], ".2f"),
            f"{100 * c['below_05']:.1f} %",
            f"{100 * c['below_01']:.1f} %",
            _g(c["ks_p"], ".2g"),
        ]
        for c in cal
    ]
    return [
        "## Calibration of the tests on the null recordings",
        "",
        "Every candidate's p-value at the first step of each null recording (nothing hidden, "
        "so each should be uniform on (0, 1): median 0.5, 5 % below 0.05, 1 % below 0.01); "
        "the friction-law terms are judged by the likelihood ratio of their refit on records "
        "that leave more residual degrees of freedom than the base has parameters, by their "
        "score elsewhere. The candidates of one record share its residual, so the KS test "
        "(against the uniform law) overstates the evidence; the shares below 0.05 and 0.01 "
        "are what the selection's threshold (α / number of candidates) meets. What keeps a "
        "p-value below the threshold from becoming a false discovery is the rest of the "
        "rule: ΔBIC > 10 and the held-out check.",
        "",
        _table(["test", "records", "p-values", "median", "< 0.05", "< 0.01", "KS p"], rows),
        "",
    ]


def _pct(k: int, n: int) -> str:
    return f"{k}/{n} ({100.0 * k / n:.0f} %)" if n else "–"


def _rates(
    rows: Sequence[dict[str, Any]],
    keys: Sequence[str] = ("detected", "top1", "named_any"),
    pct: bool = True,
) -> str:
    """``k/n`` (with percent when ``pct``) of each boolean key over ``rows``, " · "-joined."""
    n = len(rows)
    if not n:
        return "–"
    counts = [sum(r[k] for r in rows) for k in keys]
    return " · ".join(_pct(k, n) if pct else f"{k}/{n}" for k in counts)


def _g(v: Any, fmt: str = ".3g") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    return format(v, fmt)


def _table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def machine() -> str:
    model = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    load = os.getloadavg() if hasattr(os, "getloadavg") else (math.nan,) * 3
    return f"{model}, {os.cpu_count()} cores, load average {load[0]:.1f} (1 min)"


def git_state() -> tuple[str, str]:
    def run(*args: str) -> str:
        try:
            return subprocess.run(
                ["git", *args], cwd=ROOT, capture_output=True, text=True, check=True
            ).stdout.strip()
        except (OSError, subprocess.CalledProcessError):
            return "(unavailable)"

    return gen.git_commit() or "(unavailable)", run("status", "--short", "fricjax", "configs")


def report(
    scored: list[dict[str, Any]],
    out: Path,
    header: dict[str, Any],
    measure: str = "output",
    bar: float = ORACLE_DBIC,
) -> str:
    """Markdown report + PNGs next to ``out``; returns the Markdown. ``bar``: the
    ``min_delta_bic`` the diagnoses ran with, by which the oracle judges the true term."""
    effects = [e for e in gen.EFFECTS if any(r["effect"] == e for r in scored)]
    levels = sorted({r["level"] for r in scored if r["effect"] != gen.NULL})
    all_eff = [r for r in scored if r["effect"] != gen.NULL]
    # level statistics count only cases whose achieved c is near the target (on_level)
    eff_rows = [r for r in all_eff if r["on_level"]]
    off = [r for r in all_eff if not r["on_level"]]
    nulls = [r for r in scored if r["effect"] == gen.NULL]
    scaled = (
        "the part of its equation-error signature that the base model cannot absorb, in the "
        "diagnosis' whitened space, is c_ee noise standard deviations: c_ee = "
        "‖(I − P_{J_w})·W·δr‖/σ_x (δr the effect's change of m·a − F* at the truth, W the "
        "diagnosis' whitener, J_w the whitened base Jacobian; c_ee² is the noncentrality of "
        "the score test at the true shape). The levels below are c_ee levels; the output-error "
        "c of the same cases is reported beside them"
        if measure == "equation"
        else "the part of its equation-error signature that the base model cannot absorb "
        "when its 26 parameters are actually refitted (bounded least squares in the "
        "diagnosis' whitened metric, noise-free record, the stick/slip rule on the samples "
        "at rest as the diagnosis applies it; generator format v2) is c noise standard "
        "deviations: "
        "c = min_θ ‖W·(r_e(θ) − r_floor)‖/σ_x (generate.refit_concealment); the linearised "
        "c_ee of the same cases is reported beside them"
        if measure == "refit"
        else "the part of its displacement signature the base model cannot absorb is c noise "
        "standard deviations: c = ‖(I − P_J)·s‖/σ_x, s = x_effect − x_base, J = "
        "∂x_sim/∂θ_base (26 parameters). The levels below are c levels; the equation-error "
        "c_ee (what the diagnosis' score test sees) of the same cases is reported beside them"
    )
    lines = [
        "# Diagnosis on concealed effects",
        "",
        "Each recording hides ONE catalogue effect in the paper-twin plant (parameters varied "
        "±15 %, phases ±0.2 rad, ω ±5 %; σ_x = 24 µm, 1 kHz), its amplitude scaled so that "
        + scaled
        + ". `rms/σ` = rms(x_effect − x_base)/σ_x: below 1, nothing shows by eye in x. "
        "Generator: `benchmarks/concealed/generate.py`; scorer: `benchmarks/concealed/score.py`. "
        "Diagnosis never reads the truth (separate `truth/CASE.json` files, opaque case ids).",
        "",
        "## What ran",
        "",
        _table(["item", "value"], [[k, v] for k, v in header.items()]),
        "",
    ]

    # targets ------------------------------------------------------------------------------
    def top1(rows: list[dict]) -> tuple[int, int]:
        return sum(r["top1"] for r in rows), len(rows)

    hi = [r for r in eff_rows if r["level"] >= 7]
    mid = [r for r in eff_rows if r["level"] == 5]
    fd = sum(r["detected"] for r in nulls)
    named_all = [h for r in all_eff + nulls for h in r["heldout"]]
    with_gain = sum(
        (c if c is not None else h is not None and h > 0)
        for r in all_eff + nulls
        for h, c in zip(r["heldout"], r.get("confirmed") or [None] * len(r["heldout"]), strict=True)
    )
    walls_1s = [r["wall_s"] for r in scored if abs(r["duration"] - 1.0) < 1e-9 and r["wall_s"]]
    med_1s = float(np.median(walls_1s)) if walls_1s else math.nan

    def verdict(ok: bool | None) -> str:
        return "–" if ok is None else ("met" if ok else "**not met**")

    k_hi, n_hi = top1(hi)
    k_mid, n_mid = top1(mid)
    lines += [
        "## Targets",
        "",
        _table(
            ["target", "measured", "verdict"],
            [
                [
                    "top-1 naming ≥ 90 % at c ≥ 7",
                    _pct(k_hi, n_hi),
                    verdict(k_hi / n_hi >= TARGET_TOP1_HIGH if n_hi else None),
                ],
                [
                    "top-1 naming ≥ 70 % at c = 5",
                    _pct(k_mid, n_mid),
                    verdict(k_mid / n_mid >= TARGET_TOP1_MID if n_mid else None),
                ],
                [
                    "false discoveries on nulls ≤ 5 %",
                    _pct(fd, len(nulls)),
                    verdict(fd / len(nulls) <= TARGET_FDR if nulls else None),
                ],
                [
                    "every named finding has a held-out improvement (> 0)",
                    f"{with_gain}/{len(named_all)}",
                    verdict(with_gain == len(named_all) if named_all else None),
                ],
                [
                    "diagnose on a 1 s recording < 1 min (median)",
                    f"{_g(med_1s, '.1f')} s",
                    verdict(med_1s < TARGET_WALL_1S if walls_1s else None),
                ],
            ],
        ),
        "",
    ]
    # per effect × level --------------------------------------------------------------------
    head = ["effect"] + [f"c = {lv:g}: detected / top-1 / named" for lv in levels]
    body = []
    for e in effects:
        cells = [e]
        for lv in levels:
            cells.append(
                _rates([r for r in eff_rows if r["effect"] == e and r["level"] == lv], pct=False)
            )
        body.append(cells)
    lv_cells = ["**all effects**"]
    for lv in levels:
        lv_cells.append(_rates([r for r in eff_rows if r["level"] == lv]))
    body.append(lv_cells)
    lines += [
        "## Detection and naming per effect and concealment",
        "",
        "detected: any finding; top-1: the first finding names the hidden effect; named: the "
        "hidden effect is among the findings. Only cases whose achieved c is within "
        "[0.75, 1.33]× the target count here and in the targets above.",
        "",
        _table(head, body),
        "",
    ]
    lines += oracle_section(eff_rows, levels, bar)
    durations = sorted({r["duration"] for r in scored})
    if len(durations) > 1:
        len_body = []
        for d in durations:
            cells = [f"{d:g} s"]
            for lv in levels:
                rs = [r for r in eff_rows if r["duration"] == d and r["level"] == lv]
                cells.append(_rates(rs, keys=("detected", "top1")))
            ns = [r for r in nulls if r["duration"] == d]
            cells.append(_pct(sum(r["detected"] for r in ns), len(ns)) if ns else "–")
            len_body.append(cells)
        lines += [
            "## Per record length",
            "",
            "detected · top-1 over all effects at their level, and false discoveries on the "
            "nulls of that length.",
            "",
            _table(
                ["length"] + [f"c = {lv:g}" for lv in levels] + ["nulls: false discoveries"],
                len_body,
            ),
            "",
        ]
    # near rest ----------------------------------------------------------------------------
    rest_rows = [r for r in eff_rows if r.get("near_rest") is not None]
    if rest_rows:
        laws = set(NEAR_REST_LAWS)
        body = []
        for lo, hi_ in ((0.0, 0.1), (0.1, 0.2), (0.2, 1.01)):
            sub = [r for r in rest_rows if lo <= r["near_rest"] < hi_]
            law_named = [r for r in sub if r["first"] in laws]
            body.append(
                [
                    f"[{lo:g}, {min(hi_, 1):g})",
                    len(sub),
                    _pct(sum(r["detected"] for r in sub), len(sub)),
                    _pct(sum(r["top1"] for r in sub), len(sub)),
                    f"{sum(r['top1'] for r in law_named)}/{len(law_named)}",
                    f"{sum(r['effect'] in laws for r in sub)}",
                ]
            )
        lines += [
            "## Naming against the share of samples near rest",
            "",
            "Near-rest fraction: samples with |v| < 4σ_v (the diagnosis' reversal mask; where "
            "a diagnosis predates that figure, recomputed from the recording with σ_x from its "
            "third difference). The plant sticks there, and the equation error is biased at "
            "the breakaways; a friction-law name given at a fraction >= "
            f"{NEAR_REST_CAVEAT:g} carries a caveat in diagnosis.json. Effects at their level, "
            "all lengths.",
            "",
            _table(
                [
                    "near-rest fraction",
                    "cases",
                    "detected",
                    "top-1",
                    "friction-law first findings correct",
                    "hidden friction-law effects",
                ],
                body,
            ),
            "",
        ]
    if off:
        lines += [
            "Cases NOT at their level (the target c could not be reached: the base model "
            "absorbs the effect, or the amplitude bound was hit; scored in the confusion "
            "matrix only): "
            + "; ".join(
                f"{r['case']} {r['effect']} target {r['level']:g} → c = {r['c']:.3g} "
                f"(first finding: {r['first']})"
                for r in off
            )
            + ".",
            "",
        ]
    # confusion ----------------------------------------------------------------------------
    truth_labels = effects + ([gen.NULL] if nulls else [])
    found_labels = [*gen.EFFECTS, UNEXPLAINED, gen.NULL]
    if any(r["first"] == "error" for r in scored):
        found_labels.append("error")
    counts = Counter((r["effect"], r["first"]) for r in scored)
    short = {e: e.replace("_", " ") for e in found_labels}
    lines += [
        "## Confusion matrix (hidden effect × first finding)",
        "",
        _table(
            ["hidden \\ first"] + [short[f] for f in found_labels],
            [[t] + [counts.get((t, f), 0) or "·" for f in found_labels] for t in truth_labels],
        ),
        "",
    ]
    # nulls --------------------------------------------------------------------------------
    if nulls:
        lines += [
            "## Null recordings",
            "",
            f"False discoveries: {_pct(fd, len(nulls))}. Findings on nulls: "
            + (
                ", ".join(
                    f"{k} ×{v}" for k, v in Counter(n for r in nulls for n in r["names"]).items()
                )
                or "none"
            )
            + ".",
            "",
        ]
        lines += null_calibration_section(nulls)
    # location and amplitude -----------------------------------------------------------------
    loc_rows = []
    for e in effects:
        rs = [r for r in eff_rows if r["effect"] == e and "loc_err" in r]
        amps = [r["amp_ratio"] for r in eff_rows if r["effect"] == e and "amp_ratio" in r]
        if not rs and not amps:
            loc_rows.append([e, "–", "–", "–", "–", "–"])
            continue
        if rs:
            key, unit = rs[0]["loc_key"], rs[0]["loc_unit"]
            errs = np.array([r["loc_err"] for r in rs])
            rel = np.array([r["loc_err"] / abs(r["loc_true"]) for r in rs])
            loc = [
                f"{key} [{unit}]",
                str(len(rs)),
                _g(float(np.median(errs))),
                _g(float(np.max(errs))),
                f"{100 * float(np.median(rel)):.2g} %",
            ]
        else:
            loc = ["(no shape parameter)", "–", "–", "–", "–"]
        ratio = f"{_g(float(np.median(amps)))} ({len(amps)})" if amps else "–"
        loc_rows.append([e, *loc[:1], loc[1], loc[2], loc[3], f"{loc[4]}; amplitude ratio {ratio}"])
    lines += [
        "## Location and amplitude of the named effect",
        "",
        "For cases where the hidden effect is among the findings: |found − true| of its shape "
        "parameter, and the median ratio found/true of its amplitude (number of cases).",
        "",
        _table(
            [
                "effect",
                "parameter",
                "n",
                "median error",
                "max error",
                "median rel. error; amplitude",
            ],
            loc_rows,
        ),
        "",
    ]
    # fit ----------------------------------------------------------------------------------
    ratio = [r["ems_after"] / r["ems_before"] for r in scored if r.get("ems_before")]
    eff_rows = all_eff  # from here on: every case
    held = [h for h in named_all if h is not None]
    lines += [
        "## Fit improvement",
        "",
        _table(
            ["figure", "value"],
            [
                [
                    "cases diagnosed without error",
                    f"{sum(r['error'] is None for r in scored)}/{len(scored)}",
                ],
                [
                    "median EMS after/before (all cases)",
                    _g(float(np.median(ratio))) if ratio else "–",
                ],
                [
                    "median EMS after/before (cases with a named finding)",
                    _g(
                        float(
                            np.median(
                                [
                                    r["ems_after"] / r["ems_before"]
                                    for r in scored
                                    if r.get("ems_before") and r["named_findings"]
                                ]
                            )
                        )
                    )
                    if any(r["named_findings"] and r.get("ems_before") for r in scored)
                    else "–",
                ],
                ["named findings", str(len(named_all))],
                ["  confirmed: a gain in every held-out check that reaches it", f"{with_gain}"],
                [
                    "  judged by cross-validation over the whitened coordinates (no time "
                    "split reaches their place, or the split could fit only the term's own "
                    "parameters): all · confirmed",
                    " · ".join(
                        str(n)
                        for n in (
                            sum(c is not None for r in scored for c in r.get("cv") or []),
                            sum(c is not None and c > 0 for r in scored for c in r.get("cv") or []),
                        )
                    ),
                ],
                [
                    "  not judged: the held-out part never reaches their place (their "
                    "gain there is only the base's extrapolation) and no cross-validation ran",
                    str(
                        sum(
                            bool(u) and c is None
                            for r in scored
                            for u, c in zip(
                                r.get("untestable") or [],
                                r.get("cv") or [None] * len(r.get("untestable") or []),
                                strict=True,
                            )
                        )
                    ),
                ],
                ["  median held-out improvement", _g(float(np.median(held))) if held else "–"],
                [
                    "candidates the held-out check rejected (reported unexplained): "
                    "all · the hidden effect · on nulls",
                    " · ".join(
                        str(n)
                        for n in (
                            sum(len(r.get("rejected", [])) for r in scored),
                            sum(r["effect"] in r.get("rejected", []) for r in scored),
                            sum(
                                len(r.get("rejected", []))
                                for r in scored
                                if r["effect"] == gen.NULL
                            ),
                        )
                    ),
                ],
            ],
        ),
        "",
    ]
    # wall time ----------------------------------------------------------------------------
    wt_rows = []
    for d in sorted({r["duration"] for r in scored}):
        ws = [r["wall_s"] for r in scored if r["duration"] == d and r["wall_s"] is not None]
        if ws:
            wt_rows.append(
                [
                    f"{d:g} s",
                    len(ws),
                    _g(float(np.median(ws)), ".1f"),
                    _g(ws[0], ".1f"),
                    _g(float(np.max(ws)), ".1f"),
                ]
            )
    lines += [
        "## Diagnose wall time per case",
        "",
        _table(["length", "cases", "median [s]", "first case (compiles) [s]", "max [s]"], wt_rows),
        "",
    ]
    # concealment as generated -------------------------------------------------------------
    gen_rows = []
    for e in effects:
        for lv in levels:
            rs = [r for r in eff_rows if r["effect"] == e and r["level"] == lv]
            if not rs:
                continue
            gen_rows.append(
                [
                    e,
                    f"{lv:g}",
                    _g(float(np.median([r["c_out"] for r in rs])), ".3g"),
                    _g(float(np.median([r["c_refit"] for r in rs])), ".3g"),
                    _g(
                        float(np.median([r["c_ee"] for r in rs]))
                        if all(r.get("c_ee") is not None for r in rs)
                        else None,
                        ".3g",
                    ),
                    _g(
                        float(np.median([r["c_ee_refit"] for r in rs]))
                        if all(r.get("c_ee_refit") is not None for r in rs)
                        else None,
                        ".3g",
                    ),
                    _g(
                        float(np.median([r["c_fit"] for r in rs]))
                        if all(r.get("c_fit") is not None for r in rs)
                        else None,
                        ".3g",
                    ),
                    _g(float(np.max([r["raw_rms"] for r in rs])), ".3g"),
                    _g(
                        float(np.median([r["absorbed"] for r in rs if r["absorbed"] is not None])),
                        ".3f",
                    ),
                    f"{sum(not r['reached'] for r in rs)}/{len(rs)}",
                ]
            )
    lines += [
        "## Concealment as generated",
        "",
        "c (median): output-error concealment ‖(I − P_J)·s‖/σ_x; c_refit (median): "
        "‖x_effect − x_sim(θ)‖/σ_x after a crude nonlinear refit of the 26 base parameters "
        "(the equation-error absorbing step, then chord Gauss–Newton with J fixed at the "
        "truth, inside the config's box) — an upper bound on what the base cannot absorb in "
        "output error; ≈ c where the linear projection holds, ≫ c where the signature is far "
        "too large for it (then c is not trustworthy, and neither is c_refit as an estimate); "
        "max rms(s)/σ_x; fraction of ‖s‖² absorbed by span J (median); cases whose target "
        "was not reached within 1 %. "
        "c_ee (median): what the diagnosis' score test can see, ‖(I − P_{J_w})·W·δr‖/σ_x with "
        "δr the effect's change of the equation-error residual at the truth, W the "
        "diagnosis' whitener, J_w the whitened base Jacobian (its square is the score test's "
        "noncentrality). c_ee,refit (median): the same norm after the base's 26 parameters are "
        "refitted in their box (bounded least squares, noise-free record; "
        "generate.refit_concealment): where it is far from c_ee the linearisation was wrong. "
        "c_fit (median): excess of the diagnosis' base fit over pure noise, "
        "√(RSS_w/σ_x² − RSS_w/σ̂²) — what the diagnosis was actually left with.",
        "",
        _table(
            [
                "effect",
                "target level",
                "c",
                "c_refit",
                "c_ee",
                "c_ee,refit",
                "c_fit",
                "max rms(s)/σ_x",
                "absorbed",
                "not reached",
            ],
            gen_rows,
        ),
        "",
    ]
    # per case -----------------------------------------------------------------------------
    case_rows = [
        [
            r["case"],
            r["effect"],
            r["truth_params"] or "–",
            f"{r['level']:g}",
            _g(r["c_out"], ".3g"),
            _g(r["c_refit"], ".3g"),
            _g(r.get("c_ee"), ".3g"),
            _g(r.get("c_ee_refit"), ".3g"),
            _g(r.get("c_fit"), ".3g"),
            _g(r.get("sigma_ratio"), ".2f"),
            _g(r["raw_rms"], ".3g"),
            ", ".join(r["names"]) or ("error" if r["error"] else "none"),
            _g(r.get("first_delta_bic"), ".1f"),
            _g(r.get("first_p"), ".2g"),
            ", ".join(_g(h, ".2f") for h in r["heldout"]) or "–",
            _g(r["wall_s"], ".0f"),
        ]
        for r in sorted(scored, key=lambda r: (r["duration"], r["effect"], r["level"], r["case"]))
    ]
    lines += [
        "## Every case",
        "",
        "c: output-error concealment; c_refit: its crude nonlinear upper bound; c_ee: "
        "equation-error (whitened) concealment at the truth, linearised; c_ee,refit: the same "
        "with the base refitted in its box; c_fit = √(RSS_w/σ_x² − "
        "RSS_w/σ̂²): the excess of the diagnosis' own base fit over pure noise, in σ_x (what it "
        "was left with; noisy, ±~6 near zero); σ̂/σ: the diagnosis' noise estimate over the "
        "true σ_x; ΔBIC₁, p₁: of the first finding; held-out: improvement of each named "
        "finding.",
        "",
        _table(
            [
                "case",
                "hidden",
                "hidden parameters (SI)",
                "target level",
                "c",
                "c_refit",
                "c_ee",
                "c_ee,refit",
                "c_fit",
                "σ̂/σ",
                "rms/σ",
                "findings",
                "ΔBIC₁",
                "p₁",
                "held-out",
                "wall [s]",
            ],
            case_rows,
        ),
        "",
    ]
    errors = [r for r in scored if r["error"]]
    if errors:
        lines += (
            ["## Errors", ""]
            + [f"- {r['case']} ({r['effect']}): {r['error']}" for r in errors]
            + [""]
        )
    plots = make_plots(scored, effects, levels, truth_labels, found_labels, out, measure)
    lines += ["## Plots", ""] + [f"![{p.stem}]({p.name})" for p in plots] + [""]
    text = "\n".join(lines)
    out.parent.mkdir(parents=True, exist_ok=True)
    from fricjax.io.atomic import write_text_atomic

    write_text_atomic(out, text)
    return text


def make_plots(
    scored: list[dict[str, Any]],
    effects: list[str],
    levels: list[float],
    truth_labels: list[str],
    found_labels: list[str],
    out: Path,
    measure: str = "output",
) -> list[Path]:
    """Detection / top-1 rate vs concealment per effect; confusion-matrix heat map."""
    from fricjax.report.plots import plt, save

    symbol = {
        "equation": "c_ee, equation error",
        "refit": "c_refit_ee, equation error after refit",
    }.get(measure, "c, output error")

    paths = []
    # rate per effect (rows) and level (columns), as heat maps with k/n in each cell
    fig, axes = plt.subplots(
        1, 2, figsize=(4.0 + 1.6 * len(levels), 1.5 + 0.4 * len(effects)), sharey=True
    )
    for ax, key, title in (
        (axes[0], "detected", "detection (any finding)"),
        (axes[1], "top1", "top-1 naming"),
    ):
        rate = np.full((len(effects), len(levels)), np.nan)
        for i, e in enumerate(effects):
            for j, lv in enumerate(levels):
                rs = [r for r in scored if r["effect"] == e and r["level"] == lv and r["on_level"]]
                if rs:
                    rate[i, j] = np.mean([r[key] for r in rs])
                    ax.text(
                        j,
                        i,
                        f"{sum(r[key] for r in rs)}/{len(rs)}",
                        ha="center",
                        va="center",
                        fontsize=8,
                    )
                else:
                    ax.text(j, i, "not reached", ha="center", va="center", fontsize=7)
        ax.imshow(np.ma.masked_invalid(rate), cmap="RdYlGn", vmin=0.0, vmax=1.0, aspect="auto")
        ax.set_xticks(range(len(levels)), [f"{lv:g}" for lv in levels])
        ax.set_xlabel(f"concealment level ({symbol})")
        ax.set_title(title)
    axes[0].set_yticks(range(len(effects)), effects, fontsize=8)
    fig.tight_layout()
    paths.append(save(fig, out.with_name(f"{out.stem}_detection.png")))

    # every case against what the score test can see (c_ee), outcome by marker
    pts = [r for r in scored if r["effect"] != gen.NULL and r.get("c_ee") is not None]
    if pts:
        fig, ax = plt.subplots(figsize=(10, 4.8))
        outcome = {
            "named first": ("o", "C2"),
            "named later": ("s", "C1"),
            "other finding": ("^", "C3"),
            "nothing found": ("x", "0.4"),
        }

        def kind(r: dict) -> str:
            if r["top1"]:
                return "named first"
            if r["named_any"]:
                return "named later"
            return "other finding" if r["detected"] else "nothing found"

        for label, (marker, color) in outcome.items():
            sel = [r for r in pts if kind(r) == label]
            if sel:
                ax.scatter(
                    [max(r["c_ee"], 1e-3) for r in sel],
                    [effects.index(r["effect"]) for r in sel],
                    marker=marker,
                    color=color,
                    label=label,
                    s=40,
                )
        ax.set_xscale("log")
        ax.set_yticks(range(len(effects)), effects, fontsize=8)
        ax.set_xlabel("c_ee = ‖(I − P_Jw)·W·δr‖/σ_x (what the score test sees)")
        ax.set_title("outcome of every case against its equation-error visibility")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0))
        fig.tight_layout()
        paths.append(save(fig, out.with_name(f"{out.stem}_visibility.png")))

    mat = np.zeros((len(truth_labels), len(found_labels)))
    for r in scored:
        if r["effect"] in truth_labels and r["first"] in found_labels:
            mat[truth_labels.index(r["effect"]), found_labels.index(r["first"])] += 1
    fig, ax = plt.subplots(figsize=(1.0 + 0.6 * len(found_labels), 1.2 + 0.5 * len(truth_labels)))
    ax.imshow(mat, cmap="Blues", aspect="auto")
    for i in range(mat.shape[0]):
        for j in range(mat.shape[1]):
            if mat[i, j]:
                ax.text(
                    j,
                    i,
                    f"{int(mat[i, j])}",
                    ha="center",
                    va="center",
                    fontsize=8,
                    color="white" if mat[i, j] > 0.6 * mat.max() else "black",
                )
    ax.set_xticks(range(len(found_labels)), found_labels, rotation=60, ha="right", fontsize=8)
    ax.set_yticks(range(len(truth_labels)), truth_labels, fontsize=8)
    ax.set_xlabel("first finding")
    ax.set_ylabel("hidden effect")
    ax.set_title("confusion matrix (counts)")
    fig.tight_layout()
    paths.append(save(fig, out.with_name(f"{out.stem}_confusion.png")))
    cal = null_calibration([r for r in scored if r["effect"] == gen.NULL])
    if cal:
        fig, ax = plt.subplots(figsize=(5.0, 4.5))
        lo = 0.5 / max(c["n"] for c in cal)  # the smallest expected quantile plotted
        ax.plot([lo, 1], [lo, 1], color="0.5", lw=1, label="uniform")
        for c in cal:
            expected = (np.arange(c["n"]) + 0.5) / c["n"]
            ax.loglog(
                expected, np.maximum(c["p"], lo / 10), ".", ms=4, label=f"{c['kind']}, {c['span']}"
            )
        ax.set_xlabel("expected p (uniform quantile)")
        ax.set_ylabel("observed p (first step, null recordings)")
        ax.set_title("calibration of the tests on nulls")
        ax.legend(fontsize=8)
        fig.tight_layout()
        paths.append(save(fig, out.with_name(f"{out.stem}_null_calibration.png")))
    return paths


# -- main ------------------------------------------------------------------------------------
def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", default=str(DEFAULT_DATA), help="case directory (generated)")
    ap.add_argument("--out", default=str(DEFAULT_OUT), help="Markdown report (PNGs beside)")
    ap.add_argument("--cases", default="all", help="effects, comma-separated; none = nulls")
    ap.add_argument("--levels", default=",".join(f"{v:g}" for v in gen.DEFAULT_LEVELS))
    ap.add_argument("--lengths", default=",".join(f"{v:g}" for v in gen.DEFAULT_LENGTHS))
    ap.add_argument("--reps", type=int, default=1, help="replicates per effect and level")
    ap.add_argument("--nulls", type=int, default=6, help="null cases per length")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=1, help="worker processes (1: this one)")
    ap.add_argument(
        "--per-process",
        type=int,
        default=10,
        help="cases per fresh worker process (0: all in one; XLA's code memory runs out "
        "after ~25 cases)",
    )
    ap.add_argument("--resume", action="store_true", help="reuse per-case diagnoses in DATA")
    ap.add_argument(
        "--report-only",
        action="store_true",
        help="diagnose nothing: report the per-case diagnoses already in DATA (cases "
        "without one are listed as not run)",
    )
    ap.add_argument(
        "--measure", choices=gen.MEASURES, default="output", help="concealment scaled to"
    )
    ap.add_argument("--note", default="", help="free text for the report's header")
    ap.add_argument(
        "--repeat",
        action="store_true",
        help="give each diagnosis a second recording of its case (same plant and motion, "
        "new noise) for the held-out check, instead of the last part of the record",
    )
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a [diagnose] setting over the benchmark config's (e.g. min_delta_bic=6); "
        "repeatable; recorded in each diagnosis and in the report",
    )
    ap.add_argument(
        "--reverse",
        action="store_true",
        help="diagnose in reverse order (a second run on the same DATA meets the first)",
    )
    args = ap.parse_args(argv)
    t_start = time.time()
    effects, with_nulls = gen.parse_effects(args.cases)
    specs = run_order(
        gen.case_specs(
            effects,
            gen.parse_floats(args.levels),
            gen.parse_floats(args.lengths),
            args.reps,
            args.nulls if with_nulls else 0,
        )
    )
    try:
        overrides = parse_overrides(args.set)
    except FricjaxError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    data = Path(args.data)
    load_start = machine()
    commit, status = git_state()
    sources = gen.source_digest()
    rows = ensure_cases(data, specs, args.seed, args.measure, lambda m: print(m, flush=True))
    if args.repeat:
        for row in rows:
            gen.write_repeat(data, row["case"])
    t_gen = time.time() - t_start
    if args.report_only:
        results = {}
        for row in rows:
            path = data / "diagnosis" / f"{row['case']}.json"
            if path.is_file():
                results[row["case"]] = json.loads(path.read_text())
    else:
        # with --resume, the diagnoses already in the folder are reused: say how many
        reused = (
            sum((data / "diagnosis" / f"{row['case']}.json").is_file() for row in rows)
            if args.resume
            else 0
        )
        try:
            results = run_all(
                rows,
                data,
                data / "diagnosis",
                args.jobs,
                args.resume,
                reverse=args.reverse,
                per_process=args.per_process,
                repeat=args.repeat,
                sources=sources,
                overrides=overrides,
            )
        except FricjaxError as err:
            print(f"error: {err}", file=sys.stderr)
            return 2
        for row in rows:  # cases another run on the same folder finished meanwhile
            path = data / "diagnosis" / f"{row['case']}.json"
            if row["case"] not in results and path.is_file():
                results[row["case"]] = json.loads(path.read_text())
    t_diag = time.time() - t_start - t_gen
    not_run = [row["case"] for row in rows if row["case"] not in results]
    # only now, after every diagnosis: the truth
    scored = []
    for row in rows:
        if row["case"] not in results:
            continue
        truth = json.loads((data / row["truth"]).read_text())
        scored.append(score_case(truth, results[row["case"]]))
        try:
            scored[-1]["c_ee"] = equation_error_concealment(truth, data / row["recording"])
        except Exception as err:  # scoring extra; the diagnosis API may change under us
            print(f"c_ee of {row['case']}: {type(err).__name__}: {err}", file=sys.stderr)
            scored[-1]["c_ee"] = None
        try:
            scored[-1].update(oracle_gain(truth, data / row["recording"]) or {})
        except Exception as err:  # scoring extra, as c_ee
            print(f"oracle of {row['case']}: {type(err).__name__}: {err}", file=sys.stderr)
        if scored[-1]["near_rest"] is None:
            scored[-1]["near_rest"] = near_rest_fraction(data / row["recording"])
        # a second recording judges every finding, where the record's split may not reach
        named = scored[-1]["named_findings"]
        scored[-1]["untestable"] = (
            [""] * named
            if args.repeat
            else untestable(results[row["case"]], data / row["recording"])
            if named
            else []
        )
    n_null = sum(s.effect == gen.NULL for s in specs)
    header = {
        "command": "python benchmarks/concealed/score.py " + " ".join(argv or sys.argv[1:]),
        "cases": f"{len(rows)} requested ({len(rows) - n_null} with an effect, {n_null} nulls); "
        f"{len(scored)} diagnosed"
        + (f"; NOT run (interrupted): {len(not_run)}" if not_run else ""),
        "concealment scaled to": {
            "output": "c (output error, displacement)",
            "equation": "c_ee (equation error, whitened: what the score test sees)",
            "refit": "c_refit_ee (equation error, whitened, base refitted nonlinearly)",
        }[args.measure],
        "effects": ", ".join(effects) + (", none" if with_nulls else ""),
        "levels c": args.levels,
        "lengths [s]": args.lengths,
        "replicates": str(args.reps),
        "seed": str(args.seed),
        "diagnose settings": "configs/paper.toml ([search], [anneal], [diagnose] defaults)"
        + "".join(f"; {k} = {v!r}" for k, v in overrides.items()),
        "[diagnose] overrides of the diagnoses": _tally(
            ", ".join(f"{k} = {v!r}" for k, v in (r.get("diagnose_overrides") or {}).items())
            or "none"
            for r in results.values()
        ),
        "held-out check on": (
            "a second recording of each case (same plant and motion, new noise draw; "
            "generate.write_repeat), given to diagnose as its validation recording"
            if args.repeat
            else "the last 30 % of each record (fit on the first 70 %)"
        ),
        ("machine (report assembled on)" if args.report_only else "machine"): (
            f"{load_start} at start; {machine()} at end"
        ),
        "jobs": str(args.jobs),
        "generation wall time": f"{t_gen:.0f} s",
        "diagnosis wall time": f"{t_diag:.0f} s"
        + (
            f" (resumed: {reused} of {len(rows)} diagnoses reused from the results folder)"
            if args.resume and not args.report_only
            else ""
        )
        + (" (report only)" if args.report_only else ""),
        ("git commit (at report time)" if args.report_only else "git commit"): commit,
        (
            "git status --short fricjax configs (at report time)"
            if args.report_only
            else "git status --short fricjax configs"
        ): "<br>".join(status.splitlines()) or "(clean)",
        "sources of the records (generate.source_digest: cases)": _tally(
            json.loads((data / row["truth"]).read_text()).get("sources") for row in rows
        ),
        "sources of the diagnoses (this run's: " + sources + ")": _tally(
            r.get("sources") for r in results.values()
        ),
        "date": time.strftime("%Y-%m-%d %H:%M:%S"),
    }
    if args.note:
        header["note"] = args.note
    bar = diagnose_settings(overrides).min_delta_bic
    text = report(scored, Path(args.out), header, args.measure, bar)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
