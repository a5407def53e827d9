"""Run configuration from TOML: model terms, parameter specification, and the settings
tables of each stage (``[preprocess]``, ``[search]``, ``[anneal]``, ``[refine]``).

Layout::

    [model]
    terms = ["harmonic_drive", "stribeck_friction"]
    axis = "linear"                 # or "rotary": units rad, N·m, kg·m² (fricjax.units)
    [model.harmonic_drive]          # options of a term (optional)
    harmonics = 10
    [params]                        # one entry per parameter the terms read
    F0 = { unit = "N", lower = 216.35, upper = 649.05, init = 432.7 }
    delta = { unit = "1", value = 1.0 }          # value => fixed
    mass = { unit = "kg", lower = 50, upper = 150, init = 95 }   # optional: mass free
    [joint]                         # several recordings fitted jointly (fricjax.joint)
    per_recording = ["F0"]          # one value per recording; the rest shared

Every mistake (unknown term or parameter, missing parameter, lower > upper, fixed value
outside bounds, wrong unit, unknown table key) is refused with one line naming the file.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fricjax.errors import FricjaxError, where
from fricjax.model.registry import TERMS, make_term
from fricjax.model.system import MASS, Model
from fricjax.params import Param, ParamSpec
from fricjax.units import LINEAR, AxisUnits, axis_unit, axis_units, same_unit

SECTIONS = (
    "model",
    "params",
    "preprocess",
    "search",
    "anneal",
    "refine",
    "diagnose",
    "output_error",
    "joint",
)
PARAM_KEYS = ("unit", "lower", "upper", "init", "value", "free")


@dataclass(frozen=True)
class Config:
    """A parsed configuration. ``spec`` lacks ``mass`` when the recording must supply it."""

    model: Model
    spec: ParamSpec
    tables: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)
    source: str = ""
    text: str = ""
    axis: AxisUnits = LINEAR

    def table(self, name: str) -> Mapping[str, Any]:
        """A settings table (``preprocess``, ``search``, ...), empty if absent."""
        return self.tables.get(name, {})

    @property
    def mass_in_spec(self) -> bool:
        return "mass" in self.spec


def load_config(path: str | Path) -> Config:
    """Read and validate a TOML config file."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise FricjaxError(f"{path}: config file not found") from None
    except OSError as err:
        raise FricjaxError(f"{path}: cannot read config ({err.strerror})") from None
    except UnicodeDecodeError as err:
        raise FricjaxError(
            f"{path}: not a TOML config (not UTF-8 text: byte {err.start} is "
            f"{err.object[err.start : err.start + 1]!r})"
        ) from None
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise FricjaxError(f"{path}: invalid TOML ({err})") from None
    return parse_config(raw, source=str(path), text=text)


def parse_config(raw: Mapping[str, Any], *, source: str = "config", text: str = "") -> Config:
    """Build a :class:`Config` from an already-parsed TOML mapping."""
    for key in raw:
        if key not in SECTIONS:
            raise FricjaxError(
                f"{where(source, key)}: unknown section (known: {', '.join(SECTIONS)})"
            )
    for key, value in raw.items():
        if not isinstance(value, Mapping):
            raise FricjaxError(f"{where(source, f'[{key}]')}: must be a table, got {value!r}")
    model = _parse_model(raw.get("model"), source)
    axis = _parse_axis(raw["model"], source)
    spec = _parse_params(raw.get("params", {}), model, source, axis)
    tables = {k: dict(v) for k, v in raw.items() if k not in ("model", "params")}
    return Config(model=model, spec=spec, tables=tables, source=source, text=text, axis=axis)


def _parse_axis(table: Mapping[str, Any], source: str) -> AxisUnits:
    kind = table.get("axis", "linear")
    return axis_units(kind if isinstance(kind, str) else repr(kind), source=f"{source}: [model]")


