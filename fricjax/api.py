"""The Python API behind every CLI command (usable directly from a notebook)."""

from __future__ import annotations

import dataclasses
import math
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from fricjax.config import Config, load_config
from fricjax.data.noise import FLIP_KAPPA, estimate_noise, reversals
from fricjax.data.preprocess import PreprocessSettings, derivatives, noise_gains
from fricjax.data.recording import MAX_MAGNITUDE, Recording, read_recording
from fricjax.errors import FricjaxError, where
from fricjax.io.atomic import check_outputs
from fricjax.params import check_values
from fricjax.problem import Problem, build_problem, joined
from fricjax.programs import enable_compilation_cache as enable_compilation_cache
from fricjax.validate import read_params

if TYPE_CHECKING:
    from collections.abc import Callable

    from fricjax.diagnose.across import AcrossDiagnosis
    from fricjax.diagnose.run import Diagnosis
    from fricjax.diagnose.stages import StageEvent
    from fricjax.simulation import SimulationReport


#: The config a command uses without ``--config``: the seed paper's harmonic-drive model,
#: right for the bundled twin and wrong for a rig whose drive or force is recorded.
PAPER_CONFIG = Path("configs/paper.toml")


def config_or_default(recording: str | Path | Recording, config: str | Path | None) -> Path:
    """``config``, or :data:`PAPER_CONFIG` when none is given and the recording has no
    measured input; a recording with ``/u`` or ``/F`` and no config is refused (the paper
    model would ignore what was measured), naming ``fricjax init-config``."""
    if config is not None:
        return Path(config)
    rec = recording if isinstance(recording, Recording) else read_recording(recording)
    measured = [f"/{k}" for k in ("u", "F") if getattr(rec, k) is not None]
    if measured:
        name = rec.path or rec.name
        raise FricjaxError(
            f"--config: missing; {name} records {' and '.join(measured)}, which the default "
            f"{PAPER_CONFIG} (the seed paper's 26-parameter harmonic-drive model) would ignore: "
            f"write a starting config with `fricjax init-config {name} --out C.toml` and pass "
            "--config C.toml"
        )
    return PAPER_CONFIG


def scale_warnings(
    recording: str | Path, config: str | Path | Config, *, mass: float | None = None
) -> list[str]:
    """Lines saying which unit of the recording looks wrong (:mod:`fricjax.data.scale`),
    read from the record preprocessed as ``config`` says; [] when the scale is plausible."""
    from fricjax.data.scale import unit_warnings
    from fricjax.problem import input_signal

    rec, cfg, problem = load(recording, config, mass=mass)
    force = None
    if input_signal(cfg.model) == "F" or (
        input_signal(cfg.model) == "u" and rec.u_unit == cfg.axis.force
    ):
        force = problem.u  # a force on the body, filtered like m·a
    elif rec.F is not None:
        force = rec.F
    m = float(problem.spec["mass"].init) if "mass" in problem.spec else None
    return unit_warnings(problem.x, problem.v, problem.a, m, cfg.axis, force=force)


def init_config(
    recording: str | Path,
    out: str | Path,
    *,
    drive: str = "measured",
    friction: str = "coulomb,viscous",
    harmonics: int = 3,
    mass: float | None = None,
    axis: str | None = None,
    u_unit: str | None = None,
    force: bool = False,
) -> tuple[str, Path]:
    """``fricjax init-config``: a commented starting config from the recording's own scale
    (:mod:`fricjax.scaffold`), written atomically to ``out``; returns (text, path)."""
    from fricjax.scaffold import scaffold_config, write_scaffold

    check_outputs([Path(out)], {"recording": recording}, "--out")
    text = scaffold_config(
        recording,
        drive=drive,
        friction=[f for f in friction.split(",") if f.strip()],
        harmonics=harmonics,
        mass=mass,
        axis=axis,
        u_unit=u_unit,
    )
    return text, write_scaffold(out, text, force=force)


def merge_sensor_file(
    motion: str | Path,
    sensor: str | Path,
    out: str | Path,
    *,
    column: str = "F",
    as_signal: str = "F",
    u_unit: str = "",
    mass: float | None = None,
) -> tuple[Recording, Path]:
    """``fricjax merge``: a second sensor at another rate resampled onto the motion's grid
    (:mod:`fricjax.data.resample`), written as a recording."""
    from fricjax.data.recording import write_recording
    from fricjax.data.resample import merge_sensor

    check_outputs([Path(out)], {"MOTION": motion, "SENSOR": sensor}, "--out")
    rec = merge_sensor(motion, sensor, column=column, as_signal=as_signal, u_unit=u_unit, mass=mass)
    return rec, write_recording(rec, out)


