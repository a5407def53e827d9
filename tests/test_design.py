"""Designing the next test: the discrimination criterion (eq. [1] of fricjax.design), the
profile and its limits, the rivals read from a diagnosis folder, and the command's
refusals."""

from __future__ import annotations

import json
from pathlib import Path

import h5py
import jax.numpy as jnp
import numpy as np
import pytest

from fricjax import api
from fricjax.cli import main
from fricjax.data.recording import Recording
from fricjax.design import (
    DESIGNED,
    DesignSettings,
    Limits,
    Rival,
    design,
    design_precision,
    divergence,
    plan_for,
    posterior_sigma,
    profile,
    project,
    read_rivals,
    record_limits,
    responses,
    scale_rival,
    standard_inputs,
)
from fricjax.design import _optimise as optimise
from fricjax.diagnose.catalogue import candidate
from fricjax.errors import FricjaxError
from fricjax.model.simulate import simulate

ROOT = Path(__file__).resolve().parents[1]
AXIS = ROOT / "examples" / "axis.csv"
AXIS_CONFIG = ROOT / "examples" / "axis.toml"
SIGMA = 1e-6  # m, the example axis' encoder noise


@pytest.fixture(scope="module")
def short_axis():
    """The example axis' first 0.4 s (0.3 s after the preprocessing trim)."""
    d = np.loadtxt(AXIS, delimiter=",", skiprows=1)[:400]
    rec = Recording(t=d[:, 0], x=d[:, 1], u=d[:, 2], mass=12.0, name="axis 0.4 s")
    _, _, problem = api.load(rec, AXIS_CONFIG)
    return problem


def rival(problem, name: str, values: dict[str, float], sd: dict[str, float]) -> Rival:
    model, spec = problem.model, problem.spec
    if name != "base":
        model, spec = candidate(name).extend(model, spec, problem)
    params = {p.name: float(p.init) for p in spec.params} | values
    free = spec.free_names
    return Rival(
        name=name,
        model=model,
        params=params,
        free=free,
        cov=np.diag([sd.get(n, 0.0) ** 2 for n in free]),
        cost=0.0,
    )


BASE = {"Fc": 8.0, "Fv": 60.0, "offset": 0.0}
STRIBECK = BASE | {"stribeck_A": 5.0, "stribeck_vst": 0.02}


def positions(problem, rivals, u) -> list[np.ndarray]:
    plan = plan_for(problem)
    t = jnp.arange(plan.n) * plan.dt
    return [
        np.asarray(simulate(r.model, r.params, t, plan.x0, 0.0, u, substeps=4).x) for r in rivals
    ]


def test_a_pinned_rival_leaves_the_whole_difference_in_noise_units(short_axis) -> None:
    rivals = [rival(short_axis, "base", BASE, {}), rival(short_axis, "stribeck", STRIBECK, {})]
    plan = plan_for(short_axis)
    u = jnp.asarray(short_axis.u[: plan.n])
    scaled = [scale_rival(r, SIGMA) for r in rivals]
    xs, _, js = responses(rivals, scaled, u, plan)
    d = np.asarray(divergence(xs, js, scaled, SIGMA))
    direct = positions(short_axis, rivals, u)
    plain = float(np.sum((direct[0] - direct[1]) ** 2)) / SIGMA**2
    assert plain > 100  # the Stribeck drop moves the body by many σ_x
    # with no parameter free to refit (σ_θ = 0), D is the squared distance, both ways
    assert d[0, 1] == pytest.approx(plain, rel=1e-9)
    assert d[1, 0] == pytest.approx(plain, rel=1e-9)
    assert d[0, 0] == d[1, 1] == 0.0


