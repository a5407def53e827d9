"""The diagnosis' settings and its ``unexplained`` finding (fricjax.diagnose.run): a mistake in
the ``[diagnose]`` table is one line naming it; where the model misfits the record's noise the
finding names the place that misfits most, never a catalogue effect."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from fricjax.diagnose.run import DiagnoseSettings, _unexplained
from fricjax.errors import FricjaxError
from fricjax.params import Param, ParamSpec


def test_diagnose_settings_refuse_a_wrong_type_or_range_in_one_line() -> None:
    cases = [
        ({"alpha": "0.01"}, "c.toml: [diagnose].alpha: must be in (0, 1), got '0.01'"),
        ({"alpha": 1.0}, "c.toml: [diagnose].alpha: must be in (0, 1), got 1.0"),
        ({"ambiguity": 1.5}, "c.toml: [diagnose].ambiguity: must be in (0, 1), got 1.5"),
        ({"max_terms": True}, "c.toml: [diagnose].max_terms: must be >= 1, got True"),
        ({"n_starts": 0}, "c.toml: [diagnose].n_starts: must be >= 1, got 0"),
        ({"n_mc": 10}, "c.toml: [diagnose].n_mc: unknown key"),
    ]
    for table, message in cases:
        with pytest.raises(FricjaxError) as err:
            DiagnoseSettings.from_dict(table, source="c.toml")
        assert str(err.value).startswith(message) and "\n" not in str(err.value)
    with pytest.raises(FricjaxError, match=r"^command line: --max-terms: must be >= 1, got 0$"):
        DiagnoseSettings.from_dict({"max_terms": 0}, source="command line", flags=True)
    # an integer where a float is meant is the same number
    assert DiagnoseSettings.from_dict({"min_delta_bic": 6}).min_delta_bic == 6.0


def test_the_output_error_is_in_units_of_the_record_s_own_noise() -> None:
    ev = SimpleNamespace(sigma_x=2.5e-5)
    oe = DiagnoseSettings(segment_s=0.05).output_error(ev)  # type: ignore[arg-type]
    assert oe.x_scale == 2.5e-5 and oe.segment_s == 0.05


def test_unexplained_names_the_segment_that_misfits_most() -> None:
    n, L, sigma = 300, 50, 1e-5
    t = np.arange(n) / 1000.0
    x = 0.01 * np.sin(2 * np.pi * 3 * t)
    rng = np.random.default_rng(0)
    x_sim = x + sigma * rng.normal(size=n)
    x_sim[150:200] += 6 * sigma  # something the model lacks, in the fourth segment only
    fit = SimpleNamespace(
        x_sim=x_sim,
        x_scale=sigma,
        segment_samples=L,
        segment_of=np.arange(n) // L,
        n_segments=6,
        n_residual=n + 10,
        cost=float(np.sum(((x_sim - x) / sigma) ** 2)),
    )
    pb = SimpleNamespace(
        t=t, x=x, n=n, v=np.gradient(x, t), spec=ParamSpec((Param("Fc", "N", 0, 1, 0.5),))
    )
    model = SimpleNamespace(problem=pb, fit=fit, n_free=1)
    f = _unexplained(model, 1e-9, 50)  # type: ignore[arg-type]
    assert f.effect == "unexplained" and f.p_value == 1e-9
    assert f.location["time_s"] == [pytest.approx(0.15), pytest.approx(0.199)]
    assert f.delta_bic > 0  # the excess over the residual degrees of freedom