def load(
    recording: str | Path | Recording, config: str | Path | Config, *, mass: float | None = None
) -> tuple[Recording, Config, Problem]:
    """Read a recording and a config and bind them into a :class:`Problem`."""
    rec = recording if isinstance(recording, Recording) else read_recording(recording, mass=mass)
    cfg = config if isinstance(config, Config) else load_config(config)
    return rec, cfg, build_problem(rec, cfg)


def inspect_recording(
    recording: str | Path,
    *,
    config: str | Path | None = None,
    mass: float | None = None,
    png: str | Path | None = None,
) -> tuple[dict[str, str], Path]:
    """Summary of a recording and a PNG of x, v, a and m·a (preprocessed as configured)."""
    from fricjax.report.plots import plot_signals
    from fricjax.units import axis_units

    out = Path(png) if png else Path(recording).with_suffix(".png")
    check_outputs([out], {"recording": recording, "--config": config}, "--png")
    rec = read_recording(recording, mass=mass)
    cfg = load_config(config) if config else None
    table = cfg.table("preprocess") if cfg else {}
    units = cfg.axis if cfg else axis_units(rec.axis or "linear")
    settings = PreprocessSettings.from_dict(table, source=str(config or "defaults"))
    d = derivatives(rec.t, rec.x, settings, u=rec.u, F=rec.F, source=str(recording))
    m = rec.mass
    force = m * d.a if m is not None else np.full_like(d.a, np.nan)
    noise_x = estimate_noise(rec.x)
    # a reversal is a crossing of the band where noise can flip the filtered velocity's sign
    gain_v, _ = noise_gains(settings, 1.0 / rec.dt)
    rest_speed = FLIP_KAPPA * gain_v * noise_x.sigma
    summary = {
        "file": str(recording),
        "name": rec.name,
        "source": rec.source,
        "samples": str(rec.n),
        "rate [Hz]": f"{1.0 / rec.dt:.6g}",
        "duration [s]": f"{rec.duration:.6g}",
        "axis": units.kind,
        f"{units.inertia_word} [{units.inertia}]": "missing" if m is None else f"{m:g}",
        f"x range [{units.position}]": f"{d.x.min():.4g} .. {d.x.max():.4g}",
        f"v range [{units.velocity}]": f"{d.v.min():.4g} .. {d.v.max():.4g}",
        f"a range [{units.acceleration}]": f"{d.a.min():.4g} .. {d.a.max():.4g}",
        "velocity reversals": str(reversals(d.v, rest_speed)),
        "input u": "none"
        if rec.u is None
        else f"{rec.u.min():.4g} .. {rec.u.max():.4g} {rec.u_unit}",
        "preprocess": f"{settings.method}, order {settings.order}, cutoff {settings.cutoff_hz:g} Hz"
        if settings.method == "butterworth"
        else f"savgol, window {settings.savgol_window}, order {settings.savgol_polyorder}",
        "sha256": rec.sha256()[:16],
    }
    if m is not None:
        summary[f"{units.inertial} range [{units.force}]"] = (
            f"{force.min():.4g} .. {force.max():.4g}"
        )
    if rec.F is not None:
        summary[f"measured F [{units.force}]"] = f"{rec.F.min():.4g} .. {rec.F.max():.4g}"
    # the recording's own noise floor, independent of any model (fricjax.data.noise)
    summary["x noise"] = noise_x.describe(units.position)
    if rec.F is not None:
        summary["F noise"] = estimate_noise(rec.F).describe(units.force)
    if rec.u is not None:
        summary["u noise"] = estimate_noise(rec.u).describe(rec.u_unit or "(u unit)")
    fig = plot_signals(
        d.t, d.x, d.v, d.a, force, title=f"{rec.name or out.stem}", path=out, units=units
    )
    return summary, fig


def cost_at(
    recording: str | Path,
    config: str | Path,
    *,
    params: str | Path | None = None,
    mass: float | None = None,
) -> dict[str, Any]:
    """Cost (seed eq. 11) and EMS at given parameters; default: a twin's generating truth."""
    _, cfg, problem = load(recording, config, mass=mass)
    if params is not None:
        named, source = read_params(params), str(params)
        check_values(named, problem.spec, source)
    else:
        from fricjax.data.twin import read_truth

        truth = read_truth(recording)  # scoring against the generator, never used to fit
        if truth is None:
            raise FricjaxError(
                f"{where(recording)}: not a synthetic twin (no truth): give --params"
            )
        named, source = truth, "truth of the twin"
    fixed_changes = {
        k: v for k, v in named.items() if k in problem.spec and not problem.spec[k].free
    }
    if fixed_changes:
        problem = _with_fixed(problem, fixed_changes)
    # a twin's truth also holds generator-only entries (noise_std, seed, model): skipped
    theta = problem.theta({k: v for k, v in named.items() if k in problem.spec})
    total = problem.cost(theta)
    if not math.isfinite(total):
        culprit = problem.model.overflowing(
            problem.spec.as_dict(theta), problem.signals, MAX_MAGNITUDE
        )
        raise FricjaxError(
            f"{where(source)}: the cost is not finite at these parameters (overflows: "
            f"{culprit or 'the residual'}); no cost to report"
        )
    return {
        "axis": cfg.axis,
        "cost": total,
        "ems": problem.ems(theta),
        "n": problem.n,
        "source": source,
        "theta": theta,
    }


