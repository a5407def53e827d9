"""IDIM anti-alias filter + decimation of residuals: zero phase, unit DC gain, pass and stop
bands, agreement with a second-order-section reference, linearity under JAX transforms."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import signal

from fricjax.data.decimate import (
    antialias_kernel,
    check_factor,
    decimate,
    decimate_np,
    decimated_length,
)
from fricjax.errors import FricjaxError

Q = 10
FS = 1000.0


@pytest.fixture(scope="module")
def kernel() -> np.ndarray:
    return antialias_kernel(Q)


def amplitude(y: np.ndarray, t: np.ndarray, f: float) -> float:
    """Least-squares amplitude of the f [Hz] sinusoid in y(t)."""
    basis = np.column_stack([np.sin(2 * np.pi * f * t), np.cos(2 * np.pi * f * t)])
    coef, *_ = np.linalg.lstsq(basis, y, rcond=None)
    return float(np.hypot(*coef))


def test_kernel_is_symmetric_with_unit_dc_gain(kernel: np.ndarray) -> None:
    assert kernel.shape[0] % 2 == 1
    np.testing.assert_array_equal(kernel, kernel[::-1])  # zero phase
    assert abs(kernel.sum() - 1.0) < 1e-15
    n = 4000
    const = decimate_np(np.full(n, -3.1648), Q)
    np.testing.assert_allclose(const, -3.1648, rtol=1e-13)  # an offset decimates to itself
    ramp = 0.2 + 0.05 * np.arange(n) / FS  # odd reflection continues a line exactly
    np.testing.assert_allclose(decimate_np(ramp, Q), ramp[::Q], rtol=0, atol=1e-13)
    assert const.shape[0] == decimated_length(n, Q) == 400
    assert decimated_length(4001, Q) == 401


def test_matches_forward_backward_sos_filter(kernel: np.ndarray) -> None:
    rng = np.random.default_rng(3)
    y = np.cumsum(rng.standard_normal(6000)) + 5.0 * np.sign(np.sin(np.arange(6000) / 300.0))
    sos = signal.cheby1(8, 0.05, 0.8 / Q, output="sos")
    _, h = signal.sosfreqz(sos, worN=[0.0])
    sos[0, :3] /= np.real(h[0])  # unit DC gain, as the kernel
    half = (kernel.shape[0] - 1) // 2
    ref = signal.sosfiltfilt(sos, y, padtype="odd", padlen=half)[::Q]
    ours = decimate_np(y, Q)
    assert np.max(np.abs(ours - ref)) < 1e-10 * np.max(np.abs(y))


@pytest.mark.parametrize(
    ("f", "lo", "hi"),
    [(5.0, 1.0, 1.012), (20.0, 1.0, 1.012), (35.0, 1.0, 1.012), (60.0, 0.0, 1e-4)],
)
def test_pass_band_and_stop_band(f: float, lo: float, hi: float) -> None:
    # Pass band up to 0.8 × the new Nyquist frequency (40 Hz): Chebyshev ripple of 0.05 dB
    # per pass, lifted to ≥ 1 by the unit-DC scaling; 60 Hz would alias onto 40 Hz.
    t = np.arange(20000) / FS
    d = decimate_np(np.sin(2 * np.pi * f * t), Q)
    gain = amplitude(d[100:-100], t[::Q][100:-100], f)
    assert lo - 1e-12 <= gain <= hi


def test_linear_under_jvp_and_vmap(kernel: np.ndarray) -> None:
    rng = np.random.default_rng(0)
    ys = jnp.asarray(rng.standard_normal((3, 3000)))
    k = jnp.asarray(kernel)
    out, tangent = jax.jvp(lambda y: decimate(y, k, Q), (ys[0],), (ys[1],))
    np.testing.assert_allclose(tangent, decimate(ys[1], k, Q), rtol=0, atol=1e-13)
    batched = jax.vmap(lambda y: decimate(y, k, Q))(ys)
    for i in range(3):
        np.testing.assert_allclose(batched[i], decimate(ys[i], k, Q), rtol=0, atol=1e-13)
    np.testing.assert_allclose(out, decimate(ys[0], k, Q), rtol=0, atol=0)


def test_bad_factor_and_short_record_refused(kernel: np.ndarray) -> None:
    with pytest.raises(FricjaxError, match=r"decimate: q: must be an integer >= 2, got 1"):
        antialias_kernel(1)
    with pytest.raises(FricjaxError, match=r"cfg.toml: decimate: must be an integer >= 1"):
        check_factor(0, "cfg.toml")
    assert check_factor(1) == 1 and decimate_np(np.arange(5.0), 1).tolist() == [0, 1, 2, 3, 4]
    half = (kernel.shape[0] - 1) // 2
    with pytest.raises(FricjaxError) as err:
        decimate(jnp.zeros(half), jnp.asarray(kernel), Q)
    assert "\n" not in str(err.value) and f"half length {half}" in str(err.value)
