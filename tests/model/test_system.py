"""Facts about the force balance: the stick/slip rule on samples at rest."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from fricjax.data.twin import PAPER_MODEL, PAPER_TRUTH
from fricjax.model.friction import CoulombViscous
from fricjax.model.system import Model
from fricjax.model.term import Signals


def _signals(n: int = 400) -> Signals:
    t = jnp.linspace(0.0, 0.4, n)
    # velocity noise around zero: what the filtered v of a stuck body looks like
    v = jnp.asarray(np.random.default_rng(0).normal(0.0, 3e-3, n))
    return Signals(t, jnp.zeros(n), v, jnp.zeros(n))


def _params() -> dict[str, jnp.ndarray]:
    return {k: jnp.asarray(v) for k, v in PAPER_TRUTH.items()}


def test_a_body_at_rest_feels_no_net_force_until_the_drive_exceeds_the_static_limit() -> None:
    p, s = _params(), _signals()
    drive = np.asarray(PAPER_MODEL.drive(p, s))
    rest = np.asarray(PAPER_MODEL.rest_force(p, s))
    fs = float(PAPER_TRUTH["Fs"])
    stuck = np.abs(drive) <= fs
    assert stuck.any() and (~stuck).any()  # the drive crosses the static limit
    assert np.all(rest[stuck] == 0.0)
    np.testing.assert_allclose(rest[~stuck], drive[~stuck] - fs * np.sign(drive[~stuck]))
    # It never evaluates sgn(v): the sliding law on the same noise flips by 2·Fs.
    sliding = np.asarray(PAPER_MODEL.force(p, s))
    assert np.max(np.abs(sliding[stuck] - rest[stuck])) > fs


def test_the_residual_uses_the_rule_only_on_the_samples_marked_at_rest() -> None:
    p, s = _params(), _signals()
    a = jnp.asarray(np.random.default_rng(1).normal(0.0, 1.0, s.t.shape[0]))
    rest = np.zeros(s.t.shape[0], dtype=bool)
    rest[100:250] = True
    plain = np.asarray(PAPER_MODEL.residual(p, s, a))
    ruled = np.asarray(PAPER_MODEL.residual(p, s, a, jnp.asarray(rest)))
    np.testing.assert_array_equal(ruled[~rest], plain[~rest])
    expected = p["mass"] * np.asarray(a) - np.asarray(PAPER_MODEL.rest_force(p, s))
    np.testing.assert_allclose(ruled[rest], expected[rest], rtol=1e-14)


def test_the_limit_is_the_friction_terms_own_static_level() -> None:
    # Coulomb–viscous friction has no Stribeck excess: a body at rest breaks away at Fc.
    model = Model((PAPER_MODEL.terms[0], CoulombViscous()))
    p = {**_params(), "Fc": jnp.asarray(250.0), "Fv": jnp.asarray(3000.0)}
    s = _signals()
    drive = np.asarray(model.drive(p, s))
    rest = np.asarray(model.rest_force(p, s))
    stuck = np.abs(drive) <= 250.0
    assert stuck.any() and (~stuck).any()
    assert np.all(rest[stuck] == 0.0)
    np.testing.assert_allclose(rest[~stuck], drive[~stuck] - 250.0 * np.sign(drive[~stuck]))
