"""Validation of an identified model on a recording: equation error and simulation error.

Equation error, in the IDIM sense (Gautier; Janot, Gautier & Brunot 2019 for EMPS). With
``τ`` the *measured* force on the actuation side and ``τ̂`` the model's prediction of it,

* models with a recorded input (``measured_input``, F_p = g·u − offset):
  ``τ = g·u`` (e.g. gτ·vir on EMPS) and ``τ̂ = m·a + F_f(v) + offset``;
* models without one (harmonic drive, seed eq. 4): ``τ = m·a`` (the measured force of seed
  eq. 11) and ``τ̂ = F_p − F_f``.

Either way ``τ − τ̂ = ±r`` with ``r`` the equation-error residual of seed eq. (11) on the
preprocessed recording (same ``[preprocess]`` as the identification). Optionally both are
low-passed and decimated by ``q`` (:mod:`fricjax.data.decimate`), as the IDIM-LS recipe
does with every column of its observation matrix. Reported over the m kept samples:

    relative error  ‖D r‖ / ‖D τ‖ [-]     error norm ‖D r‖ [N]
    error std       std(D r) [N]          EMS  mean((D r)²) [N²]   (= identify's EMS at q = 1)

Simulation error: the model is simulated and compared with the record exactly as
``fricjax simulate`` does (:func:`fricjax.simulation.simulate_against`: from the first kept
sample, with the preprocessed velocity there, the trimmed ends left out), reported as
``100·‖y_sim − y‖/‖y‖`` [%] for y = position x, velocity v and acceleration a and, in
closed loop, the actuation force g·u. A rig with a pure integrator in the plant runs in closed
loop; simulated open loop from the recorded input it drifts (every force error integrates
twice), so a recording with a reference ``/r`` and a given controller is re-simulated in
closed loop (:mod:`fricjax.model.closed_loop`) with the recorded input not explained by the
feedback law added as an external input (the EMPS pulses); otherwise the model is
simulated open loop from the recorded input (:func:`fricjax.model.simulate.simulate`).

:func:`fit_simulation_error` identifies by closed-loop *simulation* error instead
(Levenberg–Marquardt on ``g·(ν_sim(θ) − u)``, the DIDIM idea of Gautier, Janot &
Vandanjon 2013), for comparison with equation-error identification.
"""

from __future__ import annotations

import json
import math
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from fricjax.config import Config, load_config, parse_config
from fricjax.data.decimate import antialias_kernel, check_factor, decimate
from fricjax.data.recording import Recording, read_recording
from fricjax.errors import FricjaxError, where
from fricjax.io.atomic import check_outputs, write_text_atomic
from fricjax.limits import check_decimation
from fricjax.model.closed_loop import CascadePD, input_disturbance, simulate_closed_loop
from fricjax.model.simulate import simulate
from fricjax.problem import needs_input
from fricjax.refine import RefineSettings, refine, uncertainty
from fricjax.simulation import param_values, problem_for, simulate_against, trx

__all__ = [
    "EquationMetrics",
    "SimulationFit",
    "SimulationMetrics",
    "Validation",
    "equation_error",
    "fit_simulation_error",
    "format_validation",
    "initial_state",
    "open_loop_rmse",
    "parse_controller",
    "simulation_error",
    "simulation_rmse",
    "validate_model",
    "validate_recording",
]


class EquationMetrics(NamedTuple):
    """Equation error in the IDIM sense (module docstring); forces in N.

    rel_error: ‖D r‖/‖D τ‖ [-]; error_norm: ‖D r‖ [N]; error_std: std(D r) [N];
    ems: mean((D r)²) [N²]; n: samples kept (after trim and decimation); decimate: q;
    tau: "g·u" or "m·a", what τ is.
    """

    rel_error: float
    error_norm: float
    error_std: float
    ems: float
    n: int
    decimate: int
    tau: str


class SimulationMetrics(NamedTuple):
    """Relative simulation errors 100·‖y_sim − y‖/‖y‖ [%] over the untrimmed samples.

    mode: "closed-loop" or "open-loop"; force: None in open loop (the input is imposed).
    """

    mode: str
    position: float
    velocity: float
    acceleration: float
    force: float | None
    n: int


class Validation(NamedTuple):
    """Everything :func:`validate_model` measured on one recording."""

    recording: str
    params: dict[str, float]
    equation: EquationMetrics
    simulation: SimulationMetrics | None

    def as_dict(self) -> dict[str, Any]:
        return {
            "recording": self.recording,
            "params": self.params,
            "equation": self.equation._asdict(),
            "simulation": None if self.simulation is None else self.simulation._asdict(),
        }


