"""One report, two renderings: a list of blocks written as Markdown and as a self-contained
HTML page (images embedded as base64 data URIs, no external asset), so that both say the
same thing from the same numbers.

Inline markup in block text: ``**bold**`` and ```code```; nothing else is interpreted.
"""

from __future__ import annotations

import base64
import html
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Heading:
    text: str
    level: int = 2


@dataclass(frozen=True)
class Para:
    text: str
    # "note": a highlighted remark (a warning the reader must not miss)
    kind: str = ""


@dataclass(frozen=True)
class Items:
    items: tuple[str, ...]
    ordered: bool = False


@dataclass(frozen=True)
class Table:
    header: tuple[str, ...]
    rows: tuple[tuple[str, ...], ...]


@dataclass(frozen=True)
class Image:
    path: Path
    caption: str


Block = Heading | Para | Items | Table | Image


def to_markdown(blocks: Sequence[Block]) -> str:
    """GitHub-flavoured Markdown; images linked by file name (they lie beside the report)."""
    out: list[str] = []
    for b in blocks:
        if isinstance(b, Heading):
            out += ["#" * b.level + " " + b.text, ""]
        elif isinstance(b, Para):
            out += [("> " if b.kind == "note" else "") + b.text, ""]
        elif isinstance(b, Items):
            out += [
                (f"{i}. " if b.ordered else "- ") + item.replace("\n", "\n   ")
                for i, item in enumerate(b.items, 1)
            ] + [""]
        elif isinstance(b, Table):
            out.append("| " + " | ".join(_md_cell(c) for c in b.header) + " |")
            out.append("|" + "|".join("---" for _ in b.header) + "|")
            out += ["| " + " | ".join(_md_cell(c) for c in row) + " |" for row in b.rows]
            out.append("")
        elif isinstance(b, Image):
            out += [f"![{b.caption}]({b.path.name})", "", f"*{b.caption}*", ""]
    return "\n".join(out).rstrip() + "\n"


def _md_cell(text: str) -> str:
    return text.replace("|", "\\|")


_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;max-width:1040px;
margin:2em auto;padding:0 1.5em;color:#1d1d1f;line-height:1.5;background:#fff}
h1{font-size:1.7em;border-bottom:2px solid #c33;padding-bottom:.2em}
h2{font-size:1.3em;margin-top:1.8em;border-bottom:1px solid #ddd}
h3{font-size:1.1em;margin-top:1.4em}
code{background:#f3f3f3;padding:0 .25em;border-radius:3px;font-size:.92em}
table{border-collapse:collapse;margin:.8em 0;font-size:.92em}
th,td{border:1px solid #ccc;padding:.3em .6em;text-align:right}
th:first-child,td:first-child{text-align:left}
th{background:#f4f4f4}
.note{background:#fff4e0;border-left:4px solid #e69500;padding:.5em .8em}
figure{margin:1em 0}figure img{max-width:100%;border:1px solid #eee}
figcaption{font-size:.9em;color:#555}
"""


def _inline(text: str) -> str:
    s = html.escape(text, quote=False)
    s = re.sub(r"`([^`]+)`", r"<code>\1</code>", s)
    return re.sub(r"\*\*([^*]+)\*\*", r"<strong>\1</strong>", s)


def to_html(blocks: Sequence[Block], title: str) -> str:
    """One HTML page; every image read from disk and embedded as a base64 PNG."""
    body: list[str] = []
    for b in blocks:
        if isinstance(b, Heading):
            body.append(f"<h{b.level}>{_inline(b.text)}</h{b.level}>")
        elif isinstance(b, Para):
            cls = ' class="note"' if b.kind == "note" else ""
            body.append(f"<p{cls}>{_inline(b.text)}</p>")
        elif isinstance(b, Items):
            tag = "ol" if b.ordered else "ul"
            lis = "".join(
                "<li>" + "<br>".join(_inline(line) for line in item.split("\n")) + "</li>"
                for item in b.items
            )
            body.append(f"<{tag}>{lis}</{tag}>")
        elif isinstance(b, Table):
            head = "".join(f"<th>{_inline(c)}</th>" for c in b.header)
            rows = "".join(
                "<tr>" + "".join(f"<td>{_inline(c)}</td>" for c in row) + "</tr>" for row in b.rows
            )
            body.append(f"<table><thead><tr>{head}</tr></thead><tbody>{rows}</tbody></table>")
        elif isinstance(b, Image):
            data = base64.b64encode(b.path.read_bytes()).decode("ascii")
            body.append(
                f'<figure><img alt="{html.escape(b.caption)}" '
                f'src="data:image/png;base64,{data}"><figcaption>{_inline(b.caption)}'
                "</figcaption></figure>"
            )
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>{html.escape(title)}</title><style>{_CSS}</style></head><body>\n"
        + "\n".join(body)
        + "\n</body></html>\n"
    )
