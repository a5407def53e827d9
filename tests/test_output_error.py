"""Output-error identification with multiple shooting (fricjax.output_error): recovery of
the paper twin's truth against equation error, single against multiple shooting, the
continuity defects, settings and the ``identify`` objective option."""

from __future__ import annotations

import math
import tomllib
from dataclasses import replace
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fricjax import output_error, programs
from fricjax.config import load_config, parse_config
from fricjax.data.recording import Recording
from fricjax.data.twin import DEFAULT_NOISE_STD, PAPER_TRUTH
from fricjax.diagnose.catalogue import candidate
from fricjax.errors import FricjaxError
from fricjax.identify import IdentifySettings, identify
from fricjax.model.simulate import simulate
from fricjax.output_error import (
    TRACES,
    OutputErrorSettings,
    fit_output_error,
    fit_output_error_batch,
    jacobian_at,
    noise_scale,
    output_error_residual,
    segmentation,
)
from fricjax.problem import build_problem, joined
from fricjax.refine import RefineSettings, refine, uncertainty

ROOT = Path(__file__).resolve().parents[1]
EMPS_TRUTH = {"gain": 35.15065188, "offset": -3.1648, "Fc": 20.3935, "Fv": 203.5034, "mass": 95.1}


# ---------------------------------------------------------------------------- settings


def test_segmentation_counts_every_sample_once():
    seg = segmentation(232, 1e-3, OutputErrorSettings(segment_s=0.05))
    # 231 intervals / 50 ms -> S = round(4.62) = 5 segments of ceil(231/5) = 47 intervals
    assert (seg.S, seg.L) == (5, 47) and seg.duration == pytest.approx(0.047)
    np.testing.assert_array_equal(seg.seg * seg.L + seg.pos, np.arange(232))
    np.testing.assert_array_equal(np.bincount(seg.seg), [47, 47, 47, 47, 44])
    assert segmentation(232, 1e-3, OutputErrorSettings()).S == 1  # 0.23 s < 0.5 s
    assert segmentation(232, 1e-3, OutputErrorSettings(segment_s=math.inf)).S == 1
    # ceil leaves no empty segment: 10 intervals asked in 4 -> 4 segments of 3, 3, 3, 1
    assert segmentation(11, 1.0, OutputErrorSettings(segments=4))[:2] == (4, 3)
    assert segmentation(11, 1.0, OutputErrorSettings(segments=7))[:2] == (5, 2)
    assert segmentation(11, 1.0, OutputErrorSettings(segments=50))[:2] == (10, 1)


def test_settings_from_dict_refuses_bad_input_in_one_line():
    s = OutputErrorSettings.from_dict({"segment_s": 0.25, "substeps": 2, "hold": "zero"}, "c.toml")
    assert (s.segment_s, s.substeps, s.hold, s.defect_weight) == (0.25, 2, "zero", 10.0)
    for table, msg in (
        ({"segments_s": 1.0}, "c.toml: [output_error].segments_s: unknown key"),
        ({"substeps": 0}, "c.toml: [output_error].substeps: must be an integer >= 1"),
        ({"substeps": 1.5}, "[output_error].substeps: must be an integer"),
        ({"segments": True}, "[output_error].segments: must be an integer"),
        ({"defect_weight": -1.0}, "[output_error].defect_weight: must be a number > 0"),
        ({"segment_s": "long"}, "[output_error].segment_s: must be a number"),
        ({"x_scale": math.inf}, "[output_error].x_scale: must be finite"),
        ({"hold": "cubic"}, "[output_error].hold: must be one of linear, zero"),
    ):
        with pytest.raises(FricjaxError) as err:
            OutputErrorSettings.from_dict(table, "c.toml")
        assert msg in str(err.value) and "\n" not in str(err.value)


def test_noise_scale_estimates_white_noise_under_smooth_motion():
    t = np.arange(2000) * 1e-3
    rng = np.random.default_rng(3)
    x = 0.05 * np.sin(2 * np.pi * 5 * t) + rng.normal(0.0, 2.4e-5, t.size)
    # the 5 Hz motion adds (2π·5)³·0.05·dt³ ≈ 1.5e-6 m to Δ³x: 1e-3 of the noise's √20·σ
    assert noise_scale(x) == pytest.approx(2.4e-5, rel=0.05)