def _with_fixed(problem: Problem, values: dict[str, float]) -> Problem:
    from dataclasses import replace

    spec = problem.spec
    params = tuple(
        replace(
            p,
            init=float(values[p.name]),
            lower=min(p.lower, float(values[p.name])),
            upper=max(p.upper, float(values[p.name])),
        )
        if p.name in values and not p.free
        else p
        for p in spec.params
    )
    return replace(problem, spec=replace(spec, params=params))


def identify_recording(
    recording: str | Path,
    config: str | Path,
    *,
    overrides: dict[str, Any] | None = None,
    out: str | Path | None = None,
    mass: float | None = None,
    on_level: Any = None,
) -> tuple[Any, Path]:
    """``fricjax identify``: identify, then write the results file (atomic).

    Ctrl-C during the search or the refiner stops it cleanly: the search's best so far
    is refined no further, qualified and written (``interrupted`` set, ``refined`` not).
    """
    from fricjax.identify import IdentifySettings, identify
    from fricjax.io.results import ResultsFile, provenance, write_results

    rec, cfg, problem = load(recording, config, mass=mass)
    settings = IdentifySettings.from_tables(cfg.tables, source=cfg.source, overrides=overrides)
    # one identification per call (and per CLI process): compilation, not the run, is
    # what the user waits for, so its programs are compiled for compile speed
    settings = dataclasses.replace(settings, fast_compile=True)
    path = (
        Path(out)
        if out
        else Path(recording).with_name(
            f"{Path(recording).stem}_{settings.method}_s{settings.seed}.results.h5"
        )
    )
    check_outputs([path], {"recording": recording, "--config": cfg.source}, "--out")
    run = identify(problem, settings, on_level=on_level)
    run.attrs["axis"] = cfg.axis.kind  # labels of the summary and of show (fricjax.units)
    attrs = provenance(
        kind="identify",
        recording_name=rec.name,
        recording_path=str(recording),
        recording_sha256=problem.checksum,
        config_text=cfg.text,
        config_path=cfg.source,
    )
    write_results(ResultsFile(runs=[run], attrs=attrs), path)
    return run, path


def identify_recordings(
    recordings: list[str | Path],
    config: str | Path,
    *,
    overrides: dict[str, Any] | None = None,
    out: str | Path | None = None,
    mass: float | None = None,
    on_level: Any = None,
    on_member: Any = None,
) -> tuple[Any, Path]:
    """``fricjax identify REC1 REC2 ...``: one recording is :func:`identify_recording`,
    unchanged; several are fitted jointly (:mod:`fricjax.joint`: shared parameters and the
    config's ``[joint].per_recording`` ones, each recording weighted by its noise), and
    the joint run written to one results file (``kind = "joint"``, atomic). Default
    ``out``: ``STEM1_joint_METHOD_sSEED.results.h5`` beside the first recording."""
    from fricjax.joint import JointSettings

    if len(recordings) == 1:
        # the [joint] table is checked even where it does not apply: a typo never waits
        # for the day a second recording is given
        JointSettings.from_config(load_config(config))
        return identify_recording(
            recordings[0], config, overrides=overrides, out=out, mass=mass, on_level=on_level
        )
    if not recordings:
        raise FricjaxError("identify: give at least one recording")
    import hashlib

    from fricjax.identify import IdentifySettings
    from fricjax.io.results import ResultsFile, provenance, write_results
    from fricjax.joint import identify_joint

    cfg = load_config(config)
    joint = JointSettings.from_config(cfg)
    settings = IdentifySettings.from_tables(cfg.tables, source=cfg.source, overrides=overrides)
    settings = dataclasses.replace(settings, fast_compile=True)
    first = Path(recordings[0])
    path = (
        Path(out)
        if out
        else first.with_name(f"{first.stem}_joint_{settings.method}_s{settings.seed}.results.h5")
    )
    inputs: dict[str, str | Path | None] = {f"recording {r}": r for r in recordings}
    check_outputs([path], {**inputs, "--config": cfg.source}, "--out")
    recs = alike_recordings(recordings, mass=mass)
    problems = [build_problem(rec, cfg) for rec in recs]
    run = identify_joint(problems, settings, joint, on_level=on_level, on_member=on_member)
    run.attrs["axis"] = cfg.axis.kind
    combined = hashlib.sha256("".join(p.checksum for p in problems).encode()).hexdigest()
    attrs = provenance(
        kind="joint",
        recording_name=" + ".join(p.name for p in problems),
        recording_path="",
        recording_sha256=combined,
        config_text=cfg.text,
        config_path=cfg.source,
    )
    write_results(ResultsFile(runs=[run], attrs=attrs), path)
    return run, path


