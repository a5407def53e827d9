"""Diagnosis end to end: a null record yields no finding (and /truth is never read), a clearly
visible effect is named, located and modelled, and the fit improves on held-out data."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest

import fricjax.diagnose.catalogue as cat
from fricjax.api import diagnose_recording
from fricjax.config import Config
from fricjax.data.recording import write_recording
from fricjax.data.twin import PAPER_MODEL, PAPER_TRUTH, paper_twin
from fricjax.diagnose.run import (
    CV_FOLDS,
    CV_FOLDS_KEY,
    CV_KEY,
    FROZEN_KEY,
    SPLIT_FROZEN,
    DiagnoseSettings,
    diagnose,
)
from fricjax.diagnose.stages import LIMITED
from fricjax.identify import IdentifySettings
from fricjax.problem import build_problem

ROOT = Path(__file__).resolve().parents[2]
# no time limit: what the diagnosis finds must not depend on the machine's load
FAST = {
    "n_mc": 400,
    "max_terms": 2,
    "time_limit": float("inf"),
    "stage_limits": dict.fromkeys(LIMITED, float("inf")),
}

#: one clearly visible instance of each effect on the 1 s paper twin (term, parameters)
VISIBLE = {
    "impact": (cat.Impact(), {"impact_A": 3000.0, "impact_t0": 0.4, "impact_w": 0.004}),
    "extra_harmonic": (cat.ExtraHarmonic(), {"harm_A": 400.0, "harm_B": 0.0, "harm_f": 37.0}),
    "asymmetric_friction": (cat.AsymmetricFriction(), {"asym_dFc": 60.0, "asym_dFv": 900.0}),
    "quadratic_drag": (cat.QuadraticDrag(), {"drag_Cd": 6000.0}),
    "position_bump": (cat.PositionBump(), {"bump_A": 400.0, "bump_x0": 0.06, "bump_w": 0.004}),
    "friction_drift": (cat.FrictionDrift(t_mid=0.5, duration=1.0), {"drift_beta": 300.0}),
}


def _settings(config: Config) -> IdentifySettings:
    return IdentifySettings.from_tables(config.tables, source=config.source)


def test_null_record_gives_no_finding_and_truth_is_never_read(
    paper_config: Config, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    rec, truth = paper_twin(duration=1.0, seed=11)
    path = write_recording(rec, tmp_path / "null.h5", truth=truth)
    opened: list[str] = []
    original = h5py.Group.__getitem__

    def spy(self: h5py.Group, name: str):
        opened.append(str(name))
        return original(self, name)

    monkeypatch.setattr(h5py.Group, "__getitem__", spy)
    # equation error only: the output-error route on a null record is the slow
    # test_simulation_test.py::test_no_friction_law_is_significant_on_a_null_record
    _diag, paths = diagnose_recording(
        path,
        ROOT / "configs" / "paper.toml",
        out=tmp_path / "out",
        overrides={**FAST, "simulation_test": False},
    )
    monkeypatch.undo()
    assert not any("truth" in name for name in opened)
    doc = json.loads(paths["json"].read_text())
    assert doc["findings"] == []
    assert set(doc["fit"]["before"]) >= {"ems", "bic", "whiteness_p"}
    assert doc["fit"]["before"]["whiteness_p"] > 0.001  # the base residual looks white
    # what the record allows: the noise level found is the twin's (24 µm), and the plant
    # rests near its reversals for a part of the record, never most of it
    assert doc["data"]["sigma_x_m"] == pytest.approx(truth["noise_std"], rel=0.25)
    assert 0.0 < doc["data"]["near_rest_fraction"] < 0.5
    report = (tmp_path / "out" / "report.md").read_text()
    assert report.startswith("# Diagnosis") and "Nothing is missing" in report
    assert "Weak evidence" not in report  # 1 s: far more noise dimensions than parameters


@pytest.mark.slow
def test_a_short_null_record_says_its_evidence_is_weak(
    paper_config: Config, tmp_path: Path
) -> None:
    """The seed's own length (0.272 s): nothing found, and the report says that this proves
    little, since the base's 26 parameters take most of the whitened dimensions."""
    rec, truth = paper_twin(duration=0.272, seed=11)
    path = write_recording(rec, tmp_path / "short.h5", truth=truth)
    diag, paths = diagnose_recording(
        path, ROOT / "configs" / "paper.toml", out=tmp_path / "out", overrides=FAST
    )
    assert diag.findings == []
    assert diag.selection.whitener.dof <= 2 * diag.base_spec.n_free
    assert "Weak evidence on this record" in paths["report"].read_text()