def test_identify_settings_objective_and_output_error_table():
    default = IdentifySettings.from_tables({})
    assert default.objective == "auto" and default.output_error == OutputErrorSettings()
    tables = {"search": {"objective": "simulation"}, "output_error": {"segment_s": 0.25}}
    s = IdentifySettings.from_tables(tables, source="c.toml")
    assert s.objective == "simulation" and s.output_error.segment_s == 0.25
    cli = IdentifySettings.from_tables({}, overrides={"objective": "simulation"})
    assert cli.objective == "simulation"
    with pytest.raises(FricjaxError, match=r"c.toml: \[search\].objective: must be one of"):
        IdentifySettings.from_tables({"search": {"objective": "output"}}, source="c.toml")
    with pytest.raises(
        FricjaxError, match="--objective: must be one of auto, equation, simulation"
    ):
        IdentifySettings.from_tables({}, overrides={"objective": "output"})
    with pytest.raises(FricjaxError, match=r"c.toml: \[output_error\].hold"):
        IdentifySettings.from_tables({"output_error": {"hold": 1}}, source="c.toml")


# ---------------------------------------------------------------------------- paper twin


def _perturbed(problem) -> np.ndarray:
    """The truth with every free parameter moved by ±5 % (fixed sign pattern), in the box."""
    spec = problem.spec
    truth = spec.flatten({k: v for k, v in PAPER_TRUTH.items() if k in spec})
    signs = np.random.default_rng(1).choice([-1.0, 1.0], truth.size)
    return np.clip(truth * (1.0 + 0.05 * signs), spec.lower, spec.upper)


@pytest.fixture(scope="module")
def twin_fits(twin_problem):
    """Equation error (LM on seed eq. 11) and output error from the same perturbed start."""
    spec = twin_problem.spec
    start = _perturbed(twin_problem)
    ee = refine(twin_problem.residual_fn, start, spec.lower, spec.upper, RefineSettings())
    ee_unc = uncertainty(twin_problem.residual_fn, ee.x, spec.lower, spec.upper)
    oe = fit_output_error(twin_problem, spec.as_dict(start))
    truth = spec.flatten({k: v for k, v in PAPER_TRUTH.items() if k in spec})
    return truth, np.asarray(ee.x), ee_unc, oe


# ~40 s of CPU (compiling LM through the 26-parameter simulator): slow, with the numbers
# measured on 2 cores in the comments; the open-loop tests below cover the same in the fast
# suite on a 4-parameter model.
@pytest.mark.slow
def test_output_error_beats_equation_error_on_the_twin(twin_fits):
    truth, ee_x, ee_unc, oe = twin_fits
    sigma = ee_unc.std
    # the parameters equation error pins to < 10 %: omega, Fp_3..5, Fp_7..9
    well = np.flatnonzero(ee_unc.rel_std < 0.1)
    assert len(well) >= 5
    ee_err = np.sqrt(np.mean(((ee_x - truth)[well] / sigma[well]) ** 2))
    oe_err = np.sqrt(np.mean(((oe.value - truth)[well] / sigma[well]) ** 2))
    # measured: 2.19 σ (equation error: the filtered a is biased) against 1.40 σ, over
    # omega, Fp_3..5, Fp_7..9, phi_4, phi_5
    assert oe_err < 0.85 * ee_err
    # a single well-placed parameter: the fundamental, ~1.8 σ off by equation error
    k = oe.names.index("omega")
    assert abs(oe.value[k] - truth[k]) < 0.3 * abs(ee_x[k] - truth[k])


@pytest.mark.slow
def test_output_error_fits_the_twin_to_the_noise(twin_fits):
    *_, oe = twin_fits
    # x_scale: the 24 µm white noise on x, estimated from Δ³x
    assert oe.x_scale == pytest.approx(DEFAULT_NOISE_STD, rel=0.05)
    # measured 2.31e-5 m: the misfit is the noise (232 samples, 28 fitted unknowns)
    assert 0.7 * DEFAULT_NOISE_STD < oe.position_rms < 1.5 * DEFAULT_NOISE_STD
    assert oe.n_segments == 1 and oe.defect_x == 0.0  # 0.23 s: one segment
    assert oe.cost < 0.05 * oe.cost_start
    assert oe.cost / oe.n_residual == pytest.approx((oe.position_rms / oe.x_scale) ** 2)


# ---------------------------------------------------------------------------- shooting


START = {**EMPS_TRUTH, "Fv": 180.0, "Fc": 25.0, "offset": 0.0, "mass": 110.0}