def alike_recordings(recordings: list[str | Path], *, mass: float | None = None) -> list[Recording]:
    """Read recordings for one joint fit, refusing (one line) recordings of different kinds
    or the same one twice (:func:`fricjax.joint.check_alike`)."""
    from fricjax.joint import check_alike

    recs = [read_recording(r, mass=mass) for r in recordings]
    check_alike(recs, [str(r) for r in recordings])
    return recs


def sweep_recording(
    recording: str | Path,
    config: str | Path,
    *,
    methods: list[str],
    schedules: list[str],
    alphas: list[float],
    restarts: int = 1,
    chains: int | None = None,
    seed: int = 0,
    refine: bool = True,
    out: str | Path = "sweep.h5",
    mass: float | None = None,
    on_run: Any = None,
) -> tuple[str, Path, bool]:
    """``fricjax sweep``: every method x schedule x alpha x restart into one results file.

    All runs share the problem and hence the compiled cost; the file is rewritten after
    each run, so an interrupted sweep keeps every finished run. Returns the ranked table,
    the file and whether Ctrl-C cut the sweep short (after at least one run).
    """
    from fricjax.identify import IdentifySettings, identify
    from fricjax.io.results import ResultsFile, provenance, write_results
    from fricjax.report.tables import fmt, format_table

    path = Path(out)
    check_outputs([path], {"recording": recording, "--config": config}, "--out")
    if not (methods and schedules and alphas) or restarts < 1:
        raise FricjaxError(
            f"{where('sweep')}: nothing to run: --methods, --schedules and --alphas each "
            f"need at least one entry and --restarts at least 1 (got {len(methods)} "
            f"methods, {len(schedules)} schedules, {len(alphas)} alphas, {restarts} restarts)"
        )
    if seed + restarts > 2**64:  # the seeds run are seed … seed + restarts − 1
        raise FricjaxError(
            f"{where('sweep', '--seed')}: seeds {seed} … {seed + restarts - 1} pass the "
            "64-bit key's largest, 2**64 − 1"
        )
    rec, cfg, problem = load(recording, config, mass=mass)
    attrs = provenance(
        kind="sweep",
        recording_name=rec.name,
        recording_path=str(recording),
        recording_sha256=problem.checksum,
        config_text=cfg.text,
        config_path=cfg.source,
    )
    runs = []
    interrupted = False
    try:
        for method in methods:
            for schedule in schedules:
                for alpha in alphas:
                    for r in range(restarts):
                        overrides = {
                            "method": method,
                            "schedule": schedule,
                            "alpha": alpha,
                            "seed": seed + r,
                            "chains": chains,
                            "refine": None if refine else False,
                        }
                        settings = IdentifySettings.from_tables(
                            cfg.tables, source=cfg.source, overrides=overrides
                        )
                        label = f"{method}_{schedule}_a{alpha:g}_s{seed + r}"
                        if on_run:
                            on_run(label)
                        runs.append(identify(problem, settings, label=label))
                        runs[-1].attrs["axis"] = cfg.axis.kind
                        write_results(ResultsFile(runs=runs, attrs=attrs), path)
    except KeyboardInterrupt:
        if not runs:
            raise
        interrupted = True
    rows = [
        (
            r.label,
            fmt(r.cost, 7),
            fmt(r.ems, 7),
            fmt(r.cost_search, 7),
            str(r.attrs["levels"]),
            f"{r.attrs['wall_time']:.2f}",
        )
        for r in sorted(runs, key=lambda r: r.cost)
    ]
    table = format_table(
        rows, ("run", "cost [N²]", "EMS [N²]", "before refine", "levels", "time [s]")
    )
    return table, path, interrupted


