from __future__ import annotations

import math
import re
from pathlib import Path

import pytest

from fricjax.config import Config, load_config
from fricjax.errors import FricjaxError

ROOT = Path(__file__).resolve().parents[1]


def test_paper_config_has_the_seed_parameters(paper_config: Config) -> None:
    spec = paper_config.spec
    assert spec.n_free == 26 and "delta" in spec and not spec["delta"].free
    assert spec["delta"].init == 1.0
    csaa = {"F0": 432.7, "Fc": 30.0, "Fv": 3749.9, "Fs": 189.99, "Fp_3": 1118.9, "Fp_10": 9.99}
    for name, value in csaa.items():
        assert spec[name].lower == pytest.approx(0.5 * value)
        assert spec[name].upper == pytest.approx(1.5 * value)
    assert (spec["vs"].lower, spec["vs"].upper) == (0.02, 0.5)
    assert spec["omega"].lower == pytest.approx(2 * math.pi * 3)
    assert spec["omega"].upper == pytest.approx(2 * math.pi * 8)
    assert spec["phi_7"].lower == pytest.approx(-math.pi)


def _write(tmp_path: Path, body: str) -> Path:
    path = tmp_path / "bad.toml"
    path.write_text('[model]\nterms = ["coulomb_viscous"]\n[params]\n' + body)
    return path


@pytest.mark.parametrize(
    ("body", "message"),
    [
        (
            "Fc = {lower = 0, upper = 1}\nFv = {lower = 0, upper = 1}\nFq = 3\n",
            r"\[params\].Fq: unknown parameter",
        ),
        (
            "Fc = {lower = 2, upper = 1}\nFv = {lower = 0, upper = 1}\n",
            r"\[params\].Fc: lower bound 2 > upper bound 1",
        ),
        (
            "Fc = {value = 5, lower = 0, upper = 1}\nFv = {lower = 0, upper = 1}\n",
            r"\[params\].Fc: fixed value 5 outside its bounds",
        ),
        ("Fc = {lower = 0, upper = 1}\n", r"\[params\].Fv: missing"),
        (
            'Fc = {unit = "kN", lower = 0, upper = 1}\nFv = {lower = 0, upper = 1}\n',
            r"\[params\].Fc: wrong unit 'kN'",
        ),
        ('Fc = {lower = 0, upper = "x"}\nFv = {lower = 0, upper = 1}\n', r"upper must be a number"),
    ],
)
def test_bad_configs_are_refused_with_one_line(tmp_path: Path, body: str, message: str) -> None:
    with pytest.raises(FricjaxError, match=message) as err:
        load_config(_write(tmp_path, body))
    assert "bad.toml" in str(err.value) and "\n" not in str(err.value)


def test_unknown_term_and_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "c.toml"
    path.write_text('[model]\nterms = ["warp_drive"]\n')
    with pytest.raises(FricjaxError, match="unknown term 'warp_drive'"):
        load_config(path)
    with pytest.raises(FricjaxError, match="config file not found"):
        load_config(tmp_path / "nope.toml")


def test_output_error_table_reaches_identify_settings(tmp_path):
    from pathlib import Path

    from fricjax.identify import IdentifySettings

    text = (Path(__file__).resolve().parents[1] / "configs" / "emps.toml").read_text()
    path = tmp_path / "oe.toml"
    path.write_text(text + "\n[output_error]\nsegment_s = 0.25\nsubsteps = 2\n")
    cfg = load_config(path)
    s = IdentifySettings.from_tables(
        cfg.tables, source=cfg.source, overrides={"objective": "simulation"}
    )
    assert s.objective == "simulation"
    assert s.output_error.segment_s == 0.25 and s.output_error.substeps == 2
    with pytest.raises(FricjaxError, match=r"oe\.toml.*segment_s"):
        IdentifySettings.from_tables(
            {**cfg.tables, "output_error": {"segment_s": -1.0}}, source=cfg.source
        )


def test_a_bad_setting_is_blamed_on_where_it_came_from():
    from fricjax.identify import IdentifySettings

    tables = {"search": {"chains": 4}, "anneal": {"alpha": 0.9}}
    cases = [
        ({"chains": 0}, "command line: --chains: must be >= 1, got 0"),
        ({"method": "tabu"}, "command line: --method: unknown method 'tabu'"),
        ({"alpha": 1.5}, "command line: alpha: must be in (0, 1), got 1.5"),
    ]
    for overrides, message in cases:
        with pytest.raises(FricjaxError, match=re.escape(message)):
            IdentifySettings.from_tables(tables, source="c.toml", overrides=overrides)
    bad_chains = {"search": {"chains": 0}}
    with pytest.raises(FricjaxError, match=re.escape("c.toml: [search].chains: must be >= 1")):
        IdentifySettings.from_tables(bad_chains, source="c.toml", overrides={"alpha": 0.5})
    bad_alpha = {"anneal": {"alpha": 1.5}}
    with pytest.raises(FricjaxError, match=re.escape("c.toml: alpha: must be in (0, 1)")):
        IdentifySettings.from_tables(bad_alpha, source="c.toml", overrides={"chains": 2})
    # A valid command-line value over a valid file value wins.
    s = IdentifySettings.from_tables(tables, source="c.toml", overrides={"chains": 2, "alpha": 0.5})
    assert s.chains == 2 and s.anneal.alpha == 0.5
