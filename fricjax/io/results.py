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
import math
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


def str_array(items: list[str]) -> np.ndarray:
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
            p["names"] = str_array(run.names)
            p["units"] = str_array(run.units)
            p["flags"] = str_array(run.flags)
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


def attr_value(value: Any) -> Any:
    if isinstance(value, bytes):
        return value.decode("utf-8", errors="replace")
    if isinstance(value, np.generic):
        return value.item()
    return value


#: Run attributes that must be numbers when present (``show`` formats them as such).
_NUMBER_ATTRS = ("alpha", "seed", "n_chains", "wall_time", "levels", "n_evals", "t0")
#: Parameter datasets that must be finite (the values and their box) and those that hold
#: NaN where the uncertainty was not computed.
_BOX = ("value", "lower", "upper")
_SIGMA = ("std", "rel_std")
#: Run attributes the best-run choice and the fit figures read: finite numbers, required.
_COST_ATTRS = ("cost", "ems", "cost_search", "ems_search")


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(
        value, bool | np.bool_
    )


class _RunReader:
    """Reads one ``/runs/<label>`` group, refusing (one line naming file and dataset) any
    entry of the wrong kind, dtype, shape or value: a results file is user input too."""

    def __init__(self, path: Path, group: h5py.Group, at: str) -> None:
        self.path, self.group, self.at = path, group, at
        self.d = 0

    def fail(self, key: str, what: str) -> FricjaxError:
        return FricjaxError(f"{where(self.path, f'{self.at}/{key}' if key else self.at)}: {what}")

    def dataset(self, key: str) -> h5py.Dataset:
        try:
            obj = self.group.get(key)
        except (KeyError, OSError):
            raise self.fail(key, "cannot be opened (a link that does not resolve)") from None
        if obj is None:
            raise self.fail(key, "missing")
        if not isinstance(obj, h5py.Dataset):
            raise self.fail(key, "is a group, expected a dataset")
        return obj

    def strings(self, key: str, length: int | None = None) -> list[str]:
        ds = self.dataset(key)
        if ds.dtype.kind not in "OSU" or ds.ndim != 1:
            raise self.fail(key, f"expected a 1-D array of strings, got {ds.dtype} {ds.shape}")
        out = read_strs(ds)
        if length is not None and len(out) != length:
            raise self.fail(key, f"has {len(out)} entries, params/names has {length}")
        return out

    def floats(
        self, key: str, shape: tuple[int | None, ...], *, finite: bool, kinds: str = "fiu"
    ) -> np.ndarray:
        ds = self.dataset(key)
        if ds.dtype.kind not in kinds:
            raise self.fail(key, f"wrong dtype {ds.dtype} (expected numbers)")
        got = ds.shape
        if len(got) != len(shape) or any(
            w is not None and g != w for g, w in zip(got, shape, strict=True)
        ):
            want = ", ".join("any" if w is None else str(w) for w in shape)
            why = f" for the {self.d} names in params/names" if self.d in shape else ""
            raise self.fail(key, f"has shape {got}, expected ({want}){why}")
        arr = np.asarray(ds[()], dtype=np.float64 if kinds != "iu" else np.int64)
        if finite and not np.isfinite(arr).all():
            i = int(np.argmax(~np.isfinite(arr.reshape(-1))))
            raise self.fail(key, f"holds {arr.reshape(-1)[i]} at index {i}, expected finite")
        return arr

    def number_attr(self, key: str, *, required: bool) -> float | None:
        if key not in self.group.attrs:
            if required:
                raise self.fail("", f"attr {key!r} missing")
            return None
        value = attr_value(self.group.attrs[key])
        if not _is_number(value) or (required and not math.isfinite(value)):
            kind = "a finite number" if required else "a number"
            raise self.fail("", f"attr {key!r} must be {kind}, got {value!r}")
        return float(value)