def _diagnose_settings(cfg: Config, overrides: dict[str, Any] | None) -> tuple[Any, Any, bool]:
    """(identify settings, diagnose settings, whether a time limit was given) of a
    diagnosis: the config's ``[diagnose]`` table checked alone first, so an error names
    where the bad value came from (the file or the command line), then the command line's
    values over it. The base fit runs once per diagnosis: compiled for compile speed
    (see identify_recording)."""
    from fricjax.diagnose.run import DiagnoseSettings
    from fricjax.identify import CLI_SOURCE, IdentifySettings

    ident = dataclasses.replace(
        IdentifySettings.from_tables(cfg.tables, source=cfg.source), fast_compile=True
    )
    table = dict(cfg.table("diagnose"))
    settings = DiagnoseSettings.from_dict(table, source=cfg.source)
    cli = {k: v for k, v in (overrides or {}).items() if v is not None}
    if cli:
        DiagnoseSettings.from_dict(cli, source=CLI_SOURCE, flags=True)
        settings = DiagnoseSettings.from_dict({**table, **cli}, source=cfg.source)
    return ident, settings, "time_limit" in cli or "time_limit" in table


def diagnose_recording(
    recording: str | Path | Recording | list[str | Path],
    config: str | Path | Config,
    *,
    out: str | Path,
    validation: str | Path | None = None,
    mass: float | None = None,
    overrides: dict[str, Any] | None = None,
    on_stage: Callable[[StageEvent], None] | None = None,
    stop: threading.Event | None = None,
) -> tuple[Diagnosis, dict[str, Path]]:
    """``fricjax diagnose``: base fit, every catalogue term refitted, the one rule; writes
    DIR/diagnosis.json, models.h5, report.md and report.html. The diagnosis' ``findings``
    are :class:`~fricjax.diagnose.select.Finding` s (``as_json()``: the diagnosis.json
    entry), its ``steps`` the typed forward-selection steps.

    ``overrides``: ``[diagnose]`` keys set from the command line (``time_limit`` among
    them); ``on_stage``: called with each :class:`~fricjax.diagnose.stages.StageEvent`
    (progress); ``stop``: a stop request from another thread (Ctrl-C): what was judged
    is written, marked interrupted. Never reads ``/truth``: the recording is read through
    :func:`read_recording`, which ignores that group.

    A list of recordings is judged as one record (:func:`fricjax.problem.joined`): tests of
    one plant run one after the other with nothing changed between them (the test that
    ``fricjax design`` proposes, run after the record it was designed from), every
    parameter shared and each recording's motion simulated from its own state.
    """
    from fricjax.diagnose.report import OUTPUT_FILES, write_diagnosis
    from fricjax.diagnose.run import diagnose

    config_path = (config.source or None) if isinstance(config, Config) else config
    if isinstance(recording, list):
        sources: dict[str, str | Path | None] = {f"recording {r}": r for r in recording}
        source: str | Path = " + ".join(str(r) for r in recording)
    else:
        source = (
            (recording.path or recording.name) if isinstance(recording, Recording) else recording
        )
        sources = {"recording": source}
    check_outputs(
        [Path(out) / name for name in OUTPUT_FILES],
        {**sources, "--config": config_path, "--validation": validation},
        "--out",
    )
    if isinstance(recording, list):
        if len(recording) < 2:
            raise FricjaxError("diagnose: recordings judged as one record need at least two")
        cfg = config if isinstance(config, Config) else load_config(config)
        recs = alike_recordings(recording, mass=mass)
        problem = joined([build_problem(r, cfg) for r in recs])
    else:
        _, cfg, problem = load(recording, config, mass=mass)
    ident, settings, _ = _diagnose_settings(cfg, overrides)
    val = None
    if validation is not None:
        _, _, val = load(validation, cfg, mass=mass)
    diag = diagnose(
        problem,
        identify_settings=ident,
        settings=settings,
        validation=val,
        recording=str(source),
        on_stage=on_stage,
        stop=stop,
    )
    return diag, write_diagnosis(diag, out)


