"""The figures a reader sees in README.md and docs/ come from committed results files.

Every paragraph or bullet of those pages that links a results file under
``benchmarks/results/`` may quote only figures that file holds: a decimal number must be
one of the file's numbers at the precision quoted, a count ``a/b`` must appear as ``a/b``,
``a of b`` or as its percentage; a table or list that such a paragraph introduces (it ends
with a colon) quotes the same files. A page updated by hand after a rerun therefore fails here
until its figures match the file the rerun wrote; a figure no results file holds cannot
hide behind a link. ``docs/history*.md`` is exempt: it records past figures on purpose.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
PAGES = [p for p in PAGES if not p.name.startswith("history")]

_LINK = re.compile(r"\]\(((?:\.\./)*benchmarks/results/[^)#\s]+\.md)(?:#[^)]*)?\)")
_FIGURE = re.compile(r"(?<![\w.])\d+\.\d+(?![\w.])|(?<![\w./])\d+/\d+(?![\w./])")
_NUMBER = re.compile(r"\d+\.\d+|\d+")


def holds(figure: str, source: str) -> bool:
    """Whether ``source`` (a results file's text) holds ``figure`` as quoted."""
    plain = source.replace(",", "")
    if "/" in figure:
        a, b = (int(s) for s in figure.split("/"))
        percent = f"{100 * a / b:.0f} %" if b else ""
        return figure in source or f"{a} of {b}" in source or (bool(b) and percent in source)
    places = len(figure.split(".")[1])
    value = float(figure)
    return any(round(float(s), places) == value for s in _NUMBER.findall(plain))


def _blocks(text: str) -> list[str]:
    """Paragraphs and bullets (a bullet's continuation lines included)."""
    return [b for b in re.split(r"\n(?=- |\d+\. )|\n\s*\n", text) if b.strip()]


def test_holds_compares_at_the_quoted_precision() -> None:
    source = "| csaa + LM | 100 % | 0.518 s | 1,084 |\nran 9 of 10"
    assert holds("0.52", source) and holds("0.518", source) and holds("1084.0", source)
    assert not holds("0.51", source) and not holds("0.5180", "0.5181")
    assert holds("10/10", source) and holds("9/10", source) and not holds("8/10", source)


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_linked_figure_is_in_its_results_file(page: Path) -> None:
    wrong = []
    introduced: list[str] = []
    for block in _blocks(page.read_text(encoding="utf-8")):
        # a table or list introduced by a paragraph that links results ("…, results):")
        # quotes that paragraph's results
        links = _LINK.findall(block) or (introduced if block.lstrip()[:1] in "|-" else [])
        introduced = links if block.rstrip().endswith(":") else []
        if not links:
            continue
        files = [(page.parent / link).resolve() for link in links]
        missing = [str(f.relative_to(ROOT)) for f in files if not f.exists()]
        assert not missing, f"{page.name} links results that are not committed: {missing}"
        source = "\n".join(f.read_text(encoding="utf-8") for f in files)
        prose = re.sub(r"\]\([^)]*\)", "]", block)  # link targets are not figures
        wrong += [
            f"{figure!r} in “{block.strip()[:70]}…”"
            for figure in _FIGURE.findall(prose)
            if not holds(figure, source)
        ]
    assert wrong == [], f"{page.name}: figures not in the linked results: {wrong}"


def _runner():  # docs/run_commands.py is a script beside the pages, not a package module
    import importlib.util

    spec = importlib.util.spec_from_file_location("run_commands", ROOT / "docs" / "run_commands.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_printed_outputs_compare_words_exactly_and_numbers_to_a_tolerance() -> None:
    same = _runner().same_output
    assert same("EMS 8.514509 N²", "EMS 8.5145 N²")
    assert not same("EMS 8.51 N²", "EMS 9.51 N²")
    assert not same("impact: p = 0.01", "stribeck: p = 0.01")
    assert not same("a 1 b", "a 1 b 2")
    assert same("wall time [s]  7.20\nEMS 8.5", "wall time [s]  13.32\nEMS 8.5")


def test_the_user_guide_marks_its_printed_outputs() -> None:
    text = (ROOT / "docs" / "user-guide.md").read_text(encoding="utf-8")
    commands = [m.group("commands") for m in _runner().BLOCK.finditer(text)]
    assert any(c.startswith("fricjax diagnose") for c in commands)
    assert any(c.startswith("fricjax identify") for c in commands)


@pytest.mark.slow
def test_the_user_guide_prints_what_its_commands_print_now() -> None:
    # about 5 minutes on 2 cores: every command of the guide, run as written
    page = ROOT / "docs" / "user-guide.md"
    assert _runner().main([str(page), "--check"]) == 0
