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
    # The generator integrates with solve_ivp and numpy's sin/exp, whose last bits depend on
    # the CPU's vector unit: another machine writes other last digits. What must hold is
    # the layout exactly (header, length, time grid) and the signals far below their noise.
    gen = _generator()
    gen.main(tmp_path)
    for name in gen.RUNS:
        made, shipped = (tmp_path / name).read_text(), (EXAMPLES / name).read_text()
        assert made.splitlines()[0] == shipped.splitlines()[0] == "t,x,u", name
        a = np.loadtxt(tmp_path / name, delimiter=",", skiprows=1)
        b = np.loadtxt(EXAMPLES / name, delimiter=",", skiprows=1)
        assert a.shape == b.shape == (int(gen.RATE * gen.DURATION), 3), name
        np.testing.assert_array_equal(a[:, 0], b[:, 0])
        np.testing.assert_allclose(a[:, 1], b[:, 1], rtol=0, atol=1e-3 * gen.NOISE_X)
        np.testing.assert_allclose(a[:, 2], b[:, 2], rtol=0, atol=1e-3 * gen.NOISE_F)


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