def _read_run(path: Path, label: str, g: Any) -> RunResult:
    at = f"/runs/{label}"
    if not isinstance(g, h5py.Group):
        raise FricjaxError(f"{where(path, at)}: is a dataset, expected a group (one per run)")
    r = _RunReader(path, g, at)
    names = r.strings("params/names")
    d = r.d = len(names)
    if len(set(names)) != d:
        dup = next(n for n in names if names.count(n) > 1)
        raise r.fail("params/names", f"{dup!r} appears more than once")
    # the parameter table first: a wrong d shows up as the table's fault, not a trace's
    units, flags = r.strings("params/units", d), r.strings("params/flags", d)
    table = {key: r.floats(f"params/{key}", (d,), finite=True) for key in _BOX}
    table.update({key: r.floats(f"params/{key}", (d,), finite=False) for key in _SIGMA})
    corr = r.floats("params/corr", (d, d), finite=False)
    fixed_group = g.get("fixed")
    if not isinstance(fixed_group, h5py.Group):
        raise r.fail("fixed", "missing group of fixed parameters (attrs name -> value)")
    fixed = {}
    for key, raw in fixed_group.attrs.items():
        value = attr_value(raw)
        if not _is_number(value) or not math.isfinite(value):
            raise r.fail(f"fixed attr {key!r}", f"must be a finite number, got {value!r}")
        if key in names:
            raise r.fail(f"fixed attr {key!r}", "is also a free parameter in params/names")
        fixed[key] = float(value)
    method = attr_value(g.attrs.get("method"))
    if not isinstance(method, str):
        raise r.fail("", f"attr 'method' must be a string, got {method!r}")
    costs = {key: r.number_attr(key, required=True) for key in _COST_ATTRS}
    for key in _NUMBER_ATTRS:
        r.number_attr(key, required=False)
    run_attrs = {k: attr_value(v) for k, v in g.attrs.items() if k not in ("method", *_COST_ATTRS)}
    chain_x = r.floats("chains/x", (None, d), finite=False)
    n_levels = None
    traces = {}
    for key in TRACE_KEYS:
        per_chain = key in ("best_cost", "current_cost", "acceptance")
        shape = (n_levels, chain_x.shape[0]) if per_chain else (n_levels,)
        traces[key] = r.floats(f"traces/{key}", shape, finite=False)
        n_levels = traces[key].shape[0]
    minima_x = r.floats("minima/x", (None, d), finite=False)
    m = minima_x.shape[0]
    return RunResult(
        label=label,
        method=method,
        names=names,
        units=units,
        value=table["value"],
        lower=table["lower"],
        upper=table["upper"],
        fixed=fixed,
        cost=costs["cost"],
        ems=costs["ems"],
        cost_search=costs["cost_search"],
        ems_search=costs["ems_search"],
        std=table["std"],
        rel_std=table["rel_std"],
        corr=corr,
        flags=flags,
        chain_x=chain_x,
        chain_cost=r.floats("chains/cost", (chain_x.shape[0],), finite=False),
        traces=traces,
        minima_x=minima_x,
        minima_cost=r.floats("minima/cost", (m,), finite=False),
        minima_count=r.floats("minima/count", (m,), finite=False, kinds="iu"),
        attrs=run_attrs,
    )


def read_strs(ds: h5py.Dataset) -> list[str]:
    return [s.decode("utf-8", errors="replace") if isinstance(s, bytes) else str(s) for s in ds[()]]


def read_results(path: str | Path) -> ResultsFile:
    """Read a results file, checking it against the layout of the module docstring.

    A file of another kind, a missing, mistyped or misshapen entry (``params/value``
    shorter than ``params/names``, strings where numbers belong, ``/runs`` empty or a
    dataset), or a NaN/inf where a value is needed (parameter values and bounds, fixed
    parameters, costs) is refused with one line naming the file and the entry.
    """
    path = Path(path)
    if not path.exists():
        raise FricjaxError(f"{where(path)}: results file not found")
    try:
        f = h5py.File(path, "r")
    except OSError as err:
        raise FricjaxError(f"{where(path)}: not a readable HDF5 results file ({err})") from None
    try:
        with f:
            if attr_value(f.attrs.get("format", "")) != FORMAT:
                raise FricjaxError(
                    f"{where(path, 'attr format')}: not a fricjax results file (expected {FORMAT})"
                )
            attrs = {k: attr_value(v) for k, v in f.attrs.items()}
            group = f.get("runs")
            if group is None:
                raise FricjaxError(f"{where(path, '/runs')}: missing group of runs")
            if not isinstance(group, h5py.Group):
                raise FricjaxError(
                    f"{where(path, '/runs')}: is a dataset, expected a group (one per run)"
                )
            if len(group) == 0:
                raise FricjaxError(f"{where(path, '/runs')}: holds no run")
            runs = [_read_run(path, label, group[label]) for label in group]
    except (OSError, KeyError) as err:
        raise FricjaxError(f"{where(path)}: unreadable results file ({err})") from None
    return ResultsFile(runs=runs, attrs=attrs)
