"""Variable projection: the linear declarations of the terms, the projected cost and its
bounds, the separable identify path, and the errors of a model that is not separable."""

from __future__ import annotations

import dataclasses
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from fricjax.config import Config, parse_config
from fricjax.errors import FricjaxError
from fricjax.identify import IdentifySettings, identify, with_settings
from fricjax.model.drive import HarmonicDrive, MeasuredInput
from fricjax.model.friction import CoulombViscous, StribeckFriction
from fricjax.model.system import MASS, Model
from fricjax.model.term import Signals, Term
from fricjax.params import Param, ParamSpec
from fricjax.problem import Problem
from fricjax.search.separable import Separable, separate


@eqx.filter_jit
def _full_cost(problem_cost: eqx.Module, theta: jax.Array) -> jax.Array:
    return jax.vmap(problem_cost)(theta)


BATCH = 6  # every projection below runs on this many points: one compilation


def _project(sep: Separable, theta_nl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``sep.project`` on ``theta_nl`` padded to BATCH rows (copies of the first)."""
    n = theta_nl.shape[0]
    padded = np.concatenate([theta_nl, np.repeat(theta_nl[:1], BATCH - n, axis=0)])
    full, cost = sep.project(padded)
    return full[:n], cost[:n]


def _uniform(rng: np.random.Generator, spec: ParamSpec, n: int) -> np.ndarray:
    return spec.lower + rng.random((n, spec.n_free)) * (spec.upper - spec.lower)


def _lin_columns(problem: Problem, sep: Separable, theta_nl: np.ndarray):
    """Ψ_S [n, k_S] and y [n] of the twin at θ_nl, in numpy (the reference least squares)."""
    lay = sep.layout
    theta = problem.spec.init.copy()
    theta[list(lay.nl_index)] = theta_nl
    p = problem.spec.unflatten(jnp.asarray(theta))
    psi = np.asarray(
        problem.model.residual_basis(p, problem.signals, jnp.asarray(problem.a)).columns
    )
    c0 = np.asarray(problem.model.to_linear(p))
    other = list(lay.other)
    return psi[:, list(lay.solved)], -(psi[:, other] @ c0[other]), p


@pytest.fixture(scope="module")
def twin_sep(twin_problem: Problem) -> Separable:
    return separate(twin_problem)


@pytest.fixture(scope="module")
def wide_problem(twin_problem: Problem) -> Problem:
    """The twin with linear boxes so wide that no bound can be active (amplitudes ≥ 0 and
    the full phase circle are no constraint at all)."""
    wide = {"F0": 1e6, "Fc": 1e6, "Fs": 1e6, "Fv": 1e8}
    params = []
    for p in twin_problem.spec.params:
        if p.name in wide:
            p = dataclasses.replace(p, lower=-wide[p.name], upper=wide[p.name])
        elif p.name.startswith("Fp_"):
            p = dataclasses.replace(p, lower=0.0, upper=1e6)
        params.append(p)
    return dataclasses.replace(
        twin_problem, spec=dataclasses.replace(twin_problem.spec, params=tuple(params))
    )


# -- linear declarations of the terms ---------------------------------------------------


def _signals(n: int = 40) -> Signals:
    t = jnp.linspace(0.0, 0.3, n)
    v = 0.4 * jnp.sin(20.0 * t)  # crosses zero: both signs and sgn(0) = 0 at t = 0
    return Signals(t, 0.02 * jnp.cos(20.0 * t), v, 3.0 * jnp.cos(7.0 * t))


@pytest.mark.parametrize(
    "term",
    [HarmonicDrive(harmonics=4), StribeckFriction(), CoulombViscous(), MeasuredInput()],
    ids=lambda t: t.name,
)
def test_every_term_force_is_its_basis_times_its_coefficients(term: Term) -> None:
    rng = np.random.default_rng(3)
    spec = ParamSpec(tuple(dataclasses.replace(q, free=True) for q in term.parameters()))
    s = _signals()
    for theta in _uniform(rng, spec, 3):
        p = spec.unflatten(jnp.asarray(theta))
        basis = term.basis(p, s)
        assert basis.columns.shape == (40, len(term.linear_names))
        assert basis.names == term.linear_names
        force = np.asarray(term.force(p, s))
        np.testing.assert_allclose(
            basis.columns @ term.to_linear(p), force, rtol=0, atol=1e-12 * np.abs(force).max()
        )
        back = term.from_linear(term.to_linear(p), p)
        for name, value in back.items():
            assert math.isclose(float(value), float(p[name]), rel_tol=1e-12, abs_tol=1e-12)


def test_model_residual_is_its_basis_times_coefficients_with_mass_and_friction_signs(
    twin_problem: Problem,
) -> None:
    rng = np.random.default_rng(4)
    model, spec = twin_problem.model, twin_problem.spec
    a = jnp.asarray(twin_problem.a)
    for theta in _uniform(rng, spec, 2):
        p = spec.unflatten(jnp.asarray(theta))
        basis = model.residual_basis(p, twin_problem.signals, a)
        # column 0 is the acceleration (mass coefficient); friction enters with a + sign
        np.testing.assert_array_equal(basis.columns[:, 0], twin_problem.a)
        assert basis.groups[0] == ("mass",) and basis.groups[-1] == ("Fv",)
        np.testing.assert_allclose(basis.columns[:, -1], twin_problem.v)
        r = np.asarray(basis.columns @ model.to_linear(p))
        ref = twin_problem.residual(theta)
        np.testing.assert_allclose(r, ref, rtol=0, atol=1e-12 * np.abs(ref).max())


# -- the projected cost ----------------------------------------------------------------


def test_projected_cost_is_the_full_cost_at_full_theta_and_beats_other_linear_values(
    twin_problem: Problem, twin_sep: Separable
) -> None:
    rng = np.random.default_rng(0)
    nl = twin_sep.nonlinear_spec
    assert nl.free_names == ("omega", "vs")
    assert twin_sep.describe() == "omega, vs over 2-D; 24 linear parameters solved exactly"
    theta_nl = _uniform(rng, nl, BATCH)
    full, e_p = _project(twin_sep, theta_nl)
    spec = twin_problem.spec
    # full_theta keeps θ_nl and lies in the box
    np.testing.assert_array_equal(full[:, list(twin_sep.layout.nl_index)], theta_nl)
    assert np.all(full >= spec.lower) and np.all(full <= spec.upper)
    e_full = np.asarray(_full_cost(twin_problem.cost_fn, jnp.asarray(full)))
    np.testing.assert_allclose(e_p, e_full, rtol=1e-9)
    # any other linear values in the box (same nonlinear ones) cost more
    lin = list(twin_sep.layout.lin_index)
    others = np.repeat(full, 50, axis=0)
    others[:, lin] = _uniform(rng, spec, others.shape[0])[:, lin]
    e_other = np.asarray(_full_cost(twin_problem.cost_fn, jnp.asarray(others))).reshape(BATCH, 50)
    assert np.all(e_other >= e_p[:, None])


def test_with_no_bound_active_the_solve_is_numpy_lstsq(wide_problem: Problem) -> None:
    sep = separate(wide_problem)
    rng = np.random.default_rng(1)
    theta_nl = _uniform(rng, sep.nonlinear_spec, 3)
    full, e_p = _project(sep, theta_nl)
    for x, theta, cost in zip(theta_nl, full, e_p, strict=True):
        s_cols, y, _ = _lin_columns(wide_problem, sep, x)
        coef, *_ = np.linalg.lstsq(s_cols, y, rcond=None)
        ref = float(np.sum((s_cols @ coef - y) ** 2))
        assert math.isclose(float(cost), ref, rel_tol=1e-10)
        c = np.asarray(
            wide_problem.model.to_linear(wide_problem.spec.unflatten(jnp.asarray(theta)))
        )
        mine = c[list(sep.layout.solved)]
        # the well-determined combination Ψ_S·c agrees to ~cond²·ε; the coefficients too
        np.testing.assert_allclose(
            s_cols @ mine, s_cols @ coef, rtol=0, atol=1e-8 * np.abs(y).max()
        )
        np.testing.assert_allclose(mine, coef, rtol=1e-6, atol=1e-6 * np.abs(coef).max())


def test_active_bounds_keep_the_solution_in_the_box_and_better_than_clipping(
    twin_problem: Problem, twin_sep: Separable
) -> None:
    spec, model = twin_problem.spec, twin_problem.model
    lin = list(twin_sep.layout.lin_index)
    lower, upper = spec.lower[lin], spec.upper[lin]
    # at the twin's generating ω and vs the unconstrained fit leaves the box
    x = np.array([2 * math.pi * 5, 0.121])
    s_cols, y, p = _lin_columns(twin_problem, twin_sep, x)
    coef, *_ = np.linalg.lstsq(s_cols, y, rcond=None)
    unconstrained = np.asarray(model.linear_values(jnp.asarray(np.r_[45.0, coef]), p))[1:]
    outside = (unconstrained < lower) | (unconstrained > upper)
    assert outside.any()  # a bound is active
    full, e_p = _project(twin_sep, x[None])
    assert np.all(full[0] >= spec.lower) and np.all(full[0] <= spec.upper)
    on_bound = (full[0][lin] == lower) | (full[0][lin] == upper)
    assert on_bound.any()
    assert math.isclose(float(e_p[0]), twin_problem.cost(full[0]), rel_tol=1e-9)
    # better than the unconstrained solution merely clipped into the box
    clipped = full[0].copy()
    clipped[lin] = np.clip(unconstrained, lower, upper)
    assert e_p[0] < twin_problem.cost(clipped)


def test_a_fully_linear_model_is_one_exact_solve_with_the_mass_column() -> None:
    # EMPS-like: F = gain·u − offset, friction Fc·sgn v + Fv·v, mass free: nothing to search
    config = parse_config(
        {
            "model": {"terms": ["measured_input", "coulomb_viscous"]},
            "params": {
                "gain": {"value": 2.0},
                "offset": {"lower": -10, "upper": 10},
                "Fc": {"lower": 0, "upper": 5},
                "Fv": {"lower": 0, "upper": 50},
                "mass": {"lower": 0.5, "upper": 3.0},
            },
        },
        source="lin.toml",
    )
    t = np.linspace(0.0, 2.0, 400)
    v, a = np.sin(3 * t), 3 * np.cos(3 * t)
    truth = {"offset": 0.7, "Fc": 1.5, "Fv": 12.0, "mass": 1.2}
    force = truth["mass"] * a + truth["Fc"] * np.sign(v) + truth["Fv"] * v + truth["offset"]
    u = force / 2.0 + 0.01 * np.random.default_rng(0).normal(size=t.size)
    problem = Problem(config.model, config.spec, t, np.zeros_like(t), v, a, u)
    sep = separate(problem)
    assert sep.describe() == "no nonlinear parameter; 4 linear parameters solved exactly"
    full, cost = sep.project(np.zeros((1, 0)))
    # the exact least-squares fit: reference by numpy on the columns [a, sgn v, v, 1] of u
    cols = np.stack([a, np.sign(v), v, np.ones_like(t)], axis=1)
    coef, *_ = np.linalg.lstsq(cols, 2.0 * u, rcond=None)
    est = dict(zip(problem.spec.free_names, full[0], strict=True))
    for name, ref in zip(("mass", "Fc", "Fv", "offset"), coef, strict=True):
        assert math.isclose(est[name], ref, rel_tol=1e-9), name
        assert math.isclose(est[name], truth[name], rel_tol=0.02), name
    assert math.isclose(float(cost[0]), problem.cost(full[0]), rel_tol=1e-12)


# -- identify ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def separable_run(twin_problem: Problem, paper_config: Config):
    settings = IdentifySettings.from_tables(paper_config.tables, source=paper_config.source)
    assert settings.separable  # the shipped default
    return settings, identify(twin_problem, settings)


def test_cost_and_theta_is_the_projected_cost_and_the_full_vector(
    twin_sep: Separable,
) -> None:
    x = jnp.array([2 * math.pi * 5, 0.121])
    cost, theta = twin_sep.cost_and_theta(x)
    assert float(cost) == float(twin_sep.projected_cost(x))
    np.testing.assert_array_equal(np.asarray(theta), np.asarray(twin_sep.full_theta(x)))


def test_separable_identify_is_bit_reproducible_and_its_chains_are_full_vectors(
    twin_problem: Problem, separable_run
) -> None:
    settings, run = separable_run
    again = identify(twin_problem, settings)  # the compiled programs are reused
    np.testing.assert_array_equal(again.value, run.value)
    np.testing.assert_array_equal(again.chain_x, run.chain_x)
    np.testing.assert_array_equal(again.traces["best_cost"], run.traces["best_cost"])
    # every chain end point is the full vector of its projected optimum: E(θ) = E_P
    costs = np.asarray(_full_cost(twin_problem.cost_fn, jnp.asarray(run.chain_x)))
    np.testing.assert_allclose(costs, run.chain_cost, rtol=1e-9)
    assert run.traces["n_evals"][-1] == run.attrs["n_evals"]
    assert np.all(np.diff(run.traces["wall_time"]) > 0)


def test_separable_identify_recovers_the_full_path_optimum(
    twin_problem: Problem, paper_config: Config, separable_run
) -> None:
    settings, sep_run = separable_run
    # the 26-D search of paper.toml; one end point polished (the refiner's compilation is
    # then the separable run's, which keeps this test fast)
    full = IdentifySettings.from_tables(
        paper_config.tables,
        source=paper_config.source,
        overrides={"separable": False, "refine_top": 1},
    )
    assert not full.separable and full.chains == 32 and full.anneal.steps_per_level == 10
    full_run = identify(twin_problem, full)
    assert math.isclose(sep_run.ems, full_run.ems, rel_tol=1e-6)
    assert sep_run.attrs["separable"] and not full_run.attrs["separable"]
    assert sep_run.attrs["search_space"].startswith("separable (omega, vs over 2-D")
    assert sep_run.chain_x.shape == (settings.chains, twin_problem.spec.n_free)
    assert sep_run.value.shape == (26,) and np.isfinite(sep_run.std).all()
    # the 2-D search costs a small fraction of the 26-D one's evaluations
    assert sep_run.attrs["n_evals"] < 0.02 * full_run.attrs["n_evals"]


def test_separable_budget_is_layered_over_search_and_anneal_then_cli() -> None:
    tables = {
        "search": {
            "chains": 32,
            "separable": True,
            "separable_budget": {"chains": 8, "alpha": 0.7, "refine_top": 1},
        },
        "anneal": {"alpha": 0.95, "steps_per_level": 10},
    }
    s = IdentifySettings.from_tables(tables)
    assert (s.chains, s.refine_top, s.anneal.alpha, s.anneal.steps_per_level) == (8, 1, 0.7, 10)
    cli = IdentifySettings.from_tables(tables, overrides={"alpha": 0.9, "chains": 4})
    assert (cli.chains, cli.anneal.alpha) == (4, 0.9)
    full = IdentifySettings.from_tables(tables, overrides={"separable": False})
    assert (full.separable, full.chains, full.anneal.alpha) == (False, 32, 0.95)


@pytest.mark.parametrize(
    ("search", "needle"),
    [
        ({"separable": "yes"}, "cfg.toml: [search].separable: must be true or false, got 'yes'"),
        (
            {"separable": True, "separable_budget": {"speed": 2}},
            "cfg.toml: [search.separable_budget].speed: unknown key",
        ),
    ],
)
def test_bad_separable_settings_are_refused_in_one_line(search: dict, needle: str) -> None:
    with pytest.raises(FricjaxError) as err:
        IdentifySettings.from_tables({"search": search}, source="cfg.toml")
    assert str(err.value).startswith(needle)


# -- a model that is not separable -------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class _Drag(Term):
    """F_f = Cd·v·|v|^q: no linear declaration (a test term)."""

    name = "test_drag"
    role = "friction"

    def parameters(self) -> tuple[Param, ...]:
        return (Param("Cd", "N*s2/m2", 0.0, 10.0, 1.0), Param("q", "1", 0.5, 2.0, 1.0))

    def force(self, p, s):
        return p["Cd"] * s.v * jnp.abs(s.v) ** p["q"]


def test_a_term_without_basis_makes_separability_a_clear_error() -> None:
    model = Model((CoulombViscous(), _Drag()))
    assert not _Drag().has_basis
    t = np.linspace(0.0, 1.0, 50)
    spec = ParamSpec((*model.parameters()[:-1], MASS.fixed_at(2.0)), source="drag.toml")
    problem = Problem(model, spec, t, np.sin(t), np.cos(t), -np.sin(t), np.zeros_like(t))
    message = (
        "model: term test_drag declares no linear basis, so the model is not separable "
        "(use the full search: --no-separable or [search].separable = false)"
    )
    with pytest.raises(FricjaxError) as err:
        separate(problem)
    assert str(err.value) == message
    with pytest.raises(FricjaxError) as err:
        identify(problem, with_settings(IdentifySettings(), separable=True))
    assert str(err.value) == message
