"""The shipped example recordings (examples/) are what their generator writes, and the
generator's plant obeys its equation of motion."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _generator():
    spec = importlib.util.spec_from_file_location("make_axis_csv", EXAMPLES / "make_axis_csv.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_committed_recordings_are_the_generated_ones(tmp_path: Path) -> None:
    gen = _generator()
    gen.main(tmp_path)
    for name in gen.RUNS:
        assert (tmp_path / name).read_bytes() == (EXAMPLES / name).read_bytes(), name


def test_generated_motion_satisfies_the_friction_law() -> None:
    gen = _generator()
    t = np.arange(4000) / 2000.0
    profile = gen.RUNS["axis.csv"][1]
    x = gen.simulate(t, profile)
    v, a = np.gradient(x, t), np.gradient(np.gradient(x, t), t)
    sliding = np.abs(v) > 0.05  # away from stops, where the central differences hold
    f = gen.force(t, profile)
    law = np.array([gen.friction(float(s)) for s in v])
    # m·a = F − F_f(v) to the accuracy of second differences at 0.5 ms steps
    scale = np.max(np.abs(f))
    assert np.max(np.abs(gen.MASS * a - (f - law))[sliding][2:-2]) < 1e-2 * scale
    stuck = np.abs(v) < 1e-9
    assert stuck.any() and np.all(np.abs(f[stuck][1:-1]) <= gen.FS + 0.05)