def _parse_model(table: Any, source: str) -> Model:
    if not isinstance(table, Mapping) or "terms" not in table:
        raise FricjaxError(f"{where(source, '[model].terms')}: missing list of model terms")
    names = table["terms"]
    if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
        raise FricjaxError(f"{where(source, '[model].terms')}: must be a non-empty list of names")
    for key in table:
        if key not in ("terms", "axis") and key not in names:
            raise FricjaxError(f"{where(source, f'[model].{key}')}: not a term of this model")
    terms = []
    for name in names:
        if name not in TERMS:
            raise FricjaxError(
                f"{where(source, '[model].terms')}: unknown term {name!r} "
                f"(known: {', '.join(sorted(TERMS))})"
            )
        options = table.get(name, {})
        if not isinstance(options, Mapping):
            raise FricjaxError(
                f"{where(source, f'[model.{name}]')}: must be a table of the term's options, "
                f"got {options!r}"
            )
        try:
            terms.append(make_term(name, options))
        except TypeError as err:
            raise FricjaxError(f"{where(source, f'[model.{name}]')}: bad option ({err})") from None
        except ValueError as err:  # the term's own check names the option
            raise FricjaxError(f"{where(source, f'[model.{name}]')}.{err}") from None
    return Model(tuple(terms))


def _parse_params(
    table: Mapping[str, Any], model: Model, source: str, axis: AxisUnits = LINEAR
) -> ParamSpec:
    defaults = {q.name: q for q in model.parameters()}
    for name in table:
        if name not in defaults:
            raise FricjaxError(
                f"{where(source, f'[params].{name}')}: unknown parameter for model "
                f"{model.name} (it takes: {', '.join(defaults)})"
            )
    params = []
    for name, default in defaults.items():
        if name not in table:
            if name == MASS.name:
                continue  # taken from the recording
            raise FricjaxError(
                f"{where(source, f'[params].{name}')}: missing (model term needs it; "
                f"unit {axis_unit(default.unit, axis)})"
            )
        params.append(_parse_param(name, table[name], default, source, axis))
    return ParamSpec(tuple(params), source=source)


def _parse_param(
    name: str, entry: Any, default: Param, source: str, axis: AxisUnits = LINEAR
) -> Param:
    loc = where(source, f"[params].{name}")
    if isinstance(entry, int | float):
        entry = {"value": entry}
    if not isinstance(entry, Mapping):
        raise FricjaxError(f"{loc}: must be a number or a table {{unit, lower, upper, init}}")
    for key in entry:
        if key not in PARAM_KEYS:
            raise FricjaxError(f"{loc}: unknown key {key!r} (known: {', '.join(PARAM_KEYS)})")
    expected = axis_unit(default.unit, axis)
    unit = str(entry.get("unit", expected))
    if not same_unit(expected, unit):
        hint = "; [model].axis = 'rotary' takes rad, N·m, kg·m²" if axis.kind == "linear" else ""
        raise FricjaxError(
            f"{loc}: wrong unit {unit!r}, expected {expected!r} ({axis.kind} axis{hint})"
        )

    def num(key: str) -> float:
        try:
            value = float(entry[key])
        except (TypeError, ValueError):
            raise FricjaxError(f"{loc}: {key} must be a number, got {entry[key]!r}") from None
        if not math.isfinite(value):
            raise FricjaxError(f"{loc}: {key} is not finite ({value})")
        return value

    free = entry.get("free", "value" not in entry)
    if not isinstance(free, bool):
        raise FricjaxError(f"{loc}: free must be true or false, got {free!r}")
    if not free:
        if "value" not in entry and "init" not in entry:
            raise FricjaxError(f"{loc}: fixed parameter needs a value")
        value = num("value") if "value" in entry else num("init")
        lower = num("lower") if "lower" in entry else value
        upper = num("upper") if "upper" in entry else value
        if lower > upper:
            raise FricjaxError(f"{loc}: lower bound {lower:g} > upper bound {upper:g}")
        if not lower <= value <= upper:
            raise FricjaxError(
                f"{loc}: fixed value {value:g} outside its bounds [{lower:g}, {upper:g}]"
            )
        return Param(
            name, unit, lower, upper, value, free=False, null=default.null, domain=default.domain
        )
    for key in ("lower", "upper"):
        if key not in entry:
            raise FricjaxError(f"{loc}: free parameter needs {key}")
    lower, upper = num("lower"), num("upper")
    if lower > upper:
        raise FricjaxError(f"{loc}: lower bound {lower:g} > upper bound {upper:g}")
    init = num("init") if "init" in entry else 0.5 * (lower + upper)
    if not lower <= init <= upper:
        raise FricjaxError(
            f"{loc}: initial value {init:g} outside its bounds [{lower:g}, {upper:g}]"
        )
    return Param(
        name, unit, lower, upper, init, free=True, null=default.null, domain=default.domain
    )
