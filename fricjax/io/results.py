"""Identification results and their HDF5 layout (one file per run or per sweep).

Layout (all datasets float64 unless noted)::

    /                     attrs: format = "fricjax-results-v1", kind ("identify"|"sweep"),
                          created (ISO time), fricjax_version, versions (JSON of package
                          versions), recording_name, recording_path, recording_sha256,
                          config (full TOML text), config_path
    /runs/<label>/        attrs: method, schedule, alpha, seed, n_chains, cost, ems,
                          cost_search, ems_search, refined (bool), wall_time [s],
                          levels, n_evals, interrupted (bool), objective, t0
        params/names      str [d]     free parameter names (search order)
        params/units      str [d]
        params/value      [d]         best (refined) values
        params/lower      [d], params/upper [d]
        params/std        [d]         Gauss–Newton standard deviation (NaN if not computed)
        params/rel_std    [d]         std / |value|
        params/flags      str [d]     identifiability warnings ("" when none)
        params/corr       [d, d]      correlation matrix
        fixed             attrs: name -> value of every fixed parameter (mass included)
        chains/x          [C, d]      final best point of each chain
        chains/cost       [C]
        traces/best_cost  [L, C]      best cost per chain per temperature level
        traces/current_cost [L, C]    current cost per chain per level
        traces/acceptance [L, C]      acceptance rate per chain per level
        traces/temperature [L]
        traces/n_evals    [L]         cumulative cost evaluations (all chains)
        traces/wall_time  [L]         seconds since the search started
        minima/x [M, d], minima/cost [M], minima/count [M]   census of distinct end points
"""

from __future__ import annotations

import datetime as _dt
import json
from dataclasses import dataclass, field
from importlib import metadata
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from fricjax.errors import FricjaxError, where
from fricjax.io.atomic import write_hdf5_atomic

FORMAT = "fricjax-results-v1"
TRACE_KEYS = ("best_cost", "current_cost", "acceptance", "temperature", "n_evals", "wall_time")


@dataclass
class RunResult:
    """One identification run (plain data; round-trips through HDF5 without loss)."""

    label: str
    method: str
    names: list[str]
    units: list[str]
    value: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    fixed: dict[str, float]
    cost: float
    ems: float
    cost_search: float
    ems_search: float
    std: np.ndarray
    rel_std: np.ndarray
    corr: np.ndarray
    flags: list[str]
    chain_x: np.ndarray
    chain_cost: np.ndarray
    traces: dict[str, np.ndarray]
    minima_x: np.ndarray
    minima_cost: np.ndarray
    minima_count: np.ndarray
    attrs: dict[str, Any] = field(default_factory=dict)

    @property
    def params(self) -> dict[str, float]:
        """Every parameter by name: free (identified) and fixed."""
        return {**self.fixed, **{n: float(v) for n, v in zip(self.names, self.value, strict=True)}}


@dataclass
class ResultsFile:
    """Everything one results file holds: provenance plus one or more runs."""

    runs: list[RunResult]
    attrs: dict[str, Any] = field(default_factory=dict)


def package_versions() -> dict[str, str]:
    out = {}
    for pkg in ("fricjax", "jax", "jaxlib", "optimistix", "equinox", "numpy", "scipy", "h5py"):
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = "unknown"
    return out


def provenance(
    *,
    kind: str,
    recording_name: str,
    recording_path: str,
    recording_sha256: str,
    config_text: str,
    config_path: str,
) -> dict[str, Any]:
    versions = package_versions()
    return {
        "format": FORMAT,
        "kind": kind,
        "created": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"),
        "fricjax_version": versions["fricjax"],
        "versions": json.dumps(versions),
        "recording_name": recording_name,
        "recording_path": recording_path,
        "recording_sha256": recording_sha256,
        "config": config_text,
        "config_path": config_path,
    }


def _str_array(items: list[str]) -> np.ndarray:
    return np.array(items, dtype=h5py.string_dtype())


