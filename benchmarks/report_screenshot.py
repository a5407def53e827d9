"""Render a diagnosis' ``report.html`` in a real headless browser and check the picture.

Run from the repository root::

    python benchmarks/report_screenshot.py DIR [--png OUT.png] [--width 1200 --height 2400]

``DIR`` holds a diagnosis (``fricjax diagnose ... --out DIR``). Chromium (Debian:
``apt-get install chromium``) renders ``DIR/report.html`` with ``--headless
--screenshot``; the screenshot must have the requested size and not be blank (a page that
failed to render is one flat colour; the report has text, tables and figures, so many
distinct grey levels over most of its rows). Exit 0 when it passes, 1 when the picture
fails a check, 2 when the browser or the report is missing (one line on stderr).
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
from matplotlib import image as mpimg

BROWSERS = ("chromium", "chromium-browser", "google-chrome")


def browser() -> str | None:
    """The first headless-capable Chromium on PATH, or None."""
    return next((p for b in BROWSERS if (p := shutil.which(b))), None)


def screenshot(html: Path, png: Path, width: int, height: int, exe: str) -> Path:
    """``exe --headless --screenshot`` of ``html`` at ``width`` × ``height`` CSS pixels."""
    with tempfile.TemporaryDirectory() as profile:
        subprocess.run(
            [
                exe,
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--hide-scrollbars",
                "--force-device-scale-factor=1",
                f"--user-data-dir={profile}",
                f"--window-size={width},{height}",
                f"--screenshot={png.resolve()}",
                html.resolve().as_uri(),
            ],
            check=True,
            capture_output=True,
            timeout=120,
        )
    return png


def check_picture(png: Path, width: int, height: int) -> list[str]:
    """What is wrong with the screenshot (empty list: nothing): its size, and whether it
    shows content: at least 30 distinct grey levels, and non-background pixels in at least
    a quarter of its rows."""
    img = mpimg.imread(png)
    problems = []
    if img.shape[:2] != (height, width):
        problems.append(f"size {img.shape[1]}×{img.shape[0]}, expected {width}×{height}")
    grey = np.round(255 * img[..., :3].mean(axis=2)).astype(int)
    levels = np.unique(grey).size
    if levels < 30:
        problems.append(f"only {levels} grey levels: blank or failed render")
    background = np.bincount(grey.ravel()).argmax()
    inked = np.mean(np.any(grey != background, axis=1))
    if inked < 0.25:
        problems.append(f"content in only {100 * inked:.0f} % of the rows")
    return problems


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("dir", type=Path, help="a diagnosis output directory")
    ap.add_argument("--png", type=Path, default=None, help="default: DIR/report.png")
    ap.add_argument("--width", type=int, default=1200)
    ap.add_argument("--height", type=int, default=2400)
    args = ap.parse_args(argv)
    html = args.dir / "report.html"
    if not html.is_file():
        print(f"error: {html}: no report (run fricjax diagnose --out {args.dir})", file=sys.stderr)
        return 2
    exe = browser()
    if exe is None:
        print("error: no chromium on PATH (Debian: apt-get install chromium)", file=sys.stderr)
        return 2
    png = args.png or args.dir / "report.png"
    screenshot(html, png, args.width, args.height, exe)
    problems = check_picture(png, args.width, args.height)
    for p in problems:
        print(f"FAIL {png}: {p}")
    if not problems:
        print(f"ok {png}: {args.width}×{args.height}, rendered by {Path(exe).name}")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