# ---------------------------------------------------------------------------- helpers


# ---------------------------------------------------------------------------- metrics


def equation_error(
    rec: Recording,
    cfg: Config,
    params: Mapping[str, float],
    *,
    decimate_by: int = 1,
    source: str = "params",
) -> EquationMetrics:
    """IDIM equation-error metrics of ``params`` on ``rec`` (module docstring)."""
    q = check_factor(decimate_by, "validate")
    problem = problem_for(rec, cfg, params, source)
    check_decimation(q, problem.n, "validate")
    p = param_values(problem, params, source)
    sig = problem.signals
    a = jnp.asarray(problem.a)
    r = problem.model.residual(p, sig, a)
    if needs_input(problem.model):
        tau, label = p["gain"] * sig.u, "g·u"
    else:
        tau, label = p["mass"] * a, "m·a"
    if q > 1:
        k = jnp.asarray(antialias_kernel(q))
        r, tau = decimate(r, k, q), decimate(tau, k, q)
    r, tau = np.asarray(r), np.asarray(tau)
    norm = float(np.linalg.norm(r))
    return EquationMetrics(
        rel_error=norm / float(np.linalg.norm(tau)),
        error_norm=norm,
        error_std=float(np.std(r)),
        ems=float(np.mean(r**2)),
        n=int(r.shape[0]),
        decimate=q,
        tau=label,
    )


def simulation_error(
    rec: Recording,
    cfg: Config,
    params: Mapping[str, float],
    *,
    controller: CascadePD | None = None,
    substeps: int = 4,
    source: str = "params",
) -> SimulationMetrics:
    """The relative errors of :func:`fricjax.simulation.simulate_against`: the same
    simulation and comparison as ``fricjax simulate`` (from the first kept sample, with the
    preprocessed velocity there, over the untrimmed samples), so the two commands report
    the same position error for the same model and recording."""
    report = simulate_against(
        rec, cfg, params, controller=controller, substeps=substeps, source=source
    )
    m = report.metrics
    return SimulationMetrics(
        mode=report.mode,
        position=m["x"].relative,
        velocity=m["v"].relative,
        acceleration=m["a"].relative,
        force=m["actuation"].relative if "actuation" in m else None,
        n=int(report.t.shape[0]),
    )


#: Samples of the output a benchmark simulation may use to set its initial state; scored
#: from there on. nonlinearbenchmark.org's EMPS split (``nonlinear_benchmarks.EMPS()``,
#: ``state_initialization_window_length = 20``) gives the model u and y[:20] and scores
#: y[20:].
BENCHMARK_INIT = 20


