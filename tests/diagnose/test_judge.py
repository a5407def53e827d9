"""The output-error judge (fricjax.diagnose.judge): its statistic keeps its false-alarm rate on
nulls, its ranking starts a hidden effect's fit at its place, and end to end a hidden Stribeck
drop is named while the same plant without it gets no finding."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from scipy import stats

import fricjax.diagnose.catalogue as cat
from fricjax.config import Config
from fricjax.data.twin import PAPER_MODEL, PAPER_TRUTH, paper_twin
from fricjax.diagnose.evidence import near_rest_band, record_noise
from fricjax.diagnose.judge import (
    CandidateFit,
    Fitted,
    Superset,
    _judge_numbers,
    f_pvalue,
    looks,
    starts,
    vuong,
)
from fricjax.diagnose.report import write_diagnosis
from fricjax.diagnose.run import DiagnoseSettings, diagnose
from fricjax.identify import IdentifySettings
from fricjax.problem import build_problem


@pytest.mark.parametrize(("k", "nu"), [(1, 20), (2, 48), (3, 1_000_000)])
def test_the_likelihood_ratio_keeps_its_false_alarm_rate_when_sigma_is_estimated(
    k: int, nu: int
) -> None:
    # Under the null, LR in units of the estimated σ̂² is χ²_k·σ²/σ̂² with σ̂²/σ² ~ χ²_ν/ν:
    # the F(k, ν) reference is exact, where χ²_k alone would overstate significance for
    # small ν. 20 000 draws: the rate at α = 0.01 is within 4 binomial errors of it.
    rng = np.random.default_rng(k)
    draws, alpha = 20_000, 0.01
    ratio = rng.chisquare(nu, draws) / nu
    lr = rng.chisquare(k, draws) / ratio
    p = f_pvalue(lr, k, nu)
    p0 = _judge_numbers(100.0, SimpleNamespace(cost=100.0 - lr[0]), k, 1000, nu)[1]
    assert p0 == pytest.approx(p[0], rel=1e-9)
    err = math.sqrt(alpha * (1 - alpha) / draws)
    assert abs(np.mean(p < alpha) - alpha) < 4 * err
    naive = np.mean(stats.chi2.sf(lr, k) < alpha)
    if nu < 100:
        assert naive > alpha + 4 * err  # why F and not χ²: the σ̂ error matters


def test_delta_bic_is_the_ratio_less_the_parameters_penalty() -> None:
    lr, _, dbic = _judge_numbers(500.0, SimpleNamespace(cost=400.0), 2, 1000, 50)
    assert lr == 100.0 and dbic == pytest.approx(100.0 - 2 * math.log(1000))
    # a fit ending above the base (LM's tolerance) is no evidence against it
    assert _judge_numbers(500.0, SimpleNamespace(cost=500.5), 2, 1000, 50)[0] == 0.0


def test_a_searched_shape_pays_for_every_shape_it_could_have_taken(twin_problem) -> None:
    # the best of G shapes is the maximum of G statistics: its p is G times the raw one
    # (the union bound), capped at 1; a term without a shape has one look
    assert looks("quadratic_drag", twin_problem) == 1
    g = looks("position_bump", twin_problem)
    assert g == cat.grid_size(cat.candidate("position_bump").grid(twin_problem)) > 100
    fit = CandidateFit("position_bump", None, None, 3, 40.0, 1e-6, 19.0, {}, g)  # type: ignore[arg-type]
    assert fit.p_value == pytest.approx(g * 1e-6)
    assert replace(fit, p_raw=0.5).p_value == 1.0
    # on a null record the best of G shapes would pass α at rate ~G·α; calibrated, at ≤ α
    rng = np.random.default_rng(4)
    draws, k, nu, alpha = 4000, 1, 400, 0.01
    lr = np.max(rng.chisquare(k, size=(draws, g)), axis=1)  # independent shapes: worst case
    raw = f_pvalue(lr, k, nu)
    assert np.mean(raw < alpha) > 0.5
    assert np.mean(np.minimum(1.0, g * raw) < alpha) <= alpha + 4 * math.sqrt(alpha / draws)


def _fitted(residual: np.ndarray, x: np.ndarray, segment: int) -> Fitted:
    n = x.shape[0]
    fit = SimpleNamespace(
        x_sim=x + residual,
        x_scale=1.0,
        segment_of=np.minimum(np.arange(n) // segment, n // segment - 1),
    )
    sup = SimpleNamespace(record=SimpleNamespace(x=x, n=n))
    return Fitted(sup, (), fit)  # type: ignore[arg-type]


def test_vuong_tells_a_better_model_from_an_equal_one() -> None:
    rng = np.random.default_rng(5)
    n, L = 2000, 50
    x = np.zeros(n)
    a, b = rng.normal(size=n), rng.normal(size=n)
    # two models that leave the same kind of residual: no preference
    t_equal, dof = vuong(_fitted(a, x, L), _fitted(b, x, L))
    assert dof == n // L - 1 and abs(t_equal) < 3.0
    # one leaves a structured misfit of 0.5 σ over a tenth of the record more
    bump = np.where((np.arange(n) > 900) & (np.arange(n) < 1100), 0.5, 0.0)
    t_better, _ = vuong(_fitted(a, x, L), _fitted(a + bump, x, L))
    assert t_better > stats.t.ppf(0.95, dof)
    # the statistic is antisymmetric
    assert vuong(_fitted(a + bump, x, L), _fitted(a, x, L))[0] == pytest.approx(-t_better)


@pytest.mark.slow  # a 0.5 s twin simulated at 16 sub-steps, and the ranking compiled
def test_the_ranking_starts_a_hidden_harmonic_at_its_frequency(paper_config: Config) -> None:
    f_true = 37.0
    truth = {**PAPER_TRUTH, "harm_A": 300.0, "harm_B": -200.0, "harm_f": f_true}
    rec, _ = paper_twin(
        duration=0.5, seed=3, model=PAPER_MODEL.with_terms([cat.ExtraHarmonic()]), truth=truth
    )
    pb = build_problem(rec, paper_config)
    sup = Superset.build(pb)
    truth = {**sup.problem.spec.as_dict(), **pb.spec.as_dict(pb.theta(PAPER_TRUTH))}
    base = Fitted(sup, (), SimpleNamespace(params=truth))  # type: ignore[arg-type]
    band = near_rest_band(pb, record_noise(pb).sigma_x)
    got = starts(base, "extra_harmonic", band, 2)
    axis = cat.candidate("extra_harmonic").grid(pb)["harm_f"]
    step = float(axis[1] - axis[0])
    assert len(got) == 2
    assert abs(got[0]["harm_f"] - f_true) <= step
    # a candidate without nonlinear parameters starts once, at the base
    assert starts(base, "quadratic_drag", band, 2) == [{}]


@pytest.fixture(scope="module")
def stribeck_diagnoses(paper_config: Config) -> dict[str, object]:
    drop = {"stribeck_A": 1500.0, "stribeck_vst": 0.05}

    def run(model: object, truth: dict[str, float]) -> object:
        rec, _ = paper_twin(duration=0.5, seed=5, model=model, truth=truth)
        pb = build_problem(rec, paper_config)
        return diagnose(
            pb,
            identify_settings=IdentifySettings(fast_compile=True),
            settings=DiagnoseSettings(max_terms=1, time_limit=math.inf),
        )

    return {
        "drop": run(PAPER_MODEL.with_terms([cat.GaussianStribeck()]), {**PAPER_TRUTH, **drop}),
        "null": run(PAPER_MODEL, PAPER_TRUTH),
    }


@pytest.mark.slow  # two whole diagnoses: every candidate's output-error fit compiled
def test_a_hidden_stribeck_drop_is_named_first_and_holds_out(stribeck_diagnoses) -> None:
    diag = stribeck_diagnoses["drop"]
    assert diag.findings and diag.findings[0].effect == "stribeck"
    f = diag.findings[0]
    assert any(v.judged and v.gain > 0 for v in f.heldout)
    # the record's equation-error EMS gets worse with the output-error refit (the filter's
    # bias at the drop): reported beside the finding as a warning, never a veto
    worse = any("EMS gets worse" in w for w in f.warnings)
    assert worse == (f.evidence["record_ems_gain"] < 0)
    assert f.p_value < 0.01 / len(diag.steps[0].fits) and f.delta_bic > 10


@pytest.mark.slow
def test_the_report_names_the_finding_with_its_held_out_gain(stribeck_diagnoses, tmp_path) -> None:
    paths = write_diagnosis(stribeck_diagnoses["drop"], tmp_path)
    doc = json.loads(paths["json"].read_text())
    assert doc["findings"][0]["effect"] == "stribeck"
    tested = {row["effect"] for row in doc["candidates"][0]["tested"]}
    assert "stribeck" in tested and "presliding_hysteresis" not in tested  # not simulable
    md = paths["report"].read_text()
    assert "Finding 1: `stribeck`" in md and "held out:" in md
    assert "σ_x" in md and "m/s" in md


@pytest.mark.slow
def test_the_same_plant_without_it_gets_no_finding(stribeck_diagnoses) -> None:
    diag = stribeck_diagnoses["null"]
    assert diag.findings == []
    assert diag.fit["before"]["lack_of_fit_p"] > 0.01


def test_the_superset_with_every_term_pinned_is_the_base_model(twin_problem) -> None:
    # one compiled program serves every candidate only if the pinned terms add no force:
    # at their nulls the superset's residual is the base's, to rounding
    sup = Superset.build(twin_problem)
    assert "presliding_hysteresis" not in sup.effects and "stribeck" in sup.effects
    theta = twin_problem.theta(PAPER_TRUTH)
    full = sup.problem.spec.flatten(
        {**sup.problem.spec.as_dict(), **twin_problem.spec.as_dict(theta)}
    )
    base_r = twin_problem.residual(theta)
    np.testing.assert_allclose(sup.problem.residual(full), base_r, rtol=0, atol=1e-9)
    names = list(sup.problem.spec.free_names)
    moves = dict(zip(names, sup.moving(("stribeck",)), strict=True))
    assert moves["stribeck_A"] and moves["Fc"]  # the term under test and the base move
    assert not moves["harm_A"] and not moves["bump_x0"]  # every other term is held
    assert sup.moving(()).sum() == twin_problem.spec.n_free == sup.n_free(())
    assert sup.moving(("stribeck",)).sum() == sup.n_free(("stribeck",))
    assert sup.n_free(("stribeck",)) == twin_problem.spec.n_free + 2


def test_base_rounds_stop_when_the_time_limit_refuses_another(monkeypatch) -> None:
    """The judge's rounds of Levenberg–Marquardt continue while a round gains at least
    CONVERGED, and not past a refusal of ``more`` (the diagnosis' time limit): the first
    round always runs, ``more`` sees the last round's wall time."""
    import fricjax.diagnose.judge as judge

    costs = iter([100.0, 90.0, 80.0, 79.9, 79.8, 79.7])
    calls: list[float] = []
    bent: list[bool] = []

    def fake_fit(problem, free, start, settings, states, n_directions, accelerate=True):
        cost = next(costs)
        calls.append(cost)
        bent.append(accelerate)
        return SimpleNamespace(success=False, cost=cost, params={}, states_x=0, states_v=0)

    monkeypatch.setattr(judge, "_fit", fake_fit)
    fit = judge.converged(None, None, {}, None)
    # 100 -> 90 -> 80 gain 10 each, 80 -> 79.9 gains less than CONVERGED: the bent rounds
    # stop there, and one plain round gaining less than CONVERGED ends the fit
    assert calls == [100.0, 90.0, 80.0, 79.9, 79.8] and fit.cost == 79.8
    assert bent == [True, True, True, True, False]

    # a fit's own convergence flag does not end the rounds: LM's stop is local, and only a
    # restart that gains less than CONVERGED shows the minimum within reach
    def converged_fit(problem, free, start, settings, states, n_directions, accelerate=True):
        fit = fake_fit(problem, free, start, settings, states, n_directions, accelerate)
        return SimpleNamespace(**{**vars(fit), "success": True})

    costs = iter([100.0, 97.0, 96.9, 96.8])
    calls.clear()
    monkeypatch.setattr(judge, "_fit", converged_fit)
    fit = judge.converged(None, None, {}, None)
    assert calls == [100.0, 97.0, 96.9, 96.8] and fit.cost == 96.8

    monkeypatch.setattr(judge, "_fit", fake_fit)
    costs = iter([100.0, 90.0, 80.0])
    calls.clear()
    seen: list[float] = []
    fit = judge.converged(None, None, {}, None, more=lambda need: seen.append(need) or False)
    assert calls == [100.0] and fit.cost == 100.0
    assert len(seen) == 1 and seen[0] >= 0.0


def test_a_limit_stops_the_rows_between_calls_not_after_the_batch(monkeypatch) -> None:
    """On a CPU the rows of a step run one call each: a time limit or Ctrl-C (``more()``
    saying no) ends the batch after the row in flight, and the rounds of restarts stop
    with each fit at its best so far."""
    import fricjax.diagnose.judge as judge

    calls: list[int] = []

    def fake_batch(problem, rows, free, settings, states, k, held=None, accelerate=True):
        calls.append(len(rows))
        return [SimpleNamespace(cost=float(r[0]), params={}, states_x=0, states_v=0) for r in rows]

    monkeypatch.setattr(judge, "lanes_per_call", lambda: 1)
    monkeypatch.setattr(judge, "fit_output_error_batch", fake_batch)
    rows = [np.array([float(c)]) for c in (5, 4, 3, 2, 1)]
    state = (np.zeros(1), np.zeros(1))
    budget = iter([True, False])  # asked before the 2nd and the 3rd call
    fits = judge.fit_rows(None, rows, [None] * 5, None, [state] * 5, 1, more=lambda: next(budget))
    assert [f.cost for f in fits] == [5.0, 4.0] and calls == [1, 1]
    # without a limit every row runs
    calls.clear()
    assert len(judge.fit_rows(None, rows, [None] * 5, None, [state] * 5, 1)) == 5
    # restarts: none once the limit is hit, the fits kept as they were
    spec = SimpleNamespace(flatten=lambda params: np.array([0.0]))
    problem = SimpleNamespace(spec=spec)
    calls.clear()
    kept = judge.converged_rows(problem, fits, [None] * 2, None, 1, more=lambda: False)
    assert kept == fits and calls == []
