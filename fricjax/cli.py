"""Command-line interface: a thin typer layer over the Python API.

Every command maps onto one API call; a user mistake (:class:`FricjaxError`) prints one line
``error: FILE: FIELD: what is wrong`` on stderr and exits with status 2, never a traceback.
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from typer._click.exceptions import NoArgsIsHelpError  # typer vendors click (pinned <0.30)
from typer.exceptions import Abort, TyperException

from fricjax.diagnose.stages import TIME_LIMIT_S as DIAGNOSE_TIME_LIMIT
from fricjax.errors import EXIT, FricjaxError, OutputFault

if TYPE_CHECKING:
    from fricjax.data.recording import Recording

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
)

RecArg = Annotated[Path, typer.Argument(help="Recording (.h5 layout v1 or .csv)")]
ConfigOpt = Annotated[Path, typer.Option("--config", "-c", help="Model config (TOML)")]
DefaultConfigOpt = Annotated[
    Path | None,
    typer.Option(
        "--config",
        "-c",
        help="Model config (TOML); default configs/paper.toml, refused for a recording "
        "with a measured input /u or /F (write one with fricjax init-config)",
    ),
]
MassOpt = Annotated[
    float | None, typer.Option("--mass", help="Moving mass [kg] (for CSV or to override)")
]
MemberOpt = Annotated[
    int | None,
    typer.Option(
        help="With a joint --results: use recording K's parameters (1-based, the order "
        "given to identify; default: the member whose data are RECORDING)",
        min=1,
    ),
]
#: The PRNG key holds 64 bits (:func:`fricjax.identify.prng_key`): a larger or negative
#: seed would silently alias another one.
SEED_RANGE = {"min": 0, "max": 2**64 - 1}


def _echo_table(rows: list[tuple[str, ...]], header: tuple[str, ...] | None = None) -> None:
    from fricjax.report.tables import format_table

    typer.echo(format_table(rows, header))


@app.command()
def twin(
    out: Annotated[Path, typer.Argument(help="Output recording (.h5)")] = Path(
        "data/paper_twin.h5"
    ),
    duration: Annotated[float, typer.Option(help="Record length [s]")] = 0.272,
    rate: Annotated[float, typer.Option(help="Sampling rate [Hz]")] = 1000.0,
    noise_std: Annotated[float | None, typer.Option(help="Noise std on x [m]")] = None,
    seed: Annotated[int, typer.Option(help="Noise seed", **SEED_RANGE)] = 0,
) -> None:
    """Write a paper-twin recording (seed eq. 5, CSAA column of Tables 1-3; truth in /truth)."""
    from fricjax.data.twin import DEFAULT_NOISE_STD, write_twin

    std = DEFAULT_NOISE_STD if noise_std is None else noise_std
    path = write_twin(out, duration=duration, rate=rate, noise_std=std, seed=seed)
    typer.echo(f"wrote {path} ({round(duration * rate)} samples, noise std {std:g} m)")


@app.command()
def inspect(
    recording: RecArg,
    config: Annotated[Path | None, typer.Option("--config", "-c", help="For [preprocess]")] = None,
    mass: MassOpt = None,
    png: Annotated[Path | None, typer.Option(help="Figure path (default: REC.png)")] = None,
) -> None:
    """Summary table and a PNG of x, v, a and measured force m·a."""
    from fricjax.api import inspect_recording

    summary, fig = inspect_recording(recording, config=config, mass=mass, png=png)
    _echo_table([(k, v) for k, v in summary.items()], ("field", "value"))
    typer.echo(f"figure: {fig}")


@app.command("import-mat")
def import_mat_cmd(
    mat: Annotated[Path, typer.Argument(help="MATLAB .mat file")],
    out: Annotated[Path, typer.Argument(help="Output recording (.h5 or .csv)")],
    map_: Annotated[
        str, typer.Option("--map", help="field=variable pairs, e.g. t=t,x=qm,u=vir")
    ] = "t=t,x=qm,u=vir",
    u_unit: Annotated[str, typer.Option(help="Unit of u (e.g. V)")] = "",
    mass: MassOpt = None,
    name: Annotated[str | None, typer.Option(help="Recording name")] = None,
) -> None:
    """Import a .mat file onto the recording layout (jittered time base resampled)."""
    from fricjax.data.importers import import_mat
    from fricjax.data.recording import write_recording
    from fricjax.io.atomic import check_outputs

    check_outputs([out], {"MAT": mat}, "OUT")

    mapping: dict[str, str] = {}
    for pair in map_.split(","):
        if "=" not in pair:
            raise FricjaxError(f"--map: {pair!r} is not field=variable")
        field, var = (s.strip() for s in pair.split("=", 1))
        mapping[field] = var
    rec = import_mat(mat, mapping=mapping, mass=mass, u_unit=u_unit, name=name)
    path = write_recording(rec, out)
    typer.echo(f"wrote {path}: {rec.n} samples, dt = {rec.dt:g} s; {rec.notes}")


@app.command()
def cost(
    recording: RecArg,
    config: ConfigOpt,
    params: Annotated[
        Path | None,
        typer.Option(help="Parameters: TOML/JSON name = value, or a results .h5 (best run)"),
    ] = None,
    mass: MassOpt = None,
) -> None:
    """Cost (seed eq. 11) and EMS at given parameters (default: a twin's truth)."""
    from fricjax.api import cost_at

    report = cost_at(recording, config, params=params, mass=mass)
    typer.echo(f"parameters: {report['source']}")
    units = report["axis"]
    _echo_table(
        [
            (f"cost [{units.force_sq}]", f"{report['cost']:.6g}"),
            (f"EMS [{units.force_sq}]", f"{report['ems']:.6g}"),
            (f"RMS residual [{units.force}]", f"{report['ems'] ** 0.5:.6g}"),
            ("samples", str(report["n"])),
        ]
    )


def _warn_scale(recording: Path | Recording, config: Path, mass: float | None) -> None:
    """Print a ``warning:`` line on stderr for each implausible unit of the recording."""
    from fricjax.api import scale_warnings

    for line in scale_warnings(recording, config, mass=mass):
        typer.echo(f"warning: {line}", err=True)


MethodOpt = Annotated[
    str | None, typer.Option(help="csaa | csaa-gauss | dsaa | dsaa-gray | rdsa (config default)")
]


def _progress(label: str):
    """A one-line live progress display on stderr (level, temperature, best cost, acceptance)."""

    def on_level(info) -> None:
        typer.echo(
            f"\r{label} level {info.level + 1:4d}  T={info.temperature:10.4g}  "
            f"best={info.best_cost:12.6g}  acc={info.mean_acceptance:5.3f}  "
            f"evals={info.n_evals:9d}  {info.wall_time:6.1f}s",
            err=True,
            nl=False,
        )

    return on_level


@app.command()
def identify(
    recording: Annotated[
        list[Path],
        typer.Argument(
            help="Recording (.h5 layout v1 or .csv); several: one joint fit (shared "
            "parameters, [joint].per_recording ones per recording)"
        ),
    ],
    config: DefaultConfigOpt = None,
    method: MethodOpt = None,
    chains: Annotated[int | None, typer.Option(help="Parallel chains (restarts)", min=1)] = None,
    seed: Annotated[
        int | None, typer.Option(help="Seed (same seed = same result)", **SEED_RANGE)
    ] = None,
    schedule: Annotated[str | None, typer.Option(help="geometric|boltzmann|cauchy|reheat")] = None,
    alpha: Annotated[float | None, typer.Option(help="Cooling factor (eq. 16)")] = None,
    steps_per_level: Annotated[
        int | None, typer.Option(help="Metropolis steps per level", min=1)
    ] = None,
    max_levels: Annotated[int | None, typer.Option(help="Hard limit on levels", min=1)] = None,
    refine: Annotated[bool, typer.Option(help="Polish with Levenberg-Marquardt")] = True,
    separable: Annotated[
        bool | None,
        typer.Option(
            "--separable/--no-separable",
            help="Search the nonlinear parameters only, solve the linear ones exactly "
            "(variable projection; default: separable in the config's search table)",
        ),
    ] = None,
    objective: Annotated[
        str | None,
        typer.Option(
            help="auto (default: output error where the equation error is not noise) | "
            "equation (seed eq. 11) | simulation (then output error with multiple shooting "
            "from the equation-error estimate); default: [search].objective"
        ),
    ] = None,
    out: Annotated[Path | None, typer.Option(help="Results file (.h5)")] = None,
    mass: MassOpt = None,
    quiet: Annotated[bool, typer.Option(help="No progress line")] = False,
) -> None:
    """Identify the config's parameters on a recording (annealing chains + refiner); on
    several recordings of one axis, jointly (docs/joint.md)."""
    from fricjax.api import (
        alike_recordings,
        config_or_default,
        enable_compilation_cache,
        identify_recordings,
    )
    from fricjax.report.show import run_summary

    recordings = recording
    if len(recordings) > 1:
        if config is None:
            raise FricjaxError("--config: missing; a joint fit of several recordings needs one")
        alike_recordings(list(recordings), mass=mass)  # before the scale check reads them
    config = config_or_default(recordings[0], config)
    for rec in recordings:
        _warn_scale(rec, config, mass)
    enable_compilation_cache()

    overrides = {
        "method": method,
        "chains": chains,
        "seed": seed,
        "schedule": schedule,
        "alpha": alpha,
        "steps_per_level": steps_per_level,
        "max_levels": max_levels,
        "refine": None if refine else False,
        "separable": separable,
        "objective": objective,
    }

    def on_member(k: int, total: int, name: str) -> None:
        typer.echo(f"own fit {k + 1}/{total}: {name}", err=True)

    result, path = identify_recordings(
        list(recordings),
        config,
        overrides=overrides,
        out=out,
        mass=mass,
        on_level=None if quiet else _progress(method or "search"),
        on_member=None if quiet else on_member,
    )
    if not quiet:
        typer.echo("", err=True)
    single = recordings[0] if len(recordings) == 1 else None
    typer.echo(run_summary(result, recording=single))
    typer.echo(f"results: {path}")
    if result.attrs.get("interrupted"):
        kept = (
            "the polished point (uncertainty not computed)"
            if result.attrs.get("refined")
            else "the search's best point, not polished"
        )
        typer.echo(f"interrupted: {path} holds {kept} (interrupted = True)", err=True)
        raise typer.Exit(EXIT["partial"])


@app.command()
def fleet(
    recordings: Annotated[
        list[Path], typer.Argument(help="Recordings, or directories of .h5/.csv recordings")
    ],
    config: ConfigOpt,
    out: Annotated[Path, typer.Option(help="Fleet file (.h5); report beside it (.md, .png)")],
    seed: Annotated[int | None, typer.Option(help="Seed of every recording's search")] = None,
    chains: Annotated[int | None, typer.Option(help="Chains per recording")] = None,
    shard_size: Annotated[
        int | None, typer.Option(help="Recordings per vmapped program (one Dask task each)")
    ] = None,
    workers: Annotated[
        int | None, typer.Option(help="Run the shards on a local Dask cluster of N processes")
    ] = None,
    scheduler: Annotated[
        str | None, typer.Option(help="Run the shards on a running Dask cluster (tcp://HOST:8786)")
    ] = None,
    order_by: Annotated[
        str | None, typer.Option(help="Recording attribute to order the report by (default: name)")
    ] = None,
    mass: MassOpt = None,
    quiet: Annotated[bool, typer.Option(help="No progress line")] = False,
) -> None:
    """Identify every recording independently (vmapped shards), write one fleet file and a
    report that flags recordings whose parameters moved beyond their sigma."""
    from fricjax.api import enable_compilation_cache, fleet_recordings

    enable_compilation_cache()

    def progress(done: int, total: int, fits: list) -> None:
        n_ok = sum(f.ok for f in fits)
        typer.echo(
            f"\rfleet shard {done}/{total}  recordings {len(fits)}  ok {n_ok}  "
            f"failed {len(fits) - n_ok}",
            err=True,
            nl=False,
        )

    fleet_file, drift, report, png = fleet_recordings(
        list(recordings),
        config,
        out,
        overrides={"seed": seed, "chains": chains},
        shard_size=shard_size,
        workers=workers,
        scheduler=scheduler,
        order_by=order_by,
        mass=mass,
        on_shard=None if quiet else progress,
    )
    if not quiet:
        typer.echo("", err=True)
    fits = fleet_file.fits
    n_ok = sum(f.ok for f in fits)
    typer.echo(
        f"{len(fits)} recordings: {n_ok} ok, {len(fits) - n_ok} failed; "
        f"{int(drift.moved.sum())} moved beyond sigma (|z| > {drift.threshold:.3g})"
    )
    for f in fits:
        if not f.ok:
            typer.echo(f"failed: {f.name}: {f.reason}")
    typer.echo(f"fleet: {out}")
    typer.echo(f"report: {report} ({png.name})")


@app.command()
def show(
    results: Annotated[Path, typer.Argument(help="Results file (.h5) of identify or sweep")],
    recording: Annotated[
        Path | None, typer.Option(help="Twin recording for truth columns (default: from file)")
    ] = None,
) -> None:
    """Print the seed-style Tables 1-4 (one column per run; truth and error for a twin)."""
    from fricjax.report.show import show_results

    typer.echo(show_results(results, recording=recording))


@app.command()
def sweep(
    recording: RecArg,
    config: DefaultConfigOpt = None,
    methods: Annotated[str, typer.Option(help="Comma-separated methods")] = "csaa,dsaa,rdsa",
    schedules: Annotated[str, typer.Option(help="Comma-separated schedules")] = "geometric",
    alphas: Annotated[str, typer.Option(help="Comma-separated cooling factors")] = "0.95",
    restarts: Annotated[int, typer.Option(help="Independent seeds per combination", min=1)] = 1,
    chains: Annotated[int | None, typer.Option(help="Chains per run", min=1)] = None,
    seed: Annotated[int, typer.Option(help="First seed", **SEED_RANGE)] = 0,
    refine: Annotated[bool, typer.Option(help="Polish with Levenberg-Marquardt")] = True,
    out: Annotated[Path, typer.Option(help="Sweep results file (.h5)")] = Path("sweep.h5"),
    mass: MassOpt = None,
) -> None:
    """Every method x schedule x alpha x restart; one file; a table ranked by final cost."""
    from fricjax.api import config_or_default, sweep_recording

    config = config_or_default(recording, config)

    def parse(text: str, kind: type) -> list:
        try:
            return [kind(s.strip()) for s in text.split(",") if s.strip()]
        except ValueError:
            raise FricjaxError(f"sweep: cannot parse {text!r}") from None

    table, path, interrupted = sweep_recording(
        recording,
        config,
        methods=parse(methods, str),
        schedules=parse(schedules, str),
        alphas=parse(alphas, float),
        restarts=restarts,
        chains=chains,
        seed=seed,
        refine=refine,
        out=out,
        mass=mass,
        on_run=lambda label: typer.echo(f"run {label}", err=True),
    )
    typer.echo(table)
    typer.echo(f"results: {path}")
    if interrupted:
        typer.echo(f"interrupted: {path} holds the runs finished so far", err=True)
        raise typer.Exit(EXIT["partial"])


@app.command()
def validate(
    recording: RecArg,
    results: Annotated[
        Path, typer.Option(help="Results .h5 of identify (best run), or TOML/JSON name = value")
    ],
    config: Annotated[
        Path | None, typer.Option("--config", "-c", help="Model config (default: from results)")
    ] = None,
    decimate: Annotated[
        int, typer.Option(help="IDIM decimation of τ and residual (EMPS recipe: 10)", min=1)
    ] = 1,
    controller: Annotated[
        str | None,
        typer.Option(help="Closed-loop re-simulation: 'emps' or kp=…,kv=…[,u_max=…] (needs /r)"),
    ] = None,
    simulate: Annotated[bool, typer.Option(help="Also compare a simulation")] = True,
    mass: MassOpt = None,
    out: Annotated[Path | None, typer.Option(help="Write the metrics as JSON")] = None,
    member: MemberOpt = None,
) -> None:
    """Evaluate identified parameters on a recording: IDIM relative error, error norm and
    std, EMS; simulation error (closed loop with --controller and /r, else open loop)."""
    from fricjax.validate import format_validation, parse_controller, validate_recording

    report = validate_recording(
        recording,
        results,
        config=config,
        decimate_by=decimate,
        controller=parse_controller(controller),
        simulate_run=simulate,
        mass=mass,
        out=out,
        member=member,
    )
    typer.echo(format_validation(report))
    if out is not None:
        typer.echo(f"metrics: {out}")


@app.command()
def simulate(
    recording: RecArg,
    results: Annotated[
        Path | None, typer.Option(help="Results .h5 of identify (best run; its config)")
    ] = None,
    params: Annotated[
        Path | None, typer.Option(help="Parameters: TOML/JSON name = value (needs --config)")
    ] = None,
    config: Annotated[
        Path | None, typer.Option("--config", "-c", help="Model config (default: from results)")
    ] = None,
    controller: Annotated[
        str | None,
        typer.Option(help="Closed loop: 'emps' or kp=…,kv=…[,u_max=…] (needs /r)"),
    ] = None,
    substeps: Annotated[int, typer.Option(help="RK4 sub-steps per sample interval", min=1)] = 4,
    out: Annotated[Path, typer.Option(help="Output folder")] = Path("simulation"),
    mass: MassOpt = None,
    member: MemberOpt = None,
) -> None:
    """Simulate identified parameters from the recording's initial state and compare x, v,
    a and force: RMS error, relative error, fit %; writes OUT/simulation.json, .h5, .png."""
    from fricjax.api import enable_compilation_cache, simulate_recording
    from fricjax.report.simulation import format_simulation

    enable_compilation_cache()
    report = simulate_recording(
        recording,
        results=results,
        params=params,
        config=config,
        controller=controller,
        substeps=substeps,
        out=out,
        mass=mass,
        member=member,
    )
    typer.echo(format_simulation(report))
    typer.echo(f"files: {', '.join(str(p) for p in report.files.values())}")


@contextmanager
def _stage_progress(quiet: bool, console: Any = None) -> Iterator[Any]:
    """A live line on stderr while a diagnosis runs: its stage, what it is doing, the time
    since it started (rich); yields the ``on_stage`` callback, or None when ``quiet`` or
    stderr is not a terminal (a log file gets no control characters)."""
    from rich.console import Console
    from rich.progress import Progress, SpinnerColumn, TextColumn, TimeElapsedColumn

    console = console or Console(stderr=True)
    if quiet:
        yield None
        return
    if not console.is_terminal:
        # a log file: one plain line per stage change and per candidate, no control codes
        def log_line(event: Any) -> None:
            typer.echo(f"{event.elapsed_s:8.1f} s  {event.stage}: {event.detail}", err=True)

        yield log_line
        return
    columns = (SpinnerColumn(), TimeElapsedColumn(), TextColumn("{task.description}"))
    with Progress(*columns, console=console, transient=True) as bar:
        task = bar.add_task("starting", total=None)
        last = [""]

        def on_stage(event: Any) -> None:
            if event.stage != last[0] and last[0]:
                bar.console.print(
                    f"[dim]{event.elapsed_s:7.1f} s[/] done: {last[0]}", highlight=False
                )
            last[0] = event.stage
            bar.update(task, description=f"[bold]{event.stage}[/]: {event.detail}")

        yield on_stage


@app.command()
def diagnose(
    recordings: Annotated[
        list[Path],
        typer.Argument(
            metavar="RECORDING...",
            help="Recording (.h5 layout v1 or .csv); several of one plant: the diagnosis "
            "across them on their joint fit (docs/joint.md)",
        ),
    ],
    config: DefaultConfigOpt = None,
    out: Annotated[Path, typer.Option(help="Output folder")] = Path("diagnosis"),
    validation: Annotated[
        Path | None, typer.Option(help="Second recording for the held-out check")
    ] = None,
    alpha: Annotated[float | None, typer.Option(help="Family-wise significance level")] = None,
    max_terms: Annotated[int | None, typer.Option(help="Most terms to add")] = None,
    time_limit: Annotated[
        float | None,
        typer.Option(
            help=f"Seconds for the whole diagnosis (default {DIAGNOSE_TIME_LIMIT:g}, or "
            "\\[diagnose].time_limit; inf: none); what it leaves out is reported first"
        ),
    ] = None,
    quiet: Annotated[bool, typer.Option("--quiet", "-q", help="No progress display")] = False,
    mass: MassOpt = None,
    joined: Annotated[
        bool,
        typer.Option(
            "--joined",
            help="Several recordings judged as one record: one run of tests, every parameter "
            "shared (the test `fricjax design` proposes, run after the record); without it, "
            "the diagnosis across recordings, which also tests run-to-run drift",
        ),
    ] = False,
) -> None:
    """Locate the mismatch, name the physics left out, model it, show the fit improve.
    Ctrl-C stops it within the fit in flight and writes what was judged (exit 3)."""
    from fricjax.api import config_or_default, diagnose_recording, enable_compilation_cache
    from fricjax.data.recording import read_recording
    from fricjax.report.tables import fmt, p_text

    if joined and len(recordings) < 2:
        raise FricjaxError("--joined: needs two or more recordings")
    if len(recordings) > 1 and not joined:
        _diagnose_across(
            recordings, config, out, validation, alpha, max_terms, time_limit, mass, quiet
        )
        return
    if joined:
        if config is None:
            raise FricjaxError("--config: missing; recordings judged as one record need one")
        target: Any = list(recordings)
    else:
        config = config_or_default(recordings[0], config)
        target = read_recording(recordings[0], mass=mass)  # read once: warnings, diagnosis
        _warn_scale(target, config, mass)
    # most of a cold diagnosis is compilation; a later record of the same length and
    # config (data are arguments, not constants) loads the programs instead
    enable_compilation_cache()
    stop = threading.Event()
    with _stage_progress(quiet) as on_stage:
        diag, paths = _stoppable(
            lambda: diagnose_recording(
                target,
                config,
                out=out,
                validation=validation,
                mass=mass,
                overrides={"alpha": alpha, "max_terms": max_terms, "time_limit": time_limit},
                on_stage=on_stage,
                stop=stop,
            ),
            stop,
        )
    headline = diag.clock.headline()
    if headline:
        typer.echo(headline)  # before any verdict: the limit and what it left untested
    if not diag.findings and diag.clock.skipped:
        # cut short: never "nothing is missing"
        typer.echo("nothing found among the candidates tested")
    elif not diag.findings:
        typer.echo("no missing physics found (residual consistent with noise)")
    for f in diag.findings:
        names = " or ".join(f.members)
        typer.echo(f"{names}: {p_text(f.p_value)}, dBIC = {fmt(f.delta_bic, 4)}")
        typer.echo(f"  {f.explanation}")
    before, after = diag.fit["before"], diag.fit["after"]
    typer.echo(
        f"EMS {fmt(before['ems'], 6)} -> {fmt(after['ems'], 6)} N^2; output error "
        f"{fmt(before['output_error_cost'], 6)} -> {fmt(after['output_error_cost'], 6)} sigma_x^2"
    )
    typer.echo(f"report: {paths['report']}")
    typer.echo(f"html: {paths['html']}")
    if diag.clock.interrupted:
        raise typer.Exit(EXIT["partial"])


def _stoppable(work: Callable[[], Any], stop: threading.Event) -> Any:
    """Run ``work`` in a worker thread; the first Ctrl-C sets ``stop`` (the work ends its
    fit in flight and returns what it judged), a second one exits at once (status 130).

    The main thread only waits, so it takes the signal at once even while a compiled
    program runs in the worker (a program in the main thread would hold it off until it
    returned)."""
    result: list[Any] = []
    error: list[BaseException] = []
    done = threading.Event()

    def run() -> None:
        try:
            result.append(work())
        except BaseException as err:  # handed to the main thread as it is
            error.append(err)
        finally:
            done.set()

    # a process started in the background by a shell inherits SIGINT ignored: the user's
    # `kill -INT` must still stop it
    signal.signal(signal.SIGINT, signal.default_int_handler)
    worker = threading.Thread(target=run, name="fricjax-diagnose", daemon=True)
    worker.start()
    # an Event, not Thread.join: a KeyboardInterrupt inside join can leave the thread
    # looking finished while it still runs
    while not done.is_set():
        try:
            done.wait(0.2)
        except KeyboardInterrupt:
            if stop.is_set():
                typer.echo("\ninterrupted again: nothing more written", err=True)
                sys.stderr.flush()
                # the worker may be inside a compiled program: leave without joining it
                os._exit(EXIT["interrupted"])
            stop.set()
            typer.echo(
                "\nstopping: the fit in flight ends, then what was judged is written "
                "(Ctrl-C again to quit without it)",
                err=True,
            )
    if error:
        raise error[0]
    return result[0]


def _diagnose_across(
    recordings: list[Path],
    config: Path | None,
    out: Path,
    validation: Path | None,
    alpha: float | None,
    max_terms: int | None,
    time_limit: float | None,
    mass: float | None,
    quiet: bool,
) -> None:
    """``diagnose REC1 REC2 ...``: the diagnosis across recordings (fricjax.diagnose.across)."""
    from fricjax.api import diagnose_recordings, enable_compilation_cache
    from fricjax.report.tables import p_text

    if config is None:
        raise FricjaxError("--config: missing; a diagnosis across recordings needs one")
    if validation is not None:
        raise FricjaxError(
            "--validation: with several recordings each is held out in turn; give no --validation"
        )
    enable_compilation_cache()

    with _stage_progress(quiet) as on_stage:
        diag, paths = diagnose_recordings(
            list(recordings),
            config,
            out=out,
            mass=mass,
            overrides={"alpha": alpha, "max_terms": max_terms, "time_limit": time_limit},
            on_stage=on_stage,
        )
    headline = diag.clock.headline()
    if headline:
        typer.echo(headline)  # before any verdict: the limit and what it left untested
    if not diag.findings and diag.clock.skipped:
        typer.echo("nothing found among the candidates tested")
    elif not diag.findings:
        typer.echo("nothing found across the recordings (no shared term, no drift)")
    for f in diag.findings:
        typer.echo(f"{' or '.join(f.members)}: {p_text(f.p_value)}, dBIC = {f.delta_bic:.1f}")
        typer.echo(f"  {f.explanation}")
    typer.echo(f"report: {paths['report']}")
    typer.echo(f"html: {paths['html']}")


@app.command()
def design(
    recording: RecArg,
    config: ConfigOpt,
    diagnosis: Annotated[
        Path | None,
        typer.Option(
            help="Folder of a diagnosis of RECORDING (its models.h5): separate its models"
        ),
    ] = None,
    results: Annotated[
        Path | None,
        typer.Option(
            help="Identify results of RECORDING: determine its parameters (--for identify)"
        ),
    ] = None,
    purpose: Annotated[
        str,
        typer.Option(
            "--for",
            help="discriminate (the diagnosis' rival models, needs --diagnosis) or identify "
            "(the parameters the record does not determine, needs --results)",
        ),
    ] = "discriminate",
    focus: Annotated[
        str | None,
        typer.Option(
            help="--for identify: parameters to determine, comma-separated (default: those "
            "the identify summary calls undetermined)"
        ),
    ] = None,
    out: Annotated[
        Path, typer.Option(help="The profile to run (CSV; .png and .json beside)")
    ] = Path("next_test.csv"),
    candidates: Annotated[
        str | None,
        typer.Option(
            help="Models to separate, comma-separated: 'base' and catalogue names "
            "(default: the diagnosis' first ambiguity set)"
        ),
    ] = None,
    limits: Annotated[
        str | None,
        typer.Option(
            help="F_max,x_range,v_max: peak input \\[unit of u], travel (lo:hi or a length) "
            "\\[m], peak speed \\[m/s]; an empty field keeps what the record did"
        ),
    ] = None,
    duration: Annotated[
        float | None, typer.Option(help="Length of the new test \\[s] (default the record's)")
    ] = None,
    starts: Annotated[
        int | None,
        typer.Option(
            help="Optimiser starts in one batch, the first three the standard tests "
            "(default: fricjax.design.DesignSettings)",
            min=1,
        ),
    ] = None,
    steps: Annotated[
        int | None,
        typer.Option(help="Gradient steps per start (default: DesignSettings)", min=1),
    ] = None,
    seed: Annotated[int, typer.Option(help="PRNG seed of the starts", **SEED_RANGE)] = 0,
    mass: MassOpt = None,
) -> None:
    """Design the next test: an input profile within the rig's limits under which the
    diagnosis' rival models predict motions that differ most, in the record's noise, after
    each has refitted what it can; or (--for identify) that determines the parameters the
    record does not (docs/design.md)."""
    from fricjax.api import design_test, enable_compilation_cache
    from fricjax.design import DesignSettings
    from fricjax.report.design import format_design, format_precision

    if purpose not in ("discriminate", "identify"):
        raise FricjaxError(f"--for: {purpose!r}: discriminate or identify")
    if purpose == "identify" and (results is None or diagnosis is not None):
        raise FricjaxError("--for identify: give --results (identify's), not --diagnosis")
    if purpose == "discriminate" and (diagnosis is None or results is not None):
        raise FricjaxError(
            "--for discriminate: give --diagnosis, not --results (or --for identify)"
        )
    enable_compilation_cache()

    def listed(text: str | None) -> list[str] | None:
        return None if text is None else [c.strip() for c in text.split(",") if c.strip()]

    from rich.console import Console

    console = Console(stderr=True)
    with console.status("designing the test: one batch of starts, by gradient"):
        result, paths = design_test(
            recording,
            config,
            diagnosis,
            results=results,
            out=out,
            candidates=listed(candidates),
            focus=listed(focus),
            limits=limits,
            duration=duration,
            settings=DesignSettings(
                **{k: v for k, v in {"starts": starts, "steps": steps}.items() if v}, seed=seed
            ),
            mass=mass,
        )
    typer.echo(format_design(result) if purpose == "discriminate" else format_precision(result))
    typer.echo(f"files: {', '.join(str(p) for p in paths.values())}")


@app.command("init-config")
def init_config_cmd(
    recording: RecArg,
    out: Annotated[Path, typer.Option("--out", "-o", help="Config to write (.toml)")],
    drive: Annotated[
        str,
        typer.Option(help="measured (measured_input on /F, else /u) | harmonic (harmonic_drive)"),
    ] = "measured",
    friction: Annotated[
        str, typer.Option(help="Comma-separated: coulomb (required), viscous, stribeck")
    ] = "coulomb,viscous",
    harmonics: Annotated[int, typer.Option(help="Harmonics of a harmonic drive")] = 3,
    axis: Annotated[
        str | None, typer.Option(help="linear | rotary (default: the recording's attr)")
    ] = None,
    mass: MassOpt = None,
    u_unit: Annotated[
        str | None,
        typer.Option(
            help="Unit of /u (default: the recording's; a CSV has none); N (N*m rotary) "
            "says u is a measured force, its gain fixed at 1"
        ),
    ] = None,
    force: Annotated[bool, typer.Option(help="Overwrite an existing --out")] = False,
) -> None:
    """Write a commented starting config with bounds from the recording's own scale."""
    from fricjax.api import init_config

    _, path = init_config(
        recording,
        out,
        drive=drive,
        friction=friction,
        harmonics=harmonics,
        mass=mass,
        axis=axis,
        u_unit=u_unit,
        force=force,
    )
    typer.echo(f"wrote {path}; next: fricjax identify {recording} --config {path}")


@app.command()
def merge(
    motion: Annotated[Path, typer.Argument(help="Motion recording (.h5 or .csv with t,x)")],
    sensor: Annotated[Path, typer.Argument(help="Sensor CSV with a t column, any rate")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Merged recording (.h5 or .csv)")],
    column: Annotated[str, typer.Option(help="Sensor column to bring over")] = "F",
    as_signal: Annotated[
        str, typer.Option("--as", help="F (force on the body, N) or u (drive input)")
    ] = "F",
    u_unit: Annotated[str, typer.Option(help="Unit of u when --as u")] = "",
    mass: MassOpt = None,
) -> None:
    """Resample a second sensor onto the motion's time grid (anti-alias + cubic spline)."""
    from fricjax.api import merge_sensor_file

    rec, path = merge_sensor_file(
        motion, sensor, out, column=column, as_signal=as_signal, u_unit=u_unit, mass=mass
    )
    typer.echo(f"wrote {path}: {rec.n} samples; {rec.notes}")


bench_app = typer.Typer(
    no_args_is_help=True,
    help="Benchmarks on the paper twin: Markdown + PNG reports (default benchmarks/results/).",
)
app.add_typer(bench_app, name="bench")
OutDirOpt = Annotated[Path, typer.Option("--out", help="Report folder")]


@bench_app.command("convergence")
def bench_convergence(
    recording: Annotated[Path, typer.Argument(help="Twin recording")] = Path("data/paper_twin.h5"),
    config: ConfigOpt = Path("configs/paper.toml"),
    out: OutDirOpt = Path("benchmarks/results"),
    methods: Annotated[str, typer.Option(help="Full-space methods, comma-separated")] = (
        "rdsa,csaa,dsaa,dsaa-gray,csaa-gauss"
    ),
    seeds: Annotated[int, typer.Option(help="Seeds per method")] = 10,
    chains: Annotated[int, typer.Option(help="Chains per run")] = 32,
    steps_per_level: Annotated[int, typer.Option(help="Steps per level")] = 20,
    levels: Annotated[int, typer.Option(help="Levels per run (no early stop)")] = 300,
    separable: Annotated[
        bool | None,
        typer.Option("--separable/--no-separable", help="Variable projection (default: if any)"),
    ] = None,
    refine: Annotated[bool, typer.Option(help="Also report the LM refiner")] = True,
) -> None:
    """RDSA/CSAA/DSAA at one evaluation budget over seeds: traces, success, errors, floor."""
    from fricjax.bench.convergence import (
        ConvergenceSettings,
        convergence_benchmark,
        convergence_table,
    )

    settings = ConvergenceSettings(
        methods=tuple(m.strip() for m in methods.split(",") if m.strip()),
        seeds=seeds,
        chains=chains,
        steps_per_level=steps_per_level,
        levels=levels,
        separable=separable,
        refine=refine,
    )

    def progress(label: str, run) -> None:
        typer.echo(
            f"{label} seed {run.seed}: raw {run.raw_cost:.6g}, refined {run.cost:.6g} N², "
            f"{run.total_time:.2f} s",
            err=True,
        )

    result, paths = convergence_benchmark(
        recording, config, out_dir=out, settings=settings, on_run=progress
    )
    typer.echo(convergence_table(result))
    typer.echo(f"report: {paths['report']}")


@bench_app.command("peers")
def bench_peers(
    recording: Annotated[Path, typer.Argument(help="Twin recording")] = Path("data/paper_twin.h5"),
    config: ConfigOpt = Path("configs/paper.toml"),
    out: OutDirOpt = Path("benchmarks/results"),
    seeds: Annotated[int, typer.Option(help="Seeds: fricjax and DE without polish")] = 10,
    slow_seeds: Annotated[int, typer.Option(help="Seeds: DE + polish, dual annealing, CMA")] = 3,
    time_cap: Annotated[float, typer.Option(help="Seconds per peer run at most")] = 60.0,
    separable: Annotated[
        bool | None,
        typer.Option("--separable/--no-separable", help="fricjax separable path (default: if any)"),
    ] = None,
) -> None:
    """fricjax against scipy DE / dual annealing and pycma: time and evaluations to target."""
    from fricjax.bench.peers import PeerSettings, peers_benchmark, peers_table

    settings = PeerSettings(
        seeds=seeds, slow_seeds=slow_seeds, time_cap=time_cap, separable=separable
    )

    def progress(name: str, run) -> None:
        typer.echo(
            f"{name} seed {run.seed}: {run.cost:.6g} N², {run.evals} evals, "
            f"{run.seconds:.2f} s ({run.note})",
            err=True,
        )

    result, path = peers_benchmark(
        recording, config, out_dir=out, settings=settings, on_run=progress
    )
    typer.echo(peers_table(result))
    typer.echo(f"report: {path}")


@bench_app.command("throughput")
def bench_throughput(
    recording: Annotated[Path, typer.Argument(help="Twin recording")] = Path("data/paper_twin.h5"),
    config: ConfigOpt = Path("configs/paper.toml"),
    out: OutDirOpt = Path("benchmarks/results"),
    subprocesses: Annotated[
        bool, typer.Option(help="Also measure 2 host devices and the YNN flag")
    ] = True,
) -> None:
    """Cost evaluations/s against chain count (f64, f32, numpy), compile, memory, peak."""
    from fricjax.bench.throughput import (
        ThroughputSettings,
        throughput_benchmark,
        throughput_table,
    )

    result, path = throughput_benchmark(
        recording,
        config,
        out_dir=out,
        settings=ThroughputSettings(subprocess=subprocesses),
        on_line=lambda line: typer.echo(line, err=True),
    )
    typer.echo(throughput_table(result))
    typer.echo(f"report: {path}")


def _version(value: bool) -> None:
    if value:
        from importlib import metadata

        typer.echo(f"fricjax {metadata.version('fricjax')}")
        raise typer.Exit(0)


@app.callback()
def _root(
    version: Annotated[
        bool,
        typer.Option(
            "--version", callback=_version, is_eager=True, help="Print the version and exit"
        ),
    ] = False,
) -> None:
    """Identify friction models from recorded motion (JAX), and find what they leave out.

    Exit status:
    0 done;
    1 the machine refused an output (disk full, folder not writable);
    2 a mistake in the command line or an input (one line names it);
    3 interrupted (Ctrl-C) after writing partial results (marked interrupted);
    130 interrupted before anything was written.
    """


def _usage_line(err: TyperException) -> str:
    """One line for a command-line mistake: ``command line: fricjax CMD: what is wrong``."""
    ctx = getattr(err, "ctx", None)
    command = f"{ctx.command_path}: " if ctx is not None else ""
    return " ".join(f"command line: {command}{err.format_message()}".split())


def main(argv: list[str] | None = None) -> None:
    """Entry point: one line on stderr for every refusal, and a distinct exit status.

    Exit statuses (one place: :data:`EXIT`): 0 done; 1 the machine refused an output
    (:class:`OutputFault`: disk full, read-only folder); 2 a user mistake (command line,
    input file, config); 3 interrupted by Ctrl-C after partial results were written (the
    file says ``interrupted``); 130 (128 + SIGINT, the shell's convention) interrupted
    before anything was written. ``fricjax`` alone (or ``fricjax bench``) prints the
    help and exits 0: asking what the tool does is not a mistake.
    """
    try:
        # Outside standalone mode typer returns the code of a typer.Exit (and turns
        # Ctrl-C into 130) instead of calling sys.exit, and raises usage errors to here.
        code = app(args=argv, prog_name="fricjax", standalone_mode=False)
    except NoArgsIsHelpError as err:
        typer.echo(err.format_message())
        sys.exit(EXIT["ok"])
    except TyperException as err:  # usage mistakes: unknown option, bad value, ...
        typer.echo(f"error: {_usage_line(err)}", err=True)
        sys.exit(EXIT["mistake"])
    except FricjaxError as err:
        typer.echo(f"error: {err}", err=True)
        sys.exit(EXIT["mistake"])
    except OutputFault as err:
        typer.echo(f"error: {err}", err=True)
        sys.exit(EXIT["machine"])
    except (KeyboardInterrupt, Abort):
        typer.echo("interrupted", err=True)
        _exit_now(EXIT["interrupted"])
    if code == EXIT["interrupted"]:
        typer.echo("interrupted", err=True)
    if code in (EXIT["interrupted"], EXIT["partial"]):
        _exit_now(code)
    if isinstance(code, int) and code != 0:
        sys.exit(code)


def _exit_now(code: int) -> None:
    """End an interrupted run at once: the interpreter's teardown would wait for (or,
    with XLA still compiling or running in a worker thread, crash under) work the user
    asked to stop. Every output is already complete on disk (written atomically)."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    main()