@pytest.mark.slow
def test_a_short_record_names_a_visible_harmonic_and_says_how_its_check_was_made(
    tmp_path: Path,
) -> None:
    """0.272 s, 300 N at 60 Hz (above the drive's ten harmonics of ~5 Hz, which absorb one
    at 37 Hz on so short a record): named; the record's own split could fit only the
    harmonic's own parameters (the first 70 % has fewer whitened dimensions than base + term
    have parameters), so it is reported but does not judge: a cross-validation whose folds
    refit all 29 parameters does (measured +92.9 % over 36 folds; the split +53.2 %), and the
    report says so; σ̂ comes from the third difference, so the fit figures' BIC is that of a
    known variance and their difference is the finding's ΔBIC (or a little more, where the
    base refitted from the term's end point fits better)."""
    term, params = cat.ExtraHarmonic(), {"harm_A": 300.0, "harm_B": 0.0, "harm_f": 60.0}
    rec, truth = paper_twin(
        duration=0.272,
        seed=5,
        model=PAPER_MODEL.with_terms([term]),
        truth={**PAPER_TRUTH, **params},
    )
    path = write_recording(rec, tmp_path / "short.h5", truth=truth)
    diag, paths = diagnose_recording(
        path, ROOT / "configs" / "paper.toml", out=tmp_path / "out", overrides=FAST
    )
    first = diag.findings[0]
    assert first["effect"] == "extra_harmonic"
    assert abs(first["params"]["harm_f"] - 60.0) < 0.5  # measured 60.03 Hz, 281 N
    assert first["heldout_untestable"] == SPLIT_FROZEN and first["heldout_improvement"] > 0
    assert first[CV_FOLDS_KEY] > CV_FOLDS and first[CV_KEY] > 0.5 and first["heldout_confirmed"]
    assert FROZEN_KEY not in first  # the check that judged refitted every parameter
    assert diag.heldout["mode"] == "frozen" and diag.heldout["improvement"] > 0
    assert diag.selection.extra["bic_sigma2"] == pytest.approx(diag.evidence.sigma_x**2)
    if len(diag.findings) == 1:
        # The finding's ΔBIC is taken against the better of the base fit and the base
        # refitted from the term's end point (its excess over the noise is significant, so
        # it was refitted and rebased: 255.22 against 255.29 measured), never more.
        drop = diag.fit["before"]["bic"] - diag.fit["after"]["bic"]
        assert first["delta_bic"] <= drop + 1e-9 and drop - first["delta_bic"] < 1.0
    report = paths["report"].read_text()
    assert "only the finding's own parameters were fitted there" in report
    folds = first[CV_FOLDS_KEY]
    assert f"judged instead by {folds}-fold cross-validation" in report and "--validation" in report


@pytest.mark.slow
@pytest.mark.parametrize("effect", ["impact"])
def test_visible_effect_is_named_located_and_pays_on_held_out_data(
    paper_config: Config, effect: str, tmp_path: Path
) -> None:
    # with a second recording of the same plant (another noise draw): both held-out checks
    # run, the finding pays in each, and the report says so
    from fricjax.diagnose.run import write_diagnosis

    diag = _check_visible(paper_config, effect, second_seed=4)
    assert diag.heldout["on"] == "second recording"
    assert diag.heldout["split"]["on"] == "last 30% of the record"
    first = diag.findings[0]
    assert first["heldout_improvement"] > 0 and first["heldout_split_improvement"] > 0
    assert first["heldout_confirmed"]
    report = write_diagnosis(diag, tmp_path)["report"].read_text()
    assert "on the second recording" in report and "confirmed" in report