def diagnose_recordings(
    recordings: list[str | Path],
    config: str | Path,
    *,
    out: str | Path,
    mass: float | None = None,
    overrides: dict[str, Any] | None = None,
    effects: list[str] | None = None,
    on_stage: Callable[[StageEvent], None] | None = None,
) -> tuple[AcrossDiagnosis, dict[str, Path]]:
    """``fricjax diagnose REC1 REC2 ...``: the diagnosis across recordings of one plant on
    their joint fit (:mod:`fricjax.diagnose.across`: shared catalogue terms judged by
    leaving one recording out, run-to-run drift, in the one forward selection of
    :mod:`fricjax.diagnose.select`); writes DIR/diagnosis.json, DIR/report.md and
    DIR/report.html (atomic).

    ``overrides``: ``alpha``, ``max_terms``, ``time_limit`` from the command line (the
    ``[diagnose]`` table's ``alpha``, ``min_delta_bic``, ``max_terms``, ``ambiguity``,
    ``time_limit`` otherwise, ``[diagnose.stage_limits]`` where tighter than the defaults of
    :mod:`fricjax.diagnose.across`); ``effects``: the catalogue entries to try (default
    all); ``on_stage``: progress events, as for one recording."""
    from fricjax.diagnose.across import across_clock, diagnose_across
    from fricjax.diagnose.report import write_across
    from fricjax.joint import JointSettings

    if len(recordings) < 2:
        raise FricjaxError("diagnose: a diagnosis across recordings needs at least two")
    inputs: dict[str, str | Path | None] = {f"recording {r}": r for r in recordings}
    check_outputs(
        [Path(out) / "diagnosis.json", Path(out) / "report.md", Path(out) / "report.html"],
        {**inputs, "--config": config},
        "--out",
    )
    cfg = load_config(config)
    joint = JointSettings.from_config(cfg)
    ident, settings, limited = _diagnose_settings(cfg, overrides)
    total = float(settings.time_limit) if limited else None
    clock = across_clock(settings.stage_limits, total, on_stage)
    recs = alike_recordings(recordings, mass=mass)
    problems = [build_problem(rec, cfg) for rec in recs]
    diag = diagnose_across(problems, ident, joint, rule=settings.rule, effects=effects, clock=clock)
    return diag, write_across(diag, out)


def simulate_recording(
    recording: str | Path | Recording,
    results: str | Path | None = None,
    params: str | Path | dict[str, float] | None = None,
    config: str | Path | Config | None = None,
    controller: Any = None,
    substeps: int = 4,
    out: str | Path | None = None,
    *,
    mass: float | None = None,
    member: int | None = None,
) -> SimulationReport:
    """``fricjax simulate``: simulate identified parameters over a recording and compare
    x, v, a and force (:mod:`fricjax.simulation`).

    Args:
        recording: the recording (path or :class:`Recording`); ``/truth`` is never read.
        results: a results .h5 of ``identify`` (its best run; its stored config is used
            unless ``config`` is given). Exactly one of ``results`` and ``params``.
        params: TOML/JSON ``name = value`` file, or a mapping; needs ``config``.
        config: model config (path or :class:`Config`).
        controller: ``"emps"``, ``"kp=…,kv=…[,u_max=…]"`` or a
            :class:`~fricjax.model.closed_loop.CascadePD`: closed loop (needs ``/r``).
        substeps: RK4 sub-steps per sample interval.
        out: folder for ``simulation.json``, ``simulation.h5``, ``simulation.png``
            (written atomically); None writes nothing.
        member: with a joint ``results``, the recording (1-based) whose parameters to
            simulate; default the member that is ``recording`` (same data).

    Returns:
        :class:`fricjax.simulation.SimulationReport`.
    """
    from fricjax.model.closed_loop import CascadePD
    from fricjax.report.simulation import write_simulation
    from fricjax.simulation import simulate_against
    from fricjax.validate import config_from_results, parse_controller

    if out is not None:
        from fricjax.report.simulation import OUTPUT_FILES

        check_outputs(
            [Path(out) / name for name in OUTPUT_FILES],
            {
                "recording": None if isinstance(recording, Recording) else recording,
                "--results": results,
                "--params": None if isinstance(params, dict) else params,
                "--config": None if isinstance(config, Config) else config,
            },
            "--out",
        )
    if (results is None) == (params is None):
        raise FricjaxError(
            f"{where('simulate', '--results/--params')}: give exactly one of them "
            f"({'neither' if results is None else 'both'} given)"
        )
    rec = recording if isinstance(recording, Recording) else read_recording(recording, mass=mass)
    if results is not None:
        results = Path(results)
        if not results.is_file():
            raise FricjaxError(f"{where(results)}: results file not found")
        if results.suffix.lower() not in (".h5", ".hdf5"):
            raise FricjaxError(f"{where(results)}: not a results .h5 (use --params for TOML/JSON)")
        named, source = read_params(results, member=member, recording=rec), str(results)
        if config is None:
            config = config_from_results(results)
    elif member is not None:
        raise FricjaxError("--member: picks a recording of a joint --results; none given")
    elif isinstance(params, dict):
        named, source = {k: float(v) for k, v in params.items()}, "params"
    else:
        named, source = read_params(params), str(params)
    if config is None:
        raise FricjaxError(f"{where(source)}: holds no config; give --config")
    cfg = config if isinstance(config, Config) else load_config(config)
    ctrl = controller if isinstance(controller, CascadePD) else parse_controller(controller)
    report = simulate_against(rec, cfg, named, controller=ctrl, substeps=substeps, source=source)
    if out is not None:
        report = write_simulation(report, out)
    return report