@pytest.fixture(scope="module")
def open_loop():
    """1.5 s of the EMPS model driven open loop by a two-tone input (no decimation, so the
    equation-error residual fits the short record), 10 µm noise on x; it reverses and
    sticks for a few samples at each reversal. Fitted with 3 segments of 0.467 s."""
    raw = tomllib.loads((ROOT / "configs" / "emps.toml").read_text())
    raw["preprocess"].pop("decimate")
    cfg = parse_config(raw, source="emps (no decimation)")
    t = np.arange(1500) * 1e-3
    u = 2.0 * np.sin(2 * np.pi * 1.5 * t) + np.sin(2 * np.pi * 4.0 * t + 0.3)
    p = {k: jnp.asarray(v) for k, v in EMPS_TRUTH.items()}
    clean = simulate(cfg.model, p, jnp.asarray(t), 0.0, 0.0, jnp.asarray(u), substeps=8)
    assert np.sum(np.asarray(clean.v) == 0.0) >= 5  # stuck samples: stops are exercised
    x = np.asarray(clean.x) + np.random.default_rng(0).normal(0.0, 1e-5, t.size)
    problem = build_problem(Recording(t=t, x=x, u=u, u_unit="V", name="open loop"), cfg)
    return problem, fit_output_error(problem, START, OutputErrorSettings(segments=3))


def test_multiple_shooting_has_the_single_shooting_optimum(open_loop):
    """The 3-segment optimum is a stationary point of plain output error (one segment):
    the Gauss–Newton step of the single-shooting residual from there is ≪ σ."""
    problem, fit = open_loop
    assert fit.success and (fit.n_segments, fit.segment_samples) == (3, 467)
    states = (fit.states_x[:1], fit.states_v[:1])
    single = output_error_residual(problem, fit.params, OutputErrorSettings(segments=1), states)
    assert single.names[-2:] == ["x_seg0", "v_seg0"]
    r, jac = (np.asarray(a) for a in jacobian_at(single.residual, jnp.asarray(single.x0)))
    free = np.flatnonzero(single.free)  # the spec's free parameters, then ξ_0, ν_0
    assert [single.names[i] for i in free[:-2]] == fit.names
    step = np.linalg.lstsq(jac[:, free], -r, rcond=None)[0][: fit.value.size]
    # measured: < 1e-3 σ (the penalty moves the optimum by O(1/w²)); a 2-σ error in θ
    # would give a step of 2 σ
    np.testing.assert_array_less(np.abs(step), 0.01 * fit.std)
    # one continuous trajectory: the single simulation from (ξ_0, ν_0) is the stitched one
    assert float(r @ r) == pytest.approx(fit.cost, rel=1e-5)
    np.testing.assert_allclose(problem.x + fit.x_scale * r, fit.x_sim, rtol=0, atol=1e-9)


def test_structured_jacobian_equals_forward_mode(open_loop):
    """The block-structured Jacobian (d + 2 tangents) is the plain forward-mode one
    (d + 2S tangents)."""
    problem, fit = open_loop
    setup = output_error_residual(problem, fit.params, OutputErrorSettings(segments=3))
    res = setup.residual
    x = jnp.asarray(setup.x0) + 1e-4  # off the record: every defect row is non-zero
    # both in one program: one compilation of the simulator instead of two
    (r, jac), r_ref, ref = eqx.filter_jit(
        lambda m, z: (m.value_and_jacobian(z), m.value(z), jax.jacfwd(m.value)(z))
    )(res, x)
    np.testing.assert_allclose(r, r_ref, rtol=1e-13)
    np.testing.assert_allclose(jac, ref, rtol=0, atol=1e-12 * float(jnp.max(jnp.abs(ref))))


def test_jacobian_along_directions_is_the_whole_one_on_their_columns(open_loop):
    """With the unit rows of two parameters and a zero row as directions (K = 3 of P = 5),
    the structured Jacobian has the whole one's columns for those parameters and for the
    segment states, and exact zeros for the other parameters; the residual is unchanged."""
    problem, fit = open_loop
    setup = output_error_residual(problem, fit.params, OutputErrorSettings(segments=3))
    every = setup.residual
    P, S = every.n_params, every.n_segments
    chosen = [every.names.index("Fc"), every.names.index("mass")]
    dirs = np.zeros((3, P))
    dirs[[0, 1], chosen] = 1.0
    some = eqx.tree_at(lambda m: m.directions, every, jnp.asarray(dirs))
    x = jnp.asarray(setup.x0) + 1e-4  # off the record: every defect row is non-zero
    both = eqx.filter_jit(lambda a, b, z: (a.value_and_jacobian(z), b.value_and_jacobian(z)))
    (r_all, j_all), (r_some, j_some) = jax.device_get(both(every, some, x))
    assert j_some.shape == j_all.shape == (problem.n + 2 * (S - 1), P + 2 * S)
    np.testing.assert_array_equal(r_some, r_all)
    others = [i for i in range(P) if i not in chosen]
    np.testing.assert_array_equal(j_some[:, others], 0.0)
    assert np.all(np.abs(j_all[:, others]).max(axis=0) > 0)  # zero by the directions only
    cols = [*chosen, *range(P, P + 2 * S)]
    atol = 1e-13 * float(np.max(np.abs(j_all)))
    np.testing.assert_allclose(j_some[:, cols], j_all[:, cols], rtol=1e-13, atol=atol)


