"""The fleet results file: every recording's fit, σ and status in one HDF5 file.

Layout (N recordings in the order given, d free parameters, f fixed ones; float64 unless
noted; a failed recording has NaN values)::

    /                      attrs: format = "fricjax-fleet-v1", kind = "fleet", created,
                           fricjax_version, versions (JSON), config (TOML text),
                           config_path, seed, method, separable, shard_size, order_by
                           ("" = file name), n_recordings, n_ok, n_failed
    /recordings/name       str [N]
    /recordings/path       str [N]
    /recordings/sha256     str [N]
    /recordings/order      str [N]   value the report orders by (attribute or file name)
    /recordings/status     str [N]   "ok" | "failed"
    /recordings/reason     str [N]   one line, "" when ok
    /recordings/shard      int64 [N] shard that fitted it (-1: never fitted)
    /params/names          str [d]   free parameters, search order
    /params/units          str [d]
    /params/lower, upper   [d]       the config's box
    /params/value          [N, d]    identified values
    /params/std            [N, d]    Gauss–Newton σ
    /params/rel_std        [N, d]
    /params/flags          str [N, d] identifiability warnings ("" when none)
    /fixed/names           str [f]
    /fixed/value           [N, f]    fixed parameters (e.g. each recording's mass)
    /fit/cost, ems, cost_search, cond   [N]   seed eq. 11 [N²], cost/n, search's best, cond(JᵀJ)
    /fit/levels, n_evals, n_minima, n   int64 [N]
    /fit/refined           bool [N]

Written atomically (:mod:`fricjax.io.atomic`): a reader sees the previous file or the
complete new one, never a partial fleet.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from fricjax.errors import FricjaxError, where
from fricjax.fleet import OK, FleetFit
from fricjax.io.atomic import write_hdf5_atomic
from fricjax.io.results import attr_value, package_versions, read_strs, str_array

FORMAT = "fricjax-fleet-v1"
_FIT_FLOATS = ("cost", "ems", "cost_search", "cond")
_FIT_INTS = ("levels", "n_evals", "n_minima", "n")


@dataclass
class FleetFile:
    """What a fleet file holds: parameter names/units/box, one fit per recording, attrs."""

    names: list[str]
    units: list[str]
    lower: np.ndarray
    upper: np.ndarray
    fits: list[FleetFit]
    attrs: dict[str, Any] = field(default_factory=dict)

    @property
    def values(self) -> np.ndarray:
        """[N, d] identified values (NaN rows for failed recordings)."""
        return _matrix(self.fits, "value", len(self.names))

    @property
    def stds(self) -> np.ndarray:
        """[N, d] σ (NaN rows for failed recordings)."""
        return _matrix(self.fits, "std", len(self.names))


def _matrix(fits: list[FleetFit], key: str, d: int) -> np.ndarray:
    out = np.full((len(fits), d), np.nan)
    for i, fit in enumerate(fits):
        value = getattr(fit, key)
        if fit.ok and value is not None:
            out[i] = value
    return out


def fleet_attrs(*, config_text: str, config_path: str, **extra: Any) -> dict[str, Any]:
    """Root attributes: provenance plus the run's settings (``extra``)."""
    import datetime as dt

    versions = package_versions()
    return {
        "format": FORMAT,
        "kind": "fleet",
        "created": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "fricjax_version": versions["fricjax"],
        "versions": json.dumps(versions),
        "config": config_text,
        "config_path": config_path,
        **extra,
    }