def parse_limits(text: str | None, problem: Problem) -> Any:
    """``--limits F_max,x_range,v_max``: peak input [unit of u] (the input then stays in
    ±F_max), travel ("lo:hi" [m], or a length [m] centred on the record's travel) and
    peak speed [m/s]; an empty field keeps what the record did."""
    from fricjax.design import record_limits

    own = record_limits(problem)
    if text is None:
        return own
    fields = text.split(",")
    if len(fields) != 3:
        raise FricjaxError(
            f"--limits: {text!r}: give F_max,x_range,v_max (empty keeps the record's)"
        )

    def number(field: str, what: str) -> float:
        try:
            value = float(field)
        except ValueError:
            raise FricjaxError(f"--limits: {what} {field!r} is not a number") from None
        if not math.isfinite(value) or value <= 0:
            raise FricjaxError(f"--limits: {what} {field!r} must be finite and > 0")
        return value

    force, travel, speed = (f.strip() for f in fields)
    if force:
        own = own._replace(u_mid=0.0, u_peak=number(force, "F_max"))
    if travel:
        if ":" in travel:
            lo, hi = (float(v) if v.strip() else math.nan for v in travel.split(":", 1))
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise FricjaxError(f"--limits: x_range {travel!r}: give lo:hi with lo < hi [m]")
        else:
            half, mid = 0.5 * number(travel, "x_range"), 0.5 * (own.x_lo + own.x_hi)
            lo, hi = mid - half, mid + half
        if not lo <= float(problem.x[0]) <= hi:
            raise FricjaxError(
                f"--limits: x_range {travel!r} excludes the start position {problem.x[0]:.4g} m"
            )
        own = own._replace(x_lo=lo, x_hi=hi)
    if speed:
        own = own._replace(speed=number(speed, "v_max"))
    return own


def design_test(
    recording: str | Path | Recording,
    config: str | Path | Config,
    diagnosis: str | Path | None = None,
    *,
    results: str | Path | None = None,
    out: str | Path | None = None,
    candidates: list[str] | None = None,
    focus: list[str] | None = None,
    limits: str | None = None,
    duration: float | None = None,
    settings: Any = None,
    mass: float | None = None,
) -> tuple[Any, dict[str, Path]]:
    """``fricjax design`` (:mod:`fricjax.design`): the next test's input profile, written to
    ``out`` (CSV) with its .png and .json when given.

    With ``diagnosis`` (a diagnosis folder of ``recording``): the profile that best
    separates the models of its first ambiguity set, or ``candidates`` ("base" and
    catalogue names). With ``results`` (an identify results file of ``recording``): the
    profile that best determines ``focus`` (default: the parameters the identify summary
    calls undetermined, else all free ones). Exactly one of the two.

    Returns:
        (:class:`~fricjax.design.Design` or :class:`~fricjax.design.PrecisionDesign`, the
        paths written).
    """
    from fricjax.design import (
        DesignSettings,
        Rival,
        commanded_input,
        design,
        design_precision,
        read_rivals,
    )
    from fricjax.output_error import noise_scale
    from fricjax.refine import covariance
    from fricjax.report.design import design_files, write_design

    if (diagnosis is None) == (results is None):
        raise FricjaxError(
            f"{where('design', '--diagnosis/--results')}: give exactly one of them "
            "(a diagnosis to separate its models, or identify results to determine parameters)"
        )
    source = (recording.path or recording.name) if isinstance(recording, Recording) else recording
    if out is not None:
        config_path = (config.source or None) if isinstance(config, Config) else config
        check_outputs(
            list(design_files(out).values()),
            {"recording": source, "--config": config_path, "--results": results},
            "--out",
        )
    if duration is not None and not (math.isfinite(duration) and duration > 0):
        raise FricjaxError(f"--duration: {duration} must be finite and > 0 [s]")
    _, _, problem = load(recording, config, mass=mass)
    commanded_input(problem)
    lim = parse_limits(limits, problem)
    settings = settings or DesignSettings()
    result: Any
    if diagnosis is not None:
        rivals, sigma = read_rivals(diagnosis, problem, candidates)
        result = design(problem, rivals, sigma, limits=lim, duration=duration, settings=settings)
    else:
        from fricjax.io.results import read_results
        from fricjax.report.show import undetermined

        runs = read_results(results).runs  # type: ignore[arg-type]
        run = min(runs, key=lambda r: r.cost)
        unknown = sorted(set(run.names) - set(problem.spec.names))
        if unknown:
            raise FricjaxError(
                f"{where(results, 'params')}: {', '.join(unknown)} not in the config's model "
                f"{problem.model.name} (identified with another config?)"
            )
        model = Rival(
            name="identified",
            model=problem.model,
            params={p.name: float(p.init) for p in problem.spec.params} | run.params,
            free=tuple(run.names),
            cov=covariance(run.std, run.corr),
            cost=0.0,
        )
        targets = focus or list(undetermined(run)) or list(run.names)
        result = design_precision(
            problem,
            model,
            noise_scale(np.asarray(problem.x)),
            targets,
            limits=lim,
            duration=duration,
            settings=settings,
        )
    return result, ({} if out is None else write_design(result, out))


