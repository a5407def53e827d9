"""The fleet on Dask distributed (a local cluster of 2 worker processes): the same numbers
as the in-process run (to rounding), and a worker killed mid-shard loses nothing."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip(
    "distributed", reason="dask.distributed not installed (pip install 'fricjax[fleet]')"
)

from distributed import Client, LocalCluster

from fricjax.config import load_config
from fricjax.data.recording import write_recording
from fricjax.data.twin import axis_twin
from fricjax.fleet import FleetFit, load_members, run_fleet
from fricjax.identify import IdentifySettings

ROOT = Path(__file__).resolve().parents[1]
AXIS = ROOT / "configs" / "axis.toml"
SHARD = 2


@pytest.fixture(scope="module")
def setup(tmp_path_factory: pytest.TempPathFactory):
    folder = tmp_path_factory.mktemp("dask_fleet")
    for s in range(6):
        write_recording(axis_twin(seed=s, name=f"run{s}")[0], folder / f"run{s}.h5")
    cfg = load_config(AXIS)
    settings = IdentifySettings.from_tables(cfg.tables, source=cfg.source)
    members = load_members([folder], cfg)
    local = run_fleet(members, settings, shard_size=SHARD)
    return members, settings, local


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory):
    # the workers share one compilation cache: the second to need a program loads it
    # (and the program store: the comparison below covers stored programs)
    cache = tmp_path_factory.mktemp("jax_cache")
    before = os.environ.get("FRICJAX_CACHE_DIR")
    os.environ["FRICJAX_CACHE_DIR"] = str(cache)
    os.environ["FRICJAX_COMPILATION_CACHE"] = "1"
    cluster = LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    )
    c = Client(cluster)
    yield c
    c.close()
    cluster.close()
    os.environ["FRICJAX_COMPILATION_CACHE"] = "0"  # the suite's setting (conftest)
    if before is None:
        os.environ.pop("FRICJAX_CACHE_DIR", None)
    else:
        os.environ["FRICJAX_CACHE_DIR"] = before


def assert_same(a: list[FleetFit], b: list[FleetFit]) -> None:
    assert [f.name for f in a] == [f.name for f in b]
    for x, y in zip(a, b, strict=True):
        assert x.status == y.status == "ok", (x.reason, y.reason)
        # other processes: equal to rounding (the same programs, another process' floats)
        np.testing.assert_allclose(x.value, y.value, rtol=1e-10, atol=0)
        np.testing.assert_allclose(x.std, y.std, rtol=1e-8, atol=0)
        assert x.cost == pytest.approx(y.cost, rel=1e-10) and x.shard == y.shard


def test_dask_run_equals_the_in_process_run(setup, client: Client) -> None:
    members, settings, local = setup
    on_dask = run_fleet(members, settings, shard_size=SHARD, client=client)
    assert_same(on_dask, local)
    # the workers ran (and stored) the programs of the store, not jit's
    assert any((Path(os.environ["FRICJAX_CACHE_DIR"]) / "programs").glob("*.jaxexport"))


def test_a_worker_killed_mid_shard_loses_no_result(setup, client: Client) -> None:
    members, settings, local = setup
    killed: list[tuple[str, int, list]] = []

    def kill_a_busy_worker(done: int, total: int, fits: list[FleetFit]) -> None:
        # after the first shard is in, SIGKILL a worker that holds an unfinished shard
        if killed or done == total:
            return
        busy = {w: keys for w, keys in client.processing().items() if keys}
        if not busy:
            return
        worker, keys = next(iter(busy.items()))
        pid = client.run(os.getpid, workers=[worker])[worker]
        os.kill(pid, signal.SIGKILL)
        killed.append((worker, pid, list(keys)))

    on_dask = run_fleet(
        members, settings, shard_size=SHARD, client=client, on_shard=kill_a_busy_worker
    )
    assert killed, "no shard was running when the first one finished"
    assert_same(on_dask, local)
    # the killed process is gone (its nanny started a new one)
    pids = set(client.run(os.getpid).values())
    assert killed[0][1] not in pids