#: Known failures on the 1 s paper twin, measured (session 3; they failed at the end of
#: session 2 already, with the same numbers): strict, so a fix shows up as XPASS.
#: quadratic_drag left this list in session 6 (likelihood-ratio test of friction-law terms).
KNOWN_GAPS = {
    "asymmetric_friction": "not detected: the base fit absorbs its linearised signature "
    "(c_ee = 2.0) yet leaves c_refit = 33 noise std of broadband structure, which inflates the "
    "residual's own noise estimate sigma_hat and so hides itself",
}


@pytest.mark.slow
@pytest.mark.parametrize(
    "effect",
    [
        pytest.param(e, marks=pytest.mark.xfail(strict=True, reason=KNOWN_GAPS[e]))
        if e in KNOWN_GAPS
        else e
        for e in sorted(set(VISIBLE) - {"impact"})
    ],
)
def test_every_visible_effect_is_named(paper_config: Config, effect: str) -> None:
    _check_visible(paper_config, effect)


@pytest.mark.slow
def test_a_term_that_leaves_too_few_degrees_of_freedom_is_not_added(
    paper_config: Config, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The visible impact is named by default (test above); asked to leave more residual
    degrees of freedom than the record has beyond the base's, forward selection adds no
    term rather than one whose σ̂² and maps could not be formed."""
    import fricjax.diagnose.select as select

    term, params = VISIBLE["impact"]
    model, truth = PAPER_MODEL.with_terms([term]), {**PAPER_TRUTH, **params}
    problem = build_problem(
        paper_twin(duration=1.0, seed=3, model=model, truth=truth)[0], paper_config
    )
    monkeypatch.setattr(select, "MIN_DOF_LEFT", 10**6)
    diag = diagnose(
        problem, identify_settings=_settings(paper_config), settings=DiagnoseSettings(**FAST)
    )
    assert not [f for f in diag.findings if f["effect"] != "unexplained"]
    assert diag.selection.model.terms == problem.model.terms
    step = diag.selection.steps[0]
    assert step.chosen is None and step.refits and step.refits[0].delta_bic > 10


def _check_visible(config: Config, effect: str, second_seed: int | None = None) -> Any:
    term, params = VISIBLE[effect]

    def record(seed: int) -> Any:
        model, truth = PAPER_MODEL.with_terms([term]), {**PAPER_TRUTH, **params}
        return build_problem(
            paper_twin(duration=1.0, seed=seed, model=model, truth=truth)[0], config
        )

    problem = record(3)
    validation = None if second_seed is None else record(second_seed)
    diag = diagnose(
        problem,
        identify_settings=_settings(config),
        settings=DiagnoseSettings(**FAST),
        validation=validation,
    )
    assert diag.findings, "nothing found"
    first = diag.findings[0]
    assert first["effect"] == effect
    assert first["delta_bic"] > 10 and first["p_value"] < 1e-3
    assert diag.fit["after"]["bic"] < diag.fit["before"]["bic"]
    assert diag.heldout["rss_w_after"] < diag.heldout["rss_w_before"]
    if effect == "impact":
        assert abs(first["params"]["impact_t0"] - 0.4) < 0.01
        lo, hi = first["location"]["time_s"]
        assert lo <= 0.4 <= hi
        assert abs(first["params"]["impact_A"] / 3000.0 - 1) < 0.2
    assert np.isfinite(diag.fit["after"]["ems"])
    return diag


def test_refit_starts_are_distinct_grid_maxima_led_by_the_best() -> None:
    # A 1-D frequency grid with peaks at 74 and 30 Hz, the uncentred statistic peaking at
    # 68 Hz, and a 2-D (location x width) grid: the best point first, the uncentred
    # statistic's best next, then the next highest points, never a grid neighbour of a
    # chosen point (73 and 75 Hz score 38.9 but neighbour 74 Hz).
    from fricjax.diagnose.select import refit_starts

    f = np.linspace(10.0, 100.0, 91)
    stats = np.exp(-((f - 74.0) ** 2) / 4.0) * 50 + np.exp(-((f - 30.0) ** 2) / 4.0) * 40
    raw = np.exp(-((f - 68.0) ** 2) / 4.0) * 60
    points = [{"harm_f": float(v)} for v in f]
    picked = [points[i]["harm_f"] for i in refit_starts(stats, raw, points)]
    assert picked == [74.0, 68.0, 30.0]
    x0, w = np.meshgrid(np.linspace(0, 0.1, 11), [1e-3, 2e-3, 4e-3], indexing="ij")
    pts = [{"x0": float(a), "w": float(b)} for a, b in zip(x0.ravel(), w.ravel(), strict=True)]
    s2 = np.exp(-((x0.ravel() - 0.05) ** 2) / 1e-3)
    chosen = refit_starts(s2, s2, pts)
    assert chosen[0] == int(np.argmax(s2)) and len(chosen) == 3
    for i in chosen:
        for j in chosen:
            if i != j:
                assert (
                    max(
                        abs(pts[i]["x0"] - pts[j]["x0"]) / 0.01,
                        abs(np.log2(pts[i]["w"] / pts[j]["w"])),
                    )
                    > 1.5
                )


def test_with_sigma_known_the_bic_of_a_null_term_stays_below_the_bar() -> None:
    # A short record's test space: 30 whitened dimensions, 26 base parameters, a term of 3
    # that is not there (linear model, unit noise). The profile BIC divides by what the one
    # dimension left happens to hold and its ΔBIC exceeds the bar of 10 on most draws; with
    # σ known (the third difference's σ̂ on such records) ΔBIC = χ²_3 − 3·ln 30 never does.
    from fricjax.diagnose.select import bic, bic_known

    rng = np.random.default_rng(0)
    m, kb, ke = 30, 26, 3
    x = rng.normal(size=(m, kb + ke))
    profile, known = [], []
    for _ in range(500):
        y = rng.normal(size=m)
        rb = y - x[:, :kb] @ np.linalg.lstsq(x[:, :kb], y, rcond=None)[0]
        rt = y - x @ np.linalg.lstsq(x, y, rcond=None)[0]
        profile.append(bic(rb @ rb, m, kb) - bic(rt @ rt, m, kb + ke))
        known.append(bic_known(rb @ rb, m, kb, 1.0) - bic_known(rt @ rt, m, kb + ke, 1.0))
        assert known[-1] == pytest.approx(rb @ rb - rt @ rt - ke * np.log(m))
    assert np.mean(np.array(profile) > 10) > 0.5
    assert np.mean(np.array(known) > 10) < 0.01


def test_the_lack_of_fit_test_against_an_outside_sigma_is_uniform_on_nulls() -> None:
    # A short record's base leaves dof = 8 whitened dimensions of pure noise, and σ̂² comes
    # from the third difference with ν = 99 (0.272 s): F = (RSS/dof)/σ̂² ~ F(8, 99), so
    # its p-value is uniform; with an excess of 5 σ² per dimension it is tiny.
    from fricjax.diagnose.select import lack_of_fit_p

    rng = np.random.default_rng(1)
    dof, nu = 8, 99
    p = np.array(
        [lack_of_fit_p(rng.chisquare(dof), dof, rng.chisquare(nu) / nu, nu) for _ in range(4000)]
    )
    assert abs(np.mean(p < 0.05) - 0.05) < 0.012
    assert abs(np.mean(p < 0.01) - 0.01) < 0.006
    assert abs(np.median(p) - 0.5) < 0.03
    assert lack_of_fit_p(dof * 6.0, dof, 1.0, nu) < 1e-5


def test_refit_starts_lead_adds_a_start_in_front() -> None:
    # A lead index is the first start and one more than the usual three; a lead that is a
    # grid neighbour of the statistic's best keeps that best out (they share one basin).
    from fricjax.diagnose.select import N_STARTS, refit_starts

    f = np.linspace(10.0, 100.0, 91)
    stats = np.exp(-((f - 74.0) ** 2) / 4.0) * 50 + np.exp(-((f - 30.0) ** 2) / 4.0) * 40
    raw = np.exp(-((f - 68.0) ** 2) / 4.0) * 60
    points = [{"harm_f": float(v)} for v in f]
    lead = int(np.argmin(np.abs(f - 50.0)))
    picked = [points[i]["harm_f"] for i in refit_starts(stats, raw, points, lead=(lead,))]
    assert picked == [50.0, 74.0, 68.0, 30.0] and len(picked) == N_STARTS + 1
    near = int(np.argmin(np.abs(f - 73.0)))
    picked = [points[i]["harm_f"] for i in refit_starts(stats, raw, points, lead=(near,))]
    assert picked[0] == 73.0 and 74.0 not in picked


def test_boxed_gain_sees_what_a_base_held_at_its_box_leaves_in_span_j() -> None:
    # A linear base of 3 parameters, the first at its upper bound; the residual wants it
    # higher still (2 units along its column) plus noise. The projected score projects
    # that column out and sees nothing of a candidate column equal to it; the boxed gain,
    # which keeps the parameter at its bound, finds the 4 units² (up to the noise).
    from fricjax.diagnose.select import boxed_base, boxed_gains
    from fricjax.params import Param, ParamSpec

    rng = np.random.default_rng(3)
    m = 40
    j = np.linalg.qr(rng.normal(size=(m, 3)))[0]
    spec = ParamSpec(
        (
            Param("p0", "N", 0.0, 1.0, 0.5),
            Param("p1", "N", -10.0, 10.0, 0.0),
            Param("p2", "N", -10.0, 10.0, 0.0),
        )
    )
    theta = np.array([1.0, 0.0, 0.0])  # p0 at its upper bound
    noise = 0.01 * rng.normal(size=m)
    r = -2.0 * j[:, 0] + 0.5 * j[:, 1] + noise  # r + J·δ: δ0 = +2 is outside the box
    boxed = boxed_base(j, r, theta, spec)
    assert boxed.q_free.shape == (m, 2)
    # the movable columns take their parts; p0's is left
    assert boxed.r_free @ j[:, 0] == pytest.approx(-2.0, abs=0.05)
    cols = np.stack([j[:, [0]], rng.normal(size=(m, 1))])  # [G=2, M, k=1]
    gains = boxed_gains(boxed, cols)
    assert gains[0] == pytest.approx(4.0, rel=0.05)
    assert gains[1] < 0.5 * gains[0]
    r_perp = r - j @ (j.T @ r)
    assert abs(r_perp @ j[:, 0]) < 1e-12  # what the projected score would see of it
    # with the box wide open nothing is held: p0's column is projected out too
    wide = ParamSpec((Param("p0", "N", -10.0, 10.0, 0.5), *spec.params[1:]))
    open_box = boxed_base(j, r, theta, wide)
    assert open_box.q_free.shape == (m, 3)
    assert boxed_gains(open_box, cols[:1])[0] < 1e-20


@pytest.mark.slow
def test_the_base_fit_is_as_good_as_identify_s_on_the_ems_and_keeps_its_mean() -> None:
    """Bundled 0.272 s twin, configs/paper.toml: the whitened fit alone left the residual's
    mean free (the whitener drops DC) and reached EMS 62 000 N² with a mean residual of
    225 N where identify reaches 4 504 N²; holding the mean by its own noise and choosing
    the EMS-best fit the whitened metric cannot tell from its optimum, the diagnosis'
    base is at least as good as identify's on the EMS, with a mean residual within a few
    of its noise standard deviations."""
    from fricjax.api import load
    from fricjax.diagnose.evidence import record_noise
    from fricjax.diagnose.locate import default_whitener
    from fricjax.diagnose.select import best_supported, gls_fit
    from fricjax.diagnose.whiten import dc_scale
    from fricjax.identify import identify

    _, _, pb = load(str(ROOT / "data" / "paper_twin.h5"), str(ROOT / "configs" / "paper.toml"))
    run = identify(pb, IdentifySettings())
    ev = record_noise(pb)
    wh = default_whitener(pb, run.value, "auto", ev.sigma_x)
    theta_gls, rss = gls_fit(pb, pb.model, pb.spec, np.asarray(run.value), wh)
    base = best_supported(pb, wh, [theta_gls, np.asarray(run.value)], rss, ev, 0.01)
    assert pb.ems(base) <= run.ems * (1 + 1e-9)
    sd_mean = ev.sigma_x * dc_scale(wh, pb.preprocess)  # [N]
    assert abs(float(np.mean(pb.residual(theta_gls)))) < 4 * sd_mean
