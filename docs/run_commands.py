"""Regenerate the printed output of a documentation page by running its commands.

A page marks a command block whose output it shows with ``<!-- run -->`` on the line before
the block::

    <!-- run -->
    ```bash
    fricjax identify examples/axis.csv --config examples/axis.toml --out out/axis.h5
    ```

    ```text
    (replaced by what the commands print on standard output)
    ```

Each line of the ``bash`` block runs from the repository root in order (progress and
warnings on standard error are not shown); the ``text`` block right after it is replaced by
their standard output. A command that fails stops the run with its error, and the page is
left as it was. Usage::

    python docs/run_commands.py docs/user-guide.md [--check]

``--check`` writes nothing and exits 1 when the page's printed output is not what the
commands print now (numbers compared to 2 % or 1e-6, since another CPU rounds differently;
the words exactly; the figures of a timing line not at all).
"""

from __future__ import annotations

import argparse
import math
import os
import re
import shlex
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BLOCK = re.compile(
    r"(<!-- run -->\n```bash\n(?P<commands>.*?)\n```\n\n```text\n)(?P<output>.*?)(\n```)", re.S
)
NUMBER = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")


def run_block(commands: str) -> str:
    """The standard output of each command of a block, run from the repository root."""
    out = []
    env = {**os.environ, "COLUMNS": "100", "NO_COLOR": "1"}
    for line in commands.splitlines():
        line = line.split("  #", 1)[0].strip()
        if not line:
            continue
        argv = shlex.split(line)
        if argv[0] == "fricjax":  # the console script of this checkout's environment
            argv = [sys.executable, "-m", "fricjax.cli", *argv[1:]]
        elif argv[0] == "python":  # this environment's interpreter, not the PATH's
            argv = [sys.executable, *argv[1:]]
        done = subprocess.run(argv, cwd=ROOT, env=env, capture_output=True, text=True)
        if done.returncode not in (0,):
            raise SystemExit(f"{line}: exit {done.returncode}\n{done.stderr[-2000:]}")
        out.append(done.stdout.rstrip("\n"))
    return "\n".join(out)


def regenerate(text: str) -> str:
    """``text`` with the output of every marked block replaced by what it prints now."""
    return BLOCK.sub(lambda m: m.group(1) + run_block(m.group("commands")) + m.group(4), text)


#: Lines whose figures are timings: compared by their words only.
TIMING = re.compile(r"wall time|\btook\b|\bs/case\b")


def same_output(a: str, b: str, rtol: float = 0.02, atol: float = 1e-6) -> bool:
    """Whether two printed outputs agree: the same words, numbers within the tolerance
    (a timing's numbers not compared: they measure the machine, not the result)."""
    a, b = (
        "\n".join(NUMBER.sub("#", ln) if TIMING.search(ln) else ln for ln in x.splitlines())
        for x in (a, b)
    )
    words_a, words_b = NUMBER.sub("#", a).split(), NUMBER.sub("#", b).split()
    if words_a != words_b:
        return False
    nums_a, nums_b = NUMBER.findall(a), NUMBER.findall(b)
    return all(
        math.isclose(float(x), float(y), rel_tol=rtol, abs_tol=atol)
        for x, y in zip(nums_a, nums_b, strict=True)
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("page", type=Path)
    parser.add_argument("--check", action="store_true", help="compare, write nothing")
    args = parser.parse_args(argv)
    text = args.page.read_text(encoding="utf-8")
    if not BLOCK.search(text):
        print(f"{args.page}: no <!-- run --> block", file=sys.stderr)
        return 2
    new = regenerate(text)
    if args.check:
        old_blocks = [m.group("output") for m in BLOCK.finditer(text)]
        new_blocks = [m.group("output") for m in BLOCK.finditer(new)]
        stale = [
            i
            for i, (a, b) in enumerate(zip(old_blocks, new_blocks, strict=True))
            if not same_output(a, b)
        ]
        for i in stale:
            print(f"{args.page}: printed output {i + 1} is stale:\n{new_blocks[i]}")
        return 1 if stale else 0
    with tempfile.NamedTemporaryFile("w", dir=args.page.parent, delete=False, suffix=".md") as f:
        f.write(new)
    os.replace(f.name, args.page)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
