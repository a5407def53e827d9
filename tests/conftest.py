"""Shared fixtures: one parsed paper config and the seed's CSAA truth, for every test."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

import fricjax  # noqa: F401  (float64 on)
from fricjax.config import Config, load_config

ROOT = Path(__file__).resolve().parents[1]
#: Where the EMPS benchmark's MAT files are looked for: $FRICJAX_EMPS_DIR, else
#: ../shared/data/real/emps/ beside the repository (never an absolute path).
EMPS_ENV = "FRICJAX_EMPS_DIR"
EMPS_FILES = ("DATA_EMPS.mat", "DATA_EMPS_PULSES.mat")


@pytest.fixture(scope="session")
def paper_config() -> Config:
    return load_config(ROOT / "configs" / "paper.toml")


@pytest.fixture(scope="session")
def emps_dir() -> Path:
    """The folder holding the EMPS benchmark's DATA_EMPS.mat and DATA_EMPS_PULSES.mat; the
    test is skipped, saying where the data comes from, when they are not there."""
    folder = Path(os.environ.get(EMPS_ENV) or ROOT.parent / "shared" / "data" / "real" / "emps")
    missing = [name for name in EMPS_FILES if not (folder / name).is_file()]
    if missing:
        pytest.skip(
            f"EMPS data not found ({', '.join(missing)} in {folder}): the EMPS benchmark "
            "(Janot, Gautier & Brunot 2019, nonlinearbenchmark.org); put its MAT files in "
            f"../shared/data/real/emps/ beside the repository or set {EMPS_ENV}"
        )
    return folder


@pytest.fixture(scope="session")
def twin_path() -> Path:
    return ROOT / "data" / "paper_twin.h5"


@pytest.fixture(scope="session")
def twin_problem(paper_config: Config, twin_path: Path):
    """The bundled paper twin bound to configs/paper.toml (compiled once per session)."""
    from fricjax.data.recording import read_recording
    from fricjax.problem import build_problem

    return build_problem(read_recording(twin_path), paper_config)


@pytest.fixture(autouse=True, scope="session")
def _no_disk_caches():
    """The CLI's commands turn on the on-disk compilation cache and program store
    (:func:`fricjax.api.enable_compilation_cache`) for the rest of their process: in the
    test process, that would write to the user's cache folder and make later tests depend
    on what an earlier run left there. Tests of the caches set their own folder."""
    before = os.environ.get("FRICJAX_COMPILATION_CACHE")
    os.environ["FRICJAX_COMPILATION_CACHE"] = "0"
    yield
    if before is None:
        os.environ.pop("FRICJAX_COMPILATION_CACHE", None)
    else:
        os.environ["FRICJAX_COMPILATION_CACHE"] = before


@pytest.fixture(autouse=True, scope="module")
def _compilations_freed_after_slow_modules(request: pytest.FixtureRequest):
    """After a module whose slow tests ran, drop jax's compiled programs.

    Each slow check compiles dozens of whole-record programs (a diagnosis fits, scores and
    refits a dozen models); ``pytest -m slow`` in one process ran out of XLA's code memory
    in its fifth module (errors, then a segmentation fault while tracing), though every
    module passes on its own. The fast suite selects no slow test, so it keeps sharing its
    compilations across modules."""
    yield
    if any(
        item.module is request.module and item.get_closest_marker("slow")
        for item in request.session.items
    ):
        import jax

        jax.clear_caches()