def test_joined_recordings_are_each_fitted_as_alone_with_shared_parameters(open_loop):
    """Two recordings joined end to end (fricjax.problem.joined): no segment spans the join,
    the join's continuity defect is not fitted (zero rows of r_aug and its Jacobian), and
    every other row, value and derivative, is the one of its own recording alone; the
    parameters' columns are shared."""
    problem, fit = open_loop
    t = np.arange(problem.n + 200) * 1e-3  # trimmed by the preprocessing, then cut to n
    u = np.sin(2 * np.pi * 2.5 * t) - 1.5 * np.cos(2 * np.pi * 0.7 * t)
    p = {k: jnp.asarray(v) for k, v in EMPS_TRUTH.items()}
    clean = simulate(problem.model, p, jnp.asarray(t), 0.03, 0.0, jnp.asarray(u), substeps=8)
    x = np.asarray(clean.x) + np.random.default_rng(1).normal(0.0, 1e-5, t.size)
    raw = tomllib.loads((ROOT / "configs" / "emps.toml").read_text())
    raw["preprocess"].pop("decimate")
    cfg = parse_config(raw, source="emps (no decimation)")
    second = build_problem(Recording(t=t, x=x, u=u, u_unit="V", name="second"), cfg)
    second = replace(
        second,
        t=second.t[: problem.n],
        x=second.x[: problem.n],
        v=second.v[: problem.n],
        a=second.a[: problem.n],
        u=second.u[: problem.n],
    )
    both = joined([problem, second])
    assert both.joins == (problem.n,) and both.n == 2 * problem.n
    np.testing.assert_array_equal(both.t, np.concatenate([problem.t, second.t]))  # own clocks
    assert both.dt == pytest.approx(1e-3, rel=1e-9)
    # one σ_x for the three (estimated, it would be each record's own, or pooled)
    settings = OutputErrorSettings(segments=3, x_scale=1e-5)
    seg = segmentation(both.n, 1e-3, settings, both.joins)
    assert (seg.S, seg.L) == (6, fit.segment_samples)
    np.testing.assert_array_equal(seg.tie, [1, 1, 0, 1, 1])
    assert seg.starts[3] == problem.n and np.all(seg.ends[:3] == problem.n - 1)
    # off the optimum, so that every defect row is non-zero
    setups = [output_error_residual(pb, fit.params, settings) for pb in (problem, second, both)]
    (r1, j1), (r2, j2), (r, j) = (
        (np.asarray(a) for a in jacobian_at(s.residual, jnp.asarray(s.x0) + 1e-4)) for s in setups
    )
    n, P = problem.n, len(problem.spec.names)

    def rows(r_: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # sample rows, position defects, velocity defects of a residual of m samples
        S_ = (r_.shape[0] - m) // 2 + 1
        return r_[:m], r_[m : m + S_ - 1], r_[m + S_ - 1 :]

    s1, s2, s = rows(r1, n), rows(r2, n), rows(r, 2 * n)
    np.testing.assert_allclose(s[0], np.concatenate([s1[0], s2[0]]), rtol=1e-9)
    for k in (1, 2):  # [defects of the first, the join's (zero), defects of the second]
        np.testing.assert_allclose(s[k], np.concatenate([s1[k], [0.0], s2[k]]), rtol=1e-9)
    join_rows = [2 * n + 2, 2 * n + 5 + 2]
    np.testing.assert_array_equal(j[join_rows], 0.0)
    # the parameters' columns: the first recording's rows, then the second's
    scale = float(np.max(np.abs(j[: 2 * n, :P])))
    np.testing.assert_allclose(
        j[: 2 * n, :P], np.concatenate([j1[:n, :P], j2[:n, :P]]), rtol=0, atol=1e-9 * scale
    )


def test_continuity_defects_vanish_at_the_optimum(open_loop):
    _, fit = open_loop
    # measured 1.1e-9 m and 4.5e-10 m/s against 1e-5 m of noise: one trajectory
    assert fit.defect_x < 1e-3 * fit.x_scale
    assert fit.defect_v * 0.467 < 1e-3 * fit.x_scale
    assert fit.position_rms == pytest.approx(1e-5, rel=0.1)


def test_a_warm_start_from_the_fitted_states_starts_at_the_optimum(open_loop):
    """Restarted from a fit's parameters AND segment states, LM starts at that fit's cost
    (the record's states would restart it off the optimum) and never ends above it; a
    state vector of the wrong length is refused."""
    problem, fit = open_loop
    settings = OutputErrorSettings(segments=3)
    again = fit_output_error(problem, fit.params, settings, (fit.states_x, fit.states_v))
    assert again.cost_start == pytest.approx(fit.cost, rel=1e-9)
    assert again.cost <= fit.cost * (1 + 1e-9)
    # the fit from the record's states (free segments, then tied) ended at the tied
    # minimum: the tied fit from there has less than gain_tol [σ_x²] left to gain
    assert fit.cost - again.cost < settings.gain_tol
    cold = output_error_residual(problem, fit.params, settings)
    warm = output_error_residual(problem, fit.params, settings, (fit.states_x, fit.states_v))
    assert not np.allclose(cold.x0, warm.x0)  # the fitted states are not the record's
    np.testing.assert_array_equal(cold.lower, warm.lower)  # and the box stays the record's
    with pytest.raises(FricjaxError, match="2 segment states given for 3 segments"):
        output_error_residual(problem, fit.params, settings, (fit.states_x[:2], fit.states_v[:2]))


@pytest.fixture
def backend_compiles():
    """A list that grows by one entry per XLA compilation while the test runs."""
    seen: list[float] = []

    def listen(event: str, duration: float, **_: object) -> None:
        if event == "/jax/core/compile/backend_compile_duration":
            seen.append(duration)

    jax.monitoring.register_event_duration_secs_listener(listen)
    yield seen
    jax.monitoring.unregister_event_duration_listener(listen)


def test_a_fit_of_the_same_structure_and_shape_is_neither_traced_nor_compiled_again(
    open_loop, backend_compiles
):
    """New start, new data of the same shape and other fixed values reuse the program of
    the fixture's fit: no trace, no XLA compilation (the Jacobian at the optimum included).
    A fit that fixes one more parameter keeps the fixture's 4 Jacobian directions by
    passing ``n_directions`` (its own default would be 3: another program)."""
    problem, fit = open_loop
    settings = OutputErrorSettings(segments=3)
    traces = TRACES.copy()
    noisier = problem.x + np.random.default_rng(7).normal(0.0, 1e-5, problem.n)
    runs = {
        "new start": (problem, {**START, "Fv": 230.0, "mass": 80.0}),
        "new data": (replace(problem, x=noisier), START),
        "Fc fixed": (replace(problem, spec=problem.spec.with_fixed({"Fc": 21.0})), START),
    }
    n_dirs = problem.spec.n_free
    fits = {k: fit_output_error(p, s, settings, n_directions=n_dirs) for k, (p, s) in runs.items()}
    assert TRACES == traces and backend_compiles == []
    # and they are fits: the same optimum from another start, another one on other data
    # (10 µm more noise moves the mass by ~σ, not by its 3-σ tolerance), Fc held at 21 N
    again = fits["new start"]
    assert again.cost == pytest.approx(fit.cost, rel=1e-6)
    i = fit.names.index("mass")
    assert abs(fits["new data"].value[i] - fit.value[i]) < 3 * fit.std[i]
    # 10 µm on top of 10 µm of noise: the misfit and σ_x grow by √2
    assert fits["new data"].position_rms == pytest.approx(math.sqrt(2) * 1e-5, rel=0.1)
    assert fits["new data"].x_scale == pytest.approx(math.sqrt(2) * fit.x_scale, rel=0.1)
    held = fits["Fc fixed"]
    assert held.params["Fc"] == 21.0 and "Fc" not in held.names and held.cost > fit.cost


def test_a_stored_fit_program_gives_the_same_fit_in_a_new_process(open_loop, tmp_path):
    """The program store (fricjax.programs) on the fit: exported once, then loaded by a
    "new process" (the in-memory programs dropped) without a trace, and both give the
    fixture's fit, bit for bit."""
    problem, fit = open_loop
    settings = OutputErrorSettings(segments=3)
    assert programs.set_store(tmp_path) is not None
    try:
        exported = fit_output_error(problem, START, settings)
        assert any(tmp_path.glob("*.jaxexport"))
        for stored in (output_error._fit_rows_jit, output_error.jacobian_at):
            stored.loaded.clear()
        traces = TRACES.copy()
        loaded = fit_output_error(problem, START, settings)
        assert TRACES == traces
    finally:
        programs.set_store(None)
    for other in (exported, loaded):
        assert other.n_steps == fit.n_steps and other.cost == fit.cost
        np.testing.assert_array_equal(other.value, fit.value)
        np.testing.assert_array_equal(other.std, fit.std)


def test_batch_rows_equal_the_fits_whose_spec_fixes_their_pinned_parameters(open_loop):
    """Row b of one batched program (some parameters pinned by the mask) is the single fit
    of the problem whose spec fixes those parameters at the same values."""
    problem, fit = open_loop
    settings = OutputErrorSettings(segments=3)
    spec = problem.spec
    pins = [{}, {"Fc": 21.0}, {"offset": -3.0, "mass": 100.0}]
    starts = np.stack([spec.flatten({**START, **pin}) for pin in pins])
    free = np.array([[q not in pin for q in spec.free_names] for pin in pins])
    rows = fit_output_error_batch(problem, starts, free, settings)
    for pin, row in zip(pins, rows, strict=True):
        fixed = replace(problem, spec=spec.with_fixed(pin))
        # the batch's K (4): one program for the three fixed patterns
        single = fit_output_error(fixed, START, settings, n_directions=spec.n_free)
        assert row.names == single.names and row.success == single.success
        assert row.cost == pytest.approx(single.cost, rel=1e-6)
        np.testing.assert_array_less(np.abs(row.value - single.value), 0.01 * single.std)
        np.testing.assert_allclose(row.std, single.std, rtol=1e-4)
        assert all(row.params[q] == v for q, v in pin.items())
    # the unpinned row is the fixture's own fit, and pinning costs fit quality
    assert rows[0].cost == pytest.approx(fit.cost, rel=1e-9)
    assert rows[1].cost > rows[0].cost and rows[2].cost > rows[0].cost
    # each row restarted from its own end point (parameters and [B, S] states) starts there
    ends = np.stack([spec.flatten(row.params) for row in rows])
    states = (np.stack([r.states_x for r in rows]), np.stack([r.states_v for r in rows]))
    again = fit_output_error_batch(problem, ends, free, settings, states)
    for row, warm in zip(rows, again, strict=True):
        assert warm.cost_start == pytest.approx(row.cost, rel=1e-9)
        assert warm.cost <= row.cost * (1 + 1e-9)


def test_free_only_tangents_give_the_fits_of_every_tangent(open_loop, monkeypatch):
    """Rows fitted with tangents along their fitted parameters only (K = 4, the default:
    the most any row fits) end where the same rows fitted with a tangent for each of the
    P = 5 parameters end (every row's directions the identity, as before directions
    existed): same LM steps, cost, values and σ. Another set of masks with the same K
    runs the same program: no trace."""
    problem, _ = open_loop
    settings = OutputErrorSettings(segments=3)
    spec = problem.spec
    P = len(spec.names)

    def masks(pins: list[dict[str, float]]) -> tuple[np.ndarray, np.ndarray]:
        starts = np.stack([spec.flatten({**START, **pin}) for pin in pins])
        return starts, np.array([[q not in pin for q in spec.free_names] for pin in pins])

    starts, free = masks([{}, {"Fc": 21.0}, {"offset": -3.0, "mass": 100.0}])
    free_only = fit_output_error_batch(problem, starts, free, settings)
    with monkeypatch.context() as m:
        m.setattr(output_error, "_directions", lambda keep, *_: np.stack([np.eye(P)] * len(keep)))
        every = fit_output_error_batch(problem, starts, free, settings)
    for a, b in zip(free_only, every, strict=True):
        assert a.names == b.names and a.n_steps == b.n_steps and a.success
        assert a.cost == pytest.approx(b.cost, rel=1e-9)
        np.testing.assert_allclose(a.value, b.value, rtol=1e-9)
        np.testing.assert_allclose(a.std, b.std, rtol=1e-9)
        np.testing.assert_allclose(a.corr, b.corr, rtol=0, atol=1e-9)
    # K = P with other masks: the program of `every` (the directions are traced)
    traces = TRACES.copy()
    starts, free = masks([{"Fv": 200.0}, {"Fc": 21.0, "Fv": 200.0}, {}])
    rows = fit_output_error_batch(problem, starts, free, settings, n_directions=P)
    assert TRACES == traces
    assert rows[0].params["Fv"] == 200.0 and "Fv" not in rows[0].names
    assert rows[2].cost < rows[0].cost < rows[1].cost  # each pin costs fit quality
    assert rows[2].cost == pytest.approx(free_only[0].cost, rel=1e-9)


def test_batch_refuses_bad_starts_and_masks_in_one_line(open_loop):
    problem, _ = open_loop
    d = problem.spec.n_free
    for starts, free, msg in (
        (np.zeros((2, d + 1)), None, "starts: shape (2, 5), expected (B >= 1, 4)"),
        (np.full((1, d), np.nan), None, "starts: not all finite"),
        (np.ones((2, d)), np.ones((2, d)), "free: must be a bool array of shape (2, 4)"),
    ):
        with pytest.raises(FricjaxError) as err:
            fit_output_error_batch(problem, starts, free)
        assert msg in str(err.value) and "\n" not in str(err.value)
    # a row fits 3 parameters, the model has 5 (gain fixed): K outside [3, 5] is refused
    free = np.array([[True, True, True, False], [True, False, False, False]])
    for k in (2, 6, 3.0):
        with pytest.raises(FricjaxError) as err:
            fit_output_error_batch(problem, np.ones((2, d)), free, n_directions=k)
        msg = "n_directions: must be an integer from 3 (the most parameters a row fits) to 5"
        assert msg in str(err.value) and "\n" not in str(err.value)


@pytest.mark.slow  # ~1 min on 2 cores: three models of the simulator compiled
def test_superset_rows_reproduce_the_fits_of_base_plus_one_term(open_loop):
    """Base + asymmetric friction + Gaussian Stribeck (catalogue terms) as ONE model: the
    row with one term free and the other pinned at its null is the fit of base + that term
    alone. The record holds a direction asymmetry dFc = 2 N, which the first row finds."""
    problem, _ = open_loop
    asym, stribeck = candidate("asymmetric_friction"), candidate("stribeck")
    superset = stribeck.extend_problem(asym.extend_problem(problem))
    truth = {**superset.spec.as_dict(), **EMPS_TRUTH, "asym_dFc": 2.0}
    p = {k: jnp.asarray(v) for k, v in truth.items()}
    t, u = jnp.asarray(problem.t), jnp.asarray(problem.u)
    clean = simulate(superset.model, p, t, problem.x[0], 0.0, u, substeps=8)
    noise = np.random.default_rng(2).normal(0.0, 1e-5, problem.n)
    x = np.asarray(clean.x) + noise
    superset = replace(superset, x=x)
    settings = OutputErrorSettings(segments=3)
    spec = superset.spec
    terms = {"asym": ("asym_dFc", "asym_dFv"), "stribeck": ("stribeck_A", "stribeck_vst")}
    start = spec.flatten(START)  # the terms at their init: amplitudes 0, vst mid-grid
    free = np.array(
        [[q not in terms[other] for q in spec.free_names] for other in ("stribeck", "asym")]
    )
    rows = fit_output_error_batch(superset, np.stack([start, start]), free, settings)
    for row, cand in zip(rows, (asym, stribeck), strict=True):
        alone = cand.extend_problem(replace(problem, x=x))
        single = fit_output_error(alone, START, settings)
        assert row.names == single.names == list(alone.spec.free_names)
        assert row.cost == pytest.approx(single.cost, rel=1e-6)
        np.testing.assert_array_less(np.abs(row.value - single.value), 0.01 * single.std)
    assert rows[0].params["stribeck_A"] == 0.0
    assert all(rows[1].params[q] == 0.0 for q in terms["asym"])
    i = rows[0].names.index("asym_dFc")
    assert abs(rows[0].value[i] - 2.0) < 3 * rows[0].std[i]
    assert rows[0].cost < rows[1].cost  # the asymmetry, not a Stribeck drop, is in the record


@pytest.mark.slow  # ~3 min on 2 cores: the 26-parameter simulator compiled twice
def test_batch_rows_on_the_twin_equal_fits_with_fixed_parameters(twin_problem):
    """On the paper twin (26 free parameters, one segment): three rows of one program, two
    with parameters pinned, against single fits whose spec fixes the same values."""
    spec = twin_problem.spec
    start = _perturbed(twin_problem)
    truth = {k: v for k, v in PAPER_TRUTH.items() if k in spec}
    pins = [{}, {"omega": truth["omega"]}, {"Fc": truth["Fc"], "Fp_6": truth["Fp_6"]}]
    starts = np.stack([spec.flatten({**spec.as_dict(start), **pin}) for pin in pins])
    free = np.array([[q not in pin for q in spec.free_names] for pin in pins])
    rows = fit_output_error_batch(twin_problem, starts, free)
    for pin, row in zip(pins, rows, strict=True):
        fixed = replace(twin_problem, spec=spec.with_fixed(pin))
        single = fit_output_error(fixed, spec.as_dict(start), n_directions=spec.n_free)
        assert row.names == single.names and row.n_steps == single.n_steps
        assert row.cost == pytest.approx(single.cost, rel=1e-6)
        np.testing.assert_array_less(np.abs(row.value - single.value), 0.01 * single.std)


def test_output_error_recovers_the_open_loop_truth(open_loop):
    problem, fit = open_loop
    for k in ("offset", "Fc", "Fv", "mass"):
        i = fit.names.index(k)
        assert abs(fit.value[i] - EMPS_TRUTH[k]) < 3.0 * fit.std[i], k
    # equation error from the same start, on the twice-differentiated 10 µm noise, is far off
    spec = problem.spec
    ee = np.asarray(refine(problem.residual_fn, spec.flatten(START), spec.lower, spec.upper).x)
    i = fit.names.index("mass")
    assert abs(ee[i] - EMPS_TRUTH["mass"]) > 100 * abs(fit.value[i] - EMPS_TRUTH["mass"])


def test_a_constant_input_is_refused(open_loop):
    problem, _ = open_loop
    with pytest.raises(FricjaxError, match="/u: all zero"):
        zero = np.zeros_like(problem.u)
        fit_output_error(replace(problem, u=zero, drive=zero), EMPS_TRUTH)


def test_a_simulation_is_driven_by_the_input_as_recorded():
    """The equation error's u is filtered like m·a ([preprocess].filter_input); the output
    error simulates the body under the input as recorded: a designed multisine with content
    above the filter's cutoff keeps it."""
    t = np.arange(600) * 1e-3
    u = np.sin(2 * np.pi * 3 * t) + 0.5 * np.sin(2 * np.pi * 150 * t)
    raw = tomllib.loads((ROOT / "configs" / "emps.toml").read_text())
    raw["preprocess"].update(filter_input=True, cutoff_hz=50.0)
    raw["preprocess"].pop("decimate")
    cfg = parse_config(raw, source="emps, input filtered")
    pb = build_problem(Recording(t=t, x=1e-3 * np.sin(t), u=u, u_unit="V", name="r"), cfg)
    trim = pb.preprocess.trim
    np.testing.assert_array_equal(pb.drive_input, u[trim : t.size - trim])
    assert np.max(np.abs(pb.u - pb.drive_input)) > 0.3  # the 150 Hz line, filtered out of u
    setup = output_error_residual(pb, EMPS_TRUTH, OutputErrorSettings(segments=1))
    np.testing.assert_array_equal(np.asarray(setup.residual.u)[0, : pb.n], pb.drive_input)


# ---------------------------------------------------------------------------- slow


@pytest.mark.slow  # ~2 min: the twin identification, then the output-error polish
def test_identify_with_the_simulation_objective(twin_problem, paper_config):
    tables = {**paper_config.tables, "search": {**paper_config.table("search")}}
    tables["search"]["objective"] = "simulation"
    run = identify(twin_problem, IdentifySettings.from_tables(tables))
    equation = identify(twin_problem, IdentifySettings.from_tables(paper_config.tables))
    # the first phase is the untouched equation-error path, bit for bit
    assert run.attrs["equation_cost"] == equation.cost
    np.testing.assert_array_equal(run.chain_x, equation.chain_x)
    assert equation.attrs["objective"] == "equation error (seed eq. 11)"
    assert run.attrs["objective_setting"] == "simulation"
    assert run.attrs["segments"] == 1 and run.attrs["position_rms"] < 1.5 * DEFAULT_NOISE_STD
    assert run.cost == run.attrs["oe_cost"] <= run.attrs["oe_cost_start"]
    assert run.attrs["equation_cost"] > 0 and np.all(np.isfinite(run.value))
    assert run.value.shape == run.std.shape == (twin_problem.spec.n_free,)


@pytest.mark.slow  # ~4 min on 2 cores: 49 segments of 0.5 s over 24.7 s, 102 unknowns
def test_emps_output_error_against_equation_error(emps_dir: Path):
    path = emps_dir / "DATA_EMPS.mat"
    from fricjax.data.importers import import_mat

    cfg = load_config(ROOT / "configs" / "emps.toml")
    rec = import_mat(path, mapping={"t": "t", "x": "qm", "u": "vir", "r": "qg"}, u_unit="V")
    problem = build_problem(rec, cfg)
    ee = identify(problem, IdentifySettings.from_tables(cfg.tables, source=cfg.source))
    fit = fit_output_error(problem, ee.params)
    assert (fit.n_segments, fit.segment_samples) == (49, 505)
    # Measured (2 cores, 100 LM steps): M 92.25 kg, Fv 191.09 N·s/m, Fc 21.77 N, offset
    # −3.399 N against equation error's 95.12, 203.37, 20.41, −3.170 (published 95.1089,
    # 203.5034, 20.3935, −3.1648): the open-loop position fit weighs the model's errors
    # differently from the force fit, which moves the estimates by 3-7 % (20-30 published
    # σ): the published model is not the whole physics of the rig.
    for k in ("mass", "Fv", "Fc", "offset"):
        assert fit.params[k] == pytest.approx(ee.params[k], rel=0.1, abs=0.5), k
    assert fit.params["mass"] < ee.params["mass"] and fit.params["Fv"] < ee.params["Fv"]
    # 1.77 mm RMS over ±0.1 m of travel, model error far above the encoder's 26 nm; the
    # defects (0.30 mm, 0.49 mm/s) stay below the misfit they trade against
    assert fit.position_rms < 2.5e-3 and fit.cost < 0.05 * fit.cost_start
    assert fit.defect_x < fit.position_rms