def simulation_rmse(
    y_sim: Float[np.ndarray, " n"], y: Float[np.ndarray, " n"], n_init: int = BENCHMARK_INIT
) -> float:
    """``sqrt(mean((y_sim[k] − y[k])²))`` over ``k ≥ n_init`` [unit of y]: the RMSE of the
    nonlinear system-identification benchmarks (nonlinearbenchmark.org), whose first
    ``n_init`` samples only initialise the simulation and are not scored."""
    y_sim, y = np.asarray(y_sim, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if y_sim.shape != y.shape or y.ndim != 1 or not 0 <= n_init < y.shape[0]:
        raise FricjaxError(
            f"{where('simulation_rmse', 'y')}: need two equal 1-D signals longer than "
            f"n_init = {n_init}, got shapes {y_sim.shape} and {y.shape}"
        )
    return float(np.sqrt(np.mean((y_sim[n_init:] - y[n_init:]) ** 2)))


def initial_state(
    t: Float[np.ndarray, " n"], x: Float[np.ndarray, " n"], n_init: int = BENCHMARK_INIT
) -> tuple[float, float]:
    """``(x0 [m], v0 [m/s])`` at ``t[0]`` from the first ``n_init`` samples only: the value
    and slope of the least-squares quadratic through them (a first difference would carry
    the noise of two samples divided by dt; the quadratic follows a constant acceleration
    over the window, which at 1 kHz and n_init = 20 spans 19 ms)."""
    k = max(min(int(n_init), len(x)), 3)
    tau = np.asarray(t[:k], dtype=np.float64) - float(t[0])
    _, c1, c0 = np.polyfit(tau, np.asarray(x[:k], dtype=np.float64), 2)
    return float(c0), float(c1)


def open_loop_rmse(
    rec: Recording,
    cfg: Config,
    params: Mapping[str, float],
    *,
    n_init: int = BENCHMARK_INIT,
    substeps: int = 4,
    source: str = "params",
) -> float:
    """Open-loop simulation RMSE [m] of the position, as nonlinearbenchmark.org scores a
    model on a test record (EMPS: DATA_EMPS_PULSES, u = vir, y = qm).

    The model is simulated (:func:`fricjax.model.simulate.simulate`) from the recorded input
    ``/u`` alone over the whole record, its state set once at ``t[0]`` from ``x[:n_init]``
    (:func:`initial_state`); the position is never fed back. Score:
    :func:`simulation_rmse` of ``x_sim`` against the recorded ``/x`` over ``k ≥ n_init``.
    """
    if rec.u is None:
        raise FricjaxError(
            f"{where(rec.name or None, '/u')}: an open-loop simulation needs a recorded input"
        )
    problem = problem_for(rec, cfg, params, source)
    p = param_values(problem, params, source)
    x0, v0 = initial_state(rec.t, rec.x, n_init)
    traj = simulate(
        problem.model, p, jnp.asarray(rec.t), x0, v0, jnp.asarray(rec.u), substeps=substeps
    )
    return simulation_rmse(np.asarray(traj.x), np.asarray(rec.x), n_init)


def validate_model(
    rec: Recording,
    cfg: Config,
    params: Mapping[str, float],
    *,
    decimate_by: int = 1,
    controller: CascadePD | None = None,
    simulate_run: bool = True,
    substeps: int = 4,
    source: str = "params",
) -> Validation:
    """Equation-error metrics and (``simulate_run``) simulation-error metrics on ``rec``."""
    eq = equation_error(rec, cfg, params, decimate_by=decimate_by, source=source)
    sim = (
        simulation_error(rec, cfg, params, controller=controller, substeps=substeps, source=source)
        if simulate_run
        else None
    )
    return Validation(rec.path or rec.name, {k: float(v) for k, v in params.items()}, eq, sim)


# ---------------------------------------------------------------------------- CLI level


def parse_controller(text: str | None) -> CascadePD | None:
    """``"emps"`` or ``"kp=160.18,kv=243.45[,u_max=10]"`` → :class:`CascadePD` (None → None)."""
    if text is None or not text.strip():
        return None
    if text.strip().lower() == "emps":
        from fricjax.model.closed_loop import EMPS_CONTROLLER

        return EMPS_CONTROLLER
    values: dict[str, float] = {}
    for pair in text.split(","):
        key, sep, value = (s.strip() for s in pair.partition("="))
        if not sep or key not in CascadePD._fields:
            raise FricjaxError(
                f"--controller: {pair.strip()!r} is not one of kp=…, kv=…, u_max=… (or 'emps')"
            )
        try:
            values[key] = float(value)
        except ValueError:
            raise FricjaxError(f"--controller: {key}: not a number ({value!r})") from None
    for key in ("kp", "kv"):
        if key not in values:
            raise FricjaxError(f"--controller: {key}: missing (give kp=…,kv=…[,u_max=…])")
    if values.get("u_max", 1.0) <= 0:
        raise FricjaxError(f"--controller: u_max: must be > 0, got {values['u_max']:g}")
    return CascadePD(**values)


def config_from_results(path: Path) -> Config:
    from fricjax.io.results import read_results

    text = str(read_results(path).attrs.get("config", ""))
    if not text.strip():
        raise FricjaxError(f"{where(path, 'attr config')}: empty; give --config")
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise FricjaxError(f"{where(path, 'attr config')}: invalid TOML ({err})") from None
    return parse_config(raw, source=f"{path}: attr config", text=text)


def read_params(
    path: str | Path, *, member: int | None = None, recording: Recording | None = None
) -> dict[str, float]:
    """Named parameter values from TOML/JSON (``name = value``) or a results file.

    A joint results file (:mod:`fricjax.joint`) gives one recording's parameters: those of
    ``member`` (1-based, the order the recordings were given), else of the member whose
    data are ``recording``'s (same sha256); neither is refused in one line, as is a
    ``member`` given for anything but a joint file."""
    path = Path(path)
    if not path.exists():
        raise FricjaxError(f"{where(path)}: parameter file not found")
    suffix = path.suffix.lower()
    try:
        if suffix in (".h5", ".hdf5"):
            from fricjax.io.results import read_results

            runs = read_results(path).runs
            objectives = {str(r.attrs.get("objective", "")) for r in runs}
            if len(objectives) > 1:
                raise FricjaxError(
                    f"{where(path, 'runs')}: mixes objectives ({'; '.join(sorted(objectives))}) "
                    "whose costs are not comparable; write one objective per file"
                )
            best = min(runs, key=lambda r: r.cost)
            return _member_params(path, best, member, recording)
        if suffix == ".json":
            raw: Any = json.loads(path.read_text(encoding="utf-8"))
        elif suffix == ".toml":
            raw = tomllib.loads(path.read_text(encoding="utf-8"))
            raw = raw.get("params", raw)
        else:
            raise FricjaxError(f"{where(path)}: parameters must be .toml, .json or results .h5")
    except (json.JSONDecodeError, tomllib.TOMLDecodeError) as err:
        raise FricjaxError(f"{where(path)}: cannot parse ({err})") from None
    except UnicodeDecodeError as err:
        raise FricjaxError(f"{where(path)}: not UTF-8 text (byte {err.start})") from None
    except OSError as err:
        raise FricjaxError(f"{where(path)}: cannot read ({err.strerror})") from None
    if member is not None:
        raise FricjaxError(
            f"--member: {path} is not a joint results file; --member picks a recording of one"
        )
    if not isinstance(raw, dict):
        raise FricjaxError(
            f"{where(path)}: top level must be a table of name = value, got "
            f"{type(raw).__name__} {json.dumps(raw)[:40] if suffix == '.json' else repr(raw)}"
        )
    out = {}
    for key, value in raw.items():
        if isinstance(value, dict):
            value = value.get("value", value.get("init"))
        number = isinstance(value, int | float) and not isinstance(value, bool)
        if not number:
            raise FricjaxError(f"{where(path, key)}: not a number ({value!r})")
        if not math.isfinite(value):
            raise FricjaxError(f"{where(path, key)}: not a finite number ({value})")
        out[key] = float(value)
    return out


def _member_params(
    path: Path, run: Any, member: int | None, recording: Recording | None
) -> dict[str, float]:
    """``run.params``, or for a joint run one member's (see :func:`read_params`)."""
    from fricjax.joint import is_joint, member_params, members_of

    if not is_joint(run):
        if member is not None:
            raise FricjaxError(
                f"--member: {path} holds a single-recording fit; --member picks a recording of "
                "a joint one"
            )
        return run.params
    members = members_of(run)
    n = len(members)
    names = ", ".join(f"{k + 1} = {m.get('name', '?')}" for k, m in enumerate(members))
    if member is None and recording is not None:
        sha = recording.sha256()
        found = [k for k, m in enumerate(members) if m.get("sha256") == sha]
        if not found:
            raise FricjaxError(
                f"{where(path)}: a joint fit of {n} recordings ({names}) and "
                f"{recording.path or recording.name} is none of them; give --member K to use "
                "recording K's parameters"
            )
        return member_params(run.params, found[0])
    if member is None:
        raise FricjaxError(
            f"{where(path)}: a joint fit of {n} recordings ({names}), not a single-recording "
            "result; give --member K where the command takes it, or one recording's results"
        )
    if not 1 <= member <= n:
        raise FricjaxError(f"--member: {member} is not a recording of {path} ({names})")
    return member_params(run.params, member - 1)


def validate_recording(
    recording: str | Path,
    results: str | Path,
    *,
    config: str | Path | None = None,
    decimate_by: int = 1,
    controller: CascadePD | None = None,
    simulate_run: bool = True,
    mass: float | None = None,
    out: str | Path | None = None,
    member: int | None = None,
) -> Validation:
    """``fricjax validate``: parameters from ``results`` (a results .h5: its best run; or
    TOML/JSON ``name = value``), config from ``config`` or the one stored in the results
    file; optional JSON report ``out`` (written atomically). A joint results file gives
    the parameters of recording ``member`` (1-based), by default of the member that is
    ``recording`` (same data; :func:`read_params`)."""
    if out is not None:
        inputs = {"recording": recording, "--results": results, "--config": config}
        check_outputs([Path(out)], inputs, "--out")
    results = Path(results)
    rec = read_recording(recording, mass=mass)
    params = read_params(results, member=member, recording=rec)
    if config is not None:
        cfg = load_config(config)
    elif results.suffix.lower() in (".h5", ".hdf5"):
        cfg = config_from_results(results)
    else:
        raise FricjaxError(f"{where(results)}: holds no config; give --config")
    report = validate_model(
        rec,
        cfg,
        params,
        decimate_by=decimate_by,
        controller=controller,
        simulate_run=simulate_run,
        source=str(results),
    )
    if out is not None:
        write_text_atomic(out, json.dumps(report.as_dict(), indent=2) + "\n")
    return report


def format_validation(v: Validation) -> str:
    """Plain-text tables of a :class:`Validation`."""
    from fricjax.report.tables import format_table

    e = v.equation
    dec = f", decimated by {e.decimate}" if e.decimate > 1 else ""
    rows = [
        (f"relative error ‖τ − τ̂‖/‖τ‖ (τ = {e.tau})", f"{100 * e.rel_error:.3f} %"),
        ("error norm [N]", f"{e.error_norm:.5g}"),
        ("error std [N]", f"{e.error_std:.4g}"),
        ("EMS [N²]", f"{e.ems:.5g}"),
        ("samples", f"{e.n}{dec}"),
    ]
    text = "equation error\n" + format_table(rows, ("metric", "value"))
    s = v.simulation
    if s is not None:
        srows = [
            ("position", f"{s.position:.4g} %"),
            ("velocity", f"{s.velocity:.4g} %"),
            ("acceleration", f"{s.acceleration:.4g} %"),
        ]
        if s.force is not None:
            srows.append(("force", f"{s.force:.4g} %"))
        text += f"\n\nsimulation error ({s.mode}, 100·‖y_sim − y‖/‖y‖)\n"
        text += format_table(srows, ("signal", "relative error"))
    return text


# ---------------------------------------------------------------------------- DIDIM


class SimulationFit(NamedTuple):
    """Result of :func:`fit_simulation_error`.

    params: every parameter by name; names, value, std: free parameters, their values and
    Gauss–Newton σ (white-residual assumption); cost: Σ (g·(ν_sim − u))² [N²] over the
    untrimmed samples; n_steps: LM iterations; success: LM converged.
    """

    params: dict[str, float]
    names: list[str]
    value: np.ndarray
    std: np.ndarray
    cost: float
    n_steps: int
    success: bool


def fit_simulation_error(
    rec: Recording,
    cfg: Config,
    start: Mapping[str, float],
    controller: CascadePD,
    *,
    substeps: int = 1,
    settings: RefineSettings | None = None,
) -> SimulationFit:
    """Closed-loop output-error identification (DIDIM): minimise over the free θ

        Σ_k (g·ν_sim(k; θ) − g·u(k))²   [N²],   k over the untrimmed samples,

    with ν_sim from :func:`simulate_closed_loop` (reference ``/r``, the external input
    recovered by :func:`input_disturbance`), by Levenberg–Marquardt from ``start`` inside
    the config's box. Needs a model with ``measured_input``, and ``/r`` and ``/u``.
    """
    src = rec.path or rec.name
    if rec.r is None:
        raise FricjaxError(f"{where(src, '/r')}: missing (closed-loop fit needs the reference)")
    if rec.u is None or not needs_input(cfg.model):
        raise FricjaxError(f"{where(src, '/u')}: closed-loop fit needs a recorded input model")
    problem = problem_for(rec, cfg, start)
    spec = problem.spec
    trim = problem.preprocess.trim if problem.preprocess is not None else 0
    t, r, u = jnp.asarray(rec.t), jnp.asarray(rec.r), jnp.asarray(rec.u)
    w = jnp.asarray(input_disturbance(controller, *trx(rec)))
    x0 = float(rec.x[0])
    v0 = float((rec.x[1] - rec.x[0]) / rec.dt)
    model = problem.model

    def residual(theta: Float[Array, " d"]) -> Float[Array, " m"]:
        p = spec.unflatten(theta)
        traj = simulate_closed_loop(model, p, t, r, x0, v0, controller, w, substeps=substeps)
        err = p["gain"] * (traj.u - u)
        return err[trim : rec.n - trim]

    theta0 = np.clip(
        spec.flatten({k: v for k, v in start.items() if k in spec}), spec.lower, spec.upper
    )
    fn = jax.jit(residual)
    out = refine(fn, theta0, spec.lower, spec.upper, settings or RefineSettings(max_steps=50))
    unc = uncertainty(fn, out.x, spec.lower, spec.upper, names=list(spec.free_names))
    x = np.asarray(out.x)
    return SimulationFit(
        params=spec.as_dict(x),
        names=list(spec.free_names),
        value=x,
        std=np.asarray(unc.std),
        cost=float(out.cost_after),
        n_steps=int(out.n_steps),
        success=bool(out.success),
    )