def test_a_rival_free_to_refit_is_charged_only_what_its_parameters_cannot_absorb(
    short_axis,
) -> None:
    plan = plan_for(short_axis)
    u = jnp.asarray(short_axis.u[: plan.n])
    truth = rival(short_axis, "base", BASE, {})
    nearby = BASE | {"Fv": 60.5}
    out = []
    for sd in (1e-9, 1e3):  # the rival's Fv pinned by the record, then left to the new test
        rivals = [truth, rival(short_axis, "base", nearby, {"Fv": sd})]
        scaled = [scale_rival(r, SIGMA) for r in rivals]
        xs, _, js = responses(rivals, scaled, u, plan)
        out.append(float(divergence(xs, js, scaled, SIGMA)[0, 1]))
    direct = positions(short_axis, rivals, u)
    plain = float(np.sum((direct[0] - direct[1]) ** 2)) / SIGMA**2
    assert out[0] == pytest.approx(plain, rel=1e-6)
    # a 0.8 % change of a linear coefficient is refitted away up to second order
    assert out[1] < 1e-2 * plain


def test_the_profile_keeps_the_peak_input_and_projection_inverts_it(short_axis) -> None:
    plan = plan_for(short_axis)
    limits = Limits(u_mid=2.0, u_peak=30.0, x_lo=-1.0, x_hi=1.0, speed=1.0)
    width = 2 * plan.harmonics + 1
    wild = profile(jnp.asarray(50.0 * np.random.default_rng(0).normal(size=width)), plan, limits)
    assert float(jnp.max(jnp.abs(wild - limits.u_mid))) <= limits.u_peak
    c = 0.3 * np.random.default_rng(1).normal(size=width)
    u = np.asarray(profile(jnp.asarray(c), plan, limits))
    assert np.max(np.abs(u - limits.u_mid)) < 0.98 * limits.u_peak
    np.testing.assert_allclose(project(u, plan, limits), c, atol=1e-9)


def test_a_standard_test_that_separates_better_is_the_test_returned(short_axis) -> None:
    # a criterion that only a chirp satisfies (its distance from the chirp) and a loss that
    # pulls every profile to a constant: no optimised profile can reach the chirp, so the
    # test handed back must be the chirp itself, said so, never a worse profile
    plan = plan_for(short_axis)
    limits = record_limits(short_axis)
    chirp = standard_inputs(short_axis, plan, limits)["chirp"]

    def score(u: np.ndarray) -> tuple[float, float]:
        return -float(np.sum((u - chirp) ** 2)), 0.0

    settings = DesignSettings(starts=4, steps=3)
    best, origin, standard = optimise(
        lambda c: jnp.sum(c**2), score, short_axis, plan, limits, settings
    )
    assert origin in ("chirp", "chirp within limits") and origin != DESIGNED
    np.testing.assert_allclose(best, chirp)
    assert set(standard) == {"chirp", "record's input", "chirp within limits"}


def test_the_default_limits_are_what_the_record_did(short_axis) -> None:
    lim = record_limits(short_axis)
    assert lim.u_mid - lim.u_peak == pytest.approx(float(np.min(short_axis.drive_input)))
    assert lim.u_mid + lim.u_peak == pytest.approx(float(np.max(short_axis.drive_input)))
    assert (lim.x_lo, lim.x_hi) == (float(np.min(short_axis.x)), float(np.max(short_axis.x)))
    assert lim.speed == pytest.approx(float(np.max(np.abs(short_axis.v))))
    given = api.parse_limits("20,,0.05", short_axis)
    assert (given.u_mid, given.u_peak, given.speed) == (0.0, 20.0, 0.05)
    assert (given.x_lo, given.x_hi) == (lim.x_lo, lim.x_hi)


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ("20,0.1", "give F_max,x_range,v_max"),
        ("abc,,", "F_max 'abc' is not a number"),
        ("-3,,", "must be finite and > 0"),
        (",0.2:0.1,", "lo < hi"),
        (",5:6,", "excludes the start position"),
    ],
)
def test_a_bad_limits_flag_is_named(short_axis, text: str, needle: str) -> None:
    with pytest.raises(FricjaxError, match=needle):
        api.parse_limits(text, short_axis)