def fleet_recordings(
    recordings: list[str | Path],
    config: str | Path,
    out: str | Path,
    *,
    overrides: dict[str, Any] | None = None,
    shard_size: int | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
    order_by: str | None = None,
    mass: float | None = None,
    on_shard: Any = None,
) -> tuple[Any, Any, Path, Path]:
    """``fricjax fleet``: identify every recording independently (:mod:`fricjax.fleet`),
    write the fleet file (atomic) and its report (``OUT.md`` + ``OUT.png``).

    ``workers``: run the shards on a local Dask cluster of that many worker processes;
    ``scheduler``: on a running Dask cluster (``tcp://host:8786``); neither: in process.
    Returns ``(fleet file contents, drift test, report path, figure path)``.
    """
    from fricjax.fleet import default_shard_size, load_members, run_fleet
    from fricjax.identify import IdentifySettings
    from fricjax.io.fleet import FleetFile, fleet_attrs, write_fleet
    from fricjax.report.fleet import write_fleet_report

    if workers is not None and scheduler is not None:
        raise FricjaxError("--workers and --scheduler: give one of them, not both")
    if workers is not None and workers < 1:
        raise FricjaxError(f"--workers: must be >= 1, got {workers}")
    cfg = load_config(config)
    settings = IdentifySettings.from_tables(cfg.tables, source=cfg.source, overrides=overrides)
    members = load_members(recordings, cfg, order_by=order_by, mass=mass)
    outputs = [Path(out), Path(out).with_suffix(".md"), Path(out).with_suffix(".png")]
    inputs = {f"recording {m.path}": m.path for m in members}
    check_outputs(outputs, {**inputs, "--config": cfg.source}, "--out")
    size = default_shard_size() if shard_size is None else shard_size
    with _dask_client(workers, scheduler) as client:
        fits = run_fleet(members, settings, shard_size=size, client=client, on_shard=on_shard)
    spec = next((m.problem.spec for m in members if m.problem is not None), cfg.spec)
    fleet = FleetFile(
        names=list(spec.free_names),
        units=[p.unit for p in spec.free],
        lower=np.asarray(spec.lower, np.float64),
        upper=np.asarray(spec.upper, np.float64),
        fits=fits,
        attrs=fleet_attrs(
            config_text=cfg.text,
            config_path=cfg.source,
            seed=settings.seed,
            method=settings.method,
            separable=settings.separable,
            shard_size=size,
            order_by=order_by or "",
        ),
    )
    path = write_fleet(fleet, out)
    report, png = path.with_suffix(".md"), path.with_suffix(".png")
    result = write_fleet_report(fleet, report, png)
    return fleet, result, report, png


class _dask_client:
    """``with _dask_client(workers, scheduler) as client``: a ``distributed.Client`` on a
    new local cluster of ``workers`` processes (one thread each: the fits are vmapped, jax
    uses the cores), on the running scheduler at ``scheduler``, or None for neither."""

    def __init__(self, workers: int | None, scheduler: str | None) -> None:
        self.workers, self.scheduler = workers, scheduler
        self.client: Any = None
        self.cluster: Any = None

    def __enter__(self) -> Any:
        if self.workers is None and self.scheduler is None:
            return None
        try:
            from distributed import Client, LocalCluster
        except ImportError:
            raise FricjaxError(
                "--workers/--scheduler: needs dask.distributed (pip install 'fricjax[fleet]')"
            ) from None
        if self.scheduler is not None:
            try:
                self.client = Client(self.scheduler, timeout="20s")
            except (OSError, TimeoutError, ValueError) as err:
                raise FricjaxError(
                    f"--scheduler {self.scheduler}: cannot connect ({err})"
                ) from None
        else:
            self.cluster = LocalCluster(
                n_workers=self.workers, threads_per_worker=1, processes=True, dashboard_address=None
            )
            self.client = Client(self.cluster)
        return self.client

    def __exit__(self, *exc: object) -> None:
        if self.client is not None:
            self.client.close()
        if self.cluster is not None:
            self.cluster.close()
