"""The held-out check (fricjax/diagnose/run.py: heldout_check): a true term pays on the part
of the record the fit has not seen, a term the data do not contain does not."""

from __future__ import annotations

import numpy as np
import pytest

import fricjax.diagnose.catalogue as cat
from fricjax.config import Config
from fricjax.data.twin import PAPER_MODEL, PAPER_TRUTH, paper_twin
from fricjax.diagnose.run import heldout_check
from fricjax.problem import build_problem

HARMONIC = {"harm_A": 60.0, "harm_B": 0.0, "harm_f": 37.0}


def _check(config: Config, hidden: bool) -> dict[str, float]:
    term = cat.ExtraHarmonic()
    truth = {**PAPER_TRUTH, **HARMONIC} if hidden else dict(PAPER_TRUTH)
    model = PAPER_MODEL.with_terms([term]) if hidden else PAPER_MODEL
    rec, _ = paper_twin(duration=1.0, seed=5, model=model, truth=truth)
    problem = build_problem(rec, config)
    ext = cat.candidate("extra_harmonic").extend_problem(problem, {"harm_f": 37.0})
    named = {**PAPER_TRUTH, "harm_A": 0.0, "harm_B": 0.0, "harm_f": 37.0}
    base = (problem.model, problem.spec, problem.theta(PAPER_TRUTH))
    final = (ext.model, ext.spec, ext.spec.flatten({k: named[k] for k in ext.spec.free_names}))
    return heldout_check(problem, base, final, 0.3)


@pytest.fixture(scope="module")
def checks(paper_config: Config) -> dict[bool, dict[str, float]]:
    return {hidden: _check(paper_config, hidden) for hidden in (True, False)}


def test_a_hidden_harmonic_pays_on_the_held_out_part(checks: dict) -> None:
    h = checks[True]
    # 60 N at 37 Hz on the last 0.3 s: the whitened test RSS must fall by a large fraction
    assert h["improvement"] > 0.2
    assert h["rss_w_after"] < h["rss_w_before"]
    assert h["on"] == "last 30% of the record"


def test_a_term_the_record_lacks_gains_nothing_on_the_held_out_part(checks: dict) -> None:
    h = checks[False]
    # fitting 3 extra parameters to noise on the training part can only cost on the test
    # part, up to chance: the whitened RSS is ~ sigma^2 * dof, so a few parameters' worth
    assert h["improvement"] < 3.0 / h["dof"] + 0.02
    # the whitened test RSS of the base is noise-sized: dof * sigma_x^2 within a factor 2
    sigma2 = 24e-6**2
    assert 0.5 < h["rss_w_before"] / (h["dof"] * sigma2) < 2.0
    assert np.isfinite(h["ems_before"]) and np.isfinite(h["ems_after"])