def write_fleet(fleet: FleetFile, path: str | Path) -> Path:
    """Write ``fleet`` to ``path`` atomically (layout in the module docstring)."""
    path = Path(path)
    fits = fleet.fits
    fixed_names = sorted({k for f in fits for k in f.fixed})

    def fill(f: h5py.File) -> None:
        for key, value in fleet.attrs.items():
            f.attrs[key] = value
        f.attrs["n_recordings"] = len(fits)
        f.attrs["n_ok"] = sum(fit.ok for fit in fits)
        f.attrs["n_failed"] = sum(not fit.ok for fit in fits)
        rec = f.create_group("recordings")
        for key in ("name", "path", "sha256", "order", "status", "reason"):
            rec[key] = str_array([str(getattr(fit, key)) for fit in fits])
        rec["shard"] = np.array([fit.shard for fit in fits], dtype=np.int64)
        p = f.create_group("params")
        p["names"] = str_array(fleet.names)
        p["units"] = str_array(fleet.units)
        p["lower"] = np.asarray(fleet.lower, np.float64)
        p["upper"] = np.asarray(fleet.upper, np.float64)
        d = len(fleet.names)
        p["value"] = fleet.values
        p["std"] = fleet.stds
        p["rel_std"] = _matrix(fits, "rel_std", d)
        flags = [fit.flags if fit.ok and fit.flags else [""] * d for fit in fits]
        p["flags"] = np.array(flags, dtype=h5py.string_dtype()).reshape(len(fits), d)
        fx = f.create_group("fixed")
        fx["names"] = str_array(fixed_names)
        fx["value"] = np.array(
            [[fit.fixed.get(k, np.nan) for k in fixed_names] for fit in fits], dtype=np.float64
        ).reshape(len(fits), len(fixed_names))
        g = f.create_group("fit")
        for key in _FIT_FLOATS:
            g[key] = np.array([getattr(fit, key) for fit in fits], dtype=np.float64)
        for key in _FIT_INTS:
            g[key] = np.array([getattr(fit, key) for fit in fits], dtype=np.int64)
        g["refined"] = np.array([fit.refined for fit in fits], dtype=bool)

    return write_hdf5_atomic(path, fill)


def read_fleet(path: str | Path) -> FleetFile:
    """Read a fleet file; anything else is refused with one line."""
    path = Path(path)
    if not path.exists():
        raise FricjaxError(f"{where(path)}: fleet file not found")
    try:
        with h5py.File(path, "r") as f:
            if attr_value(f.attrs.get("format", "")) != FORMAT:
                raise FricjaxError(
                    f"{where(path, 'attr format')}: not a fricjax fleet file (expected {FORMAT})"
                )
            attrs = {k: attr_value(v) for k, v in f.attrs.items()}
            rec = {k: read_strs(f["recordings"][k]) for k in ("name", "path", "sha256", "order")}
            status = read_strs(f["recordings/status"])
            reason = read_strs(f["recordings/reason"])
            shard = f["recordings/shard"][()]
            p = f["params"]
            value, std, rel = p["value"][()], p["std"][()], p["rel_std"][()]
            flags = [
                [s.decode() if isinstance(s, bytes) else str(s) for s in row]
                for row in p["flags"][()]
            ]
            fixed_names = read_strs(f["fixed/names"])
            fixed = f["fixed/value"][()]
            g = f["fit"]
            floats = {k: g[k][()] for k in _FIT_FLOATS}
            ints = {k: g[k][()] for k in _FIT_INTS}
            refined = g["refined"][()]
            fits = []
            for i in range(len(status)):
                ok = status[i] == OK
                fits.append(
                    FleetFit(
                        **{k: rec[k][i] for k in rec},
                        status=status[i],
                        reason=reason[i],
                        value=value[i] if ok else None,
                        std=std[i] if ok else None,
                        rel_std=rel[i] if ok else None,
                        flags=flags[i] if ok else [],
                        fixed={
                            k: float(fixed[i, j])
                            for j, k in enumerate(fixed_names)
                            if np.isfinite(fixed[i, j])
                        },
                        **{k: float(floats[k][i]) for k in _FIT_FLOATS},
                        **{k: int(ints[k][i]) for k in _FIT_INTS},
                        refined=bool(refined[i]),
                        shard=int(shard[i]),
                    )
                )
            return FleetFile(
                names=read_strs(p["names"]),
                units=read_strs(p["units"]),
                lower=p["lower"][()],
                upper=p["upper"][()],
                fits=fits,
                attrs=attrs,
            )
    except (OSError, KeyError) as err:
        raise FricjaxError(f"{where(path)}: unreadable fleet file ({err})") from None