@pytest.mark.slow
def test_the_design_separates_more_than_its_starts_within_the_limits(short_axis) -> None:
    rivals = [
        rival(short_axis, "base", BASE, {"Fc": 0.05, "Fv": 0.5, "offset": 0.05}),
        rival(short_axis, "stribeck", STRIBECK, {"Fc": 0.05, "Fv": 0.5, "stribeck_A": 0.1}),
    ]
    settings = DesignSettings(starts=3, steps=10)
    d = design(short_axis, rivals, SIGMA, settings=settings)
    lim = d.limits
    assert np.all(np.abs(d.u - lim.u_mid) <= lim.u_peak)
    assert d.violation <= 0.01
    assert np.all(d.x >= lim.x_lo - 0.01 * (lim.x_hi - lim.x_lo))
    # the first start is the chirp's projection: gradient ascent from it gained
    chirp = d.standard["chirp"]["separation"]
    assert d.separation > chirp
    # the expected evidence adds the new record's D to the record's own
    assert d.expected_delta_bic[0, 1] == pytest.approx(
        d.divergence[0, 1] - (rivals[0].k - rivals[1].k) * np.log(short_axis.n + d.plan.n)
    )


def write_models(folder: Path, problem, steps: list[tuple[str, dict]]) -> None:
    """A diagnosis folder in the layout of docs/formats.md: per step, the term it named and
    its fits by name ("base" the model it started from, with the terms named before)."""
    folder.mkdir(parents=True, exist_ok=True)
    with h5py.File(folder / "models.h5", "w") as f:
        f.attrs["format"] = "fricjax-diagnosis-models-v1"
        f.attrs["sigma_x_m"] = SIGMA
        f.attrs["n_samples"] = problem.n
        before: list[str] = []
        for i, (named, fits) in enumerate(steps):
            g = f.create_group(f"steps/{i}")
            g.attrs["named"] = named
            for name, values in fits.items():
                active = before if name == "base" else [*before, name]
                model, spec = problem.model, problem.spec
                for e in active:
                    model, spec = candidate(e).extend(model, spec, problem)
                params = {p.name: float(p.init) for p in spec.params} | values
                sub = g.create_group(name)
                sub.attrs["active"] = json.dumps(active)
                sub.attrs["cost"] = 100.0
                sub.attrs["delta_bic"] = 10.0
                sub.attrs["p_value"] = 1e-4
                sub["names"] = np.array(list(params), dtype=h5py.string_dtype())
                sub["values"] = np.array(list(params.values()))
                sub["free"] = np.array([n in spec.free_names for n in params])
                sub["cov"] = 1e-4 * np.eye(len(spec.free_names))
            before = [*before, named]
    named, fits = steps[0]
    findings = [
        {"effect": named, "alternatives": [{"effect": n} for n in fits if n not in (named, "base")]}
    ]
    (folder / "diagnosis.json").write_text(json.dumps({"findings": findings}), encoding="utf-8")


def test_the_rivals_come_from_the_diagnosis_ambiguity_set_or_by_name(
    short_axis, tmp_path: Path
) -> None:
    drag = BASE | {"drag_Cd": 3.0}
    first = {"base": BASE, "stribeck": STRIBECK, "quadratic_drag": drag}
    second = {"base": STRIBECK, "quadratic_drag": STRIBECK | {"drag_Cd": 2.0}}
    write_models(tmp_path, short_axis, [("stribeck", first), ("", second)])
    rivals, sigma = read_rivals(tmp_path, short_axis)
    assert [r.name for r in rivals] == ["stribeck", "quadratic_drag"] and sigma == SIGMA
    assert rivals[0].params["stribeck_A"] == 5.0 and rivals[1].params["drag_Cd"] == 3.0
    assert rivals[1].model.name.endswith("quadratic_drag")
    # by name: the last step that fitted them all, whose base holds the Stribeck term
    rivals, _ = read_rivals(tmp_path, short_axis, ["base", "quadratic_drag"])
    assert [r.name for r in rivals] == ["base", "quadratic_drag"]
    assert "stribeck" in rivals[0].model.name and rivals[1].params["drag_Cd"] == 2.0
    assert rivals[0].cov.shape == (5, 5)
    with pytest.raises(FricjaxError, match="no step fitted all of base, impact"):
        read_rivals(tmp_path, short_axis, ["base", "impact"])