def write_results(results: ResultsFile, path: str | Path) -> Path:
    """Write atomically (:mod:`fricjax.io.atomic`: built in memory, then renamed)."""

    def fill(f: h5py.File) -> None:
        for key, value in results.attrs.items():
            f.attrs[key] = value
        runs = f.create_group("runs")
        for run in results.runs:
            g = runs.create_group(run.label)
            for key, value in run.attrs.items():
                g.attrs[key] = value
            g.attrs["method"] = run.method
            for key in ("cost", "ems", "cost_search", "ems_search"):
                g.attrs[key] = float(getattr(run, key))
            p = g.create_group("params")
            p["names"] = _str_array(run.names)
            p["units"] = _str_array(run.units)
            p["flags"] = _str_array(run.flags)
            for key in ("value", "lower", "upper", "std", "rel_std", "corr"):
                p[key] = np.asarray(getattr(run, key), dtype=np.float64)
            fixed = g.create_group("fixed")
            for key, value in run.fixed.items():
                fixed.attrs[key] = float(value)
            c = g.create_group("chains")
            c["x"] = np.asarray(run.chain_x, dtype=np.float64)
            c["cost"] = np.asarray(run.chain_cost, dtype=np.float64)
            tr = g.create_group("traces")
            for key in TRACE_KEYS:
                tr[key] = np.asarray(run.traces[key], dtype=np.float64)
            m = g.create_group("minima")
            m["x"] = np.asarray(run.minima_x, dtype=np.float64)
            m["cost"] = np.asarray(run.minima_cost, dtype=np.float64)
            m["count"] = np.asarray(run.minima_count, dtype=np.int64)

    return write_hdf5_atomic(path, fill)


def _attr(value: Any) -> Any:
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, np.generic):
        return value.item()
    return value


def _strs(ds: h5py.Dataset) -> list[str]:
    return [s.decode() if isinstance(s, bytes) else str(s) for s in ds[()]]


def read_results(path: str | Path) -> ResultsFile:
    """Read a results file; a file of another kind is refused with one line."""
    path = Path(path)
    if not path.exists():
        raise FricjaxError(f"{where(path)}: results file not found")
    try:
        with h5py.File(path, "r") as f:
            if _attr(f.attrs.get("format", "")) != FORMAT:
                raise FricjaxError(
                    f"{where(path, 'attr format')}: not a fricjax results file (expected {FORMAT})"
                )
            attrs = {k: _attr(v) for k, v in f.attrs.items()}
            runs = []
            for label, g in f["runs"].items():
                p = g["params"]
                run_attrs = {k: _attr(v) for k, v in g.attrs.items()}
                runs.append(
                    RunResult(
                        label=label,
                        method=str(run_attrs.pop("method")),
                        names=_strs(p["names"]),
                        units=_strs(p["units"]),
                        value=p["value"][()],
                        lower=p["lower"][()],
                        upper=p["upper"][()],
                        fixed={k: float(v) for k, v in g["fixed"].attrs.items()},
                        cost=float(run_attrs.pop("cost")),
                        ems=float(run_attrs.pop("ems")),
                        cost_search=float(run_attrs.pop("cost_search")),
                        ems_search=float(run_attrs.pop("ems_search")),
                        std=p["std"][()],
                        rel_std=p["rel_std"][()],
                        corr=p["corr"][()],
                        flags=_strs(p["flags"]),
                        chain_x=g["chains/x"][()],
                        chain_cost=g["chains/cost"][()],
                        traces={k: g["traces"][k][()] for k in TRACE_KEYS},
                        minima_x=g["minima/x"][()],
                        minima_cost=g["minima/cost"][()],
                        minima_count=g["minima/count"][()],
                        attrs=run_attrs,
                    )
                )
    except (OSError, KeyError) as err:
        raise FricjaxError(f"{where(path)}: unreadable results file ({err})") from None
    return ResultsFile(runs=runs, attrs=attrs)
