"""The config reference page: generated from the term registry, committed in step with it."""

from __future__ import annotations

from pathlib import Path

from fricjax.model.registry import TERMS
from fricjax.report.reference import config_reference

PAGE = Path(__file__).resolve().parents[2] / "docs" / "config-reference.md"


def test_committed_page_is_the_generated_one() -> None:
    # After changing a term or a setting:
    #     python -m fricjax.report.reference docs/config-reference.md
    assert PAGE.read_text() == config_reference()


def test_every_term_and_parameter_is_listed_with_its_linearity() -> None:
    text = config_reference()
    for name, factory in TERMS.items():
        section = text[text.index(f"### `{name}` (") :]
        section = section[: section.index("\n### ", 1)] if "\n### " in section[1:] else section
        for p in factory().parameters():
            base = p.name.rsplit("_", 1)[0] if p.name[-1].isdigit() else p.name
            assert f"`{p.name}`" in section or f"`{base}_i`" in section, (name, p.name)
    # F = Fc·sgn(v) + Fv·v is linear in Fc and Fv; the Stribeck velocity enters through exp.
    assert "| `Fc` | `N` | [0, 10000] | free | yes | yes | 0 |" in text
    assert "| `vs` | `m/s` | [0.0001, 10] | free | no | no |  |" in text
    assert "| `phi_i` (i = 1..10) | `rad` | [-3.14159, 3.14159] | free | no | yes |  |" in text
