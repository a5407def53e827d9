from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np

from fricjax.model.drive import HarmonicDrive, MeasuredInput
from fricjax.model.term import Signals


def test_harmonic_series_matches_numpy_reference() -> None:
    rng = np.random.default_rng(3)
    n_h = 7
    amps = rng.uniform(10, 1000, n_h)
    phases = rng.uniform(-math.pi, math.pi, n_h)
    omega, f0 = 2 * math.pi * 4.3, 123.4
    t = np.arange(500) / 1000.0
    p = {"F0": f0, "omega": omega}
    p.update({f"Fp_{i + 1}": amps[i] for i in range(n_h)})
    p.update({f"phi_{i + 1}": phases[i] for i in range(n_h)})
    p = {k: jnp.asarray(v) for k, v in p.items()}
    ref = f0 + sum(amps[i] * np.sin((i + 1) * omega * t + phases[i]) for i in range(n_h))
    z = jnp.zeros_like(jnp.asarray(t))
    got = HarmonicDrive(harmonics=n_h).force(p, Signals(jnp.asarray(t), z, z, z))
    np.testing.assert_allclose(np.asarray(got), ref, rtol=0, atol=1e-9)
    # scalar time (simulator) gives the same value
    s0 = Signals(jnp.asarray(t[123]), 0.0, 0.0, 0.0)
    assert abs(float(HarmonicDrive(harmonics=n_h).force(p, s0)) - ref[123]) < 1e-9


def test_measured_input_is_gain_times_u_minus_offset() -> None:
    u = jnp.linspace(-4, 4, 9)
    z = jnp.zeros_like(u)
    p = {"gain": jnp.asarray(35.15), "offset": jnp.asarray(-3.1648)}
    got = MeasuredInput().force(p, Signals(z, z, z, u))
    np.testing.assert_allclose(np.asarray(got), 35.15 * np.asarray(u) + 3.1648, rtol=1e-14)