def test_the_command_refuses_in_one_line(short_axis, tmp_path: Path, capsys) -> None:
    twin, paper = str(ROOT / "data" / "paper_twin.h5"), str(ROOT / "configs" / "paper.toml")
    cases = [
        (
            [str(AXIS), "-c", str(AXIS_CONFIG), "--mass", "12", "--diagnosis", str(tmp_path)],
            "models.h5: no such file",
        ),
        ([twin, "-c", paper, "--diagnosis", str(tmp_path)], "has no measured input"),
        (
            [
                str(AXIS),
                "-c",
                str(AXIS_CONFIG),
                "--mass",
                "12",
                "--diagnosis",
                str(tmp_path),
                "--duration",
                "-1",
            ],
            "--duration",
        ),
    ]
    for args, needle in cases:
        with pytest.raises(SystemExit) as exc:
            main(["design", *args, "--out", str(tmp_path / "next.csv")])
        err = capsys.readouterr().err.strip().splitlines()
        assert exc.value.code == 2 and len(err) == 1 and needle in err[0], (args, err)


def test_the_expected_sigma_is_the_record_and_the_test_combined(short_axis) -> None:
    # one free parameter: information adds, 1/σ² = 1/σ_record² + ‖J‖²/σ_x²
    r = rival(short_axis, "base", BASE, {"Fv": 0.3})
    r = Rival(r.name, r.model, r.params, ("Fv",), np.array([[0.09]]), 0.0)
    s = scale_rival(r, SIGMA)
    np.testing.assert_allclose(posterior_sigma(jnp.zeros((10, 1)), s, SIGMA), [0.3], rtol=1e-12)
    j = np.random.default_rng(2).normal(size=(10, 1)) * 2e-6  # m per N·s/m
    expected = 1.0 / np.sqrt(1.0 / 0.09 + np.sum(j**2) / SIGMA**2)
    got = posterior_sigma(jnp.asarray(j * 0.3), s, SIGMA)
    np.testing.assert_allclose(got, [expected], rtol=1e-10)


@pytest.mark.slow
def test_a_precision_design_determines_a_loose_parameter_within_the_limits(short_axis) -> None:
    r = rival(short_axis, "base", BASE, {"Fc": 0.01, "Fv": 30.0, "offset": 0.01})
    d = design_precision(short_axis, r, SIGMA, ["Fv"], settings=DesignSettings(starts=2, steps=8))
    i = d.names.index("Fv")
    assert d.sigma_after[i] < 0.01 * d.sigma_before[i]
    assert d.violation <= 0.01 and np.all(np.abs(d.u - d.limits.u_mid) <= d.limits.u_peak)
    assert 0 < d.shrink < 0.01


def test_the_purpose_and_its_input_must_agree(tmp_path: Path, capsys) -> None:
    base = [str(AXIS), "-c", str(AXIS_CONFIG), "--mass", "12", "--out", str(tmp_path / "n.csv")]
    cases = [
        (["--for", "identify", "--diagnosis", str(tmp_path)], "give --results"),
        (["--for", "bogus"], "discriminate or identify"),
        ([], "give --diagnosis"),
    ]
    for args, needle in cases:
        with pytest.raises(SystemExit) as exc:
            main(["design", *base, *args])
        err = capsys.readouterr().err.strip().splitlines()
        assert exc.value.code == 2 and len(err) == 1 and needle in err[0], (args, err)
