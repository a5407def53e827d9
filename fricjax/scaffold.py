"""A commented starting config for a recording (``fricjax init-config``).

The user picks the base model (drive kind, friction terms); the bounds come from the
recording's own scale, after the same preprocessing identification will use:

* ``v_max = max|v|`` [m/s] and the largest inertial force ``m·max|a|`` [N];
* a force scale ``F_s`` [N]: the largest of ``m·max|a|``, the measured force ``max|F|``, and
  (drive input in another unit) ``max|ĝ·u|`` with ``ĝ`` the least-squares gain of
  ``m·a = g·u − offset − Fc·sgn(v) − Fv·v``. With a harmonic drive nothing measures the
  drive force, so ``F_s = 3·m·max|a|`` (a drive that also overcomes friction of up to twice
  the inertial force; widen the bounds if friction dominates);
* Coulomb and static levels in ``[0, F_s]``; viscous coefficient in ``[0, F_s/v_max]`` (its
  force at top speed at most ``F_s``); Stribeck velocity in ``[v_max/1000, v_max]``;
  offsets in ``[−F_s, F_s]``; drive fundamental ``ω`` in ``[ω_d/2, 2·ω_d]`` around the
  strongest line ``ω_d`` of the spectrum of ``x`` (detrended), harmonic amplitudes in
  ``[0, F_s]``.

Every bound is written with the figure it came from, so the user can see and widen it.
Units follow the axis (:mod:`fricjax.units`). The text is parsed back with
:func:`fricjax.config.parse_config` before it is returned: what is written is accepted.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fricjax.config import parse_config
from fricjax.data.preprocess import PreprocessSettings, derivatives
from fricjax.data.recording import Recording, read_recording, require_mass
from fricjax.errors import FricjaxError, where
from fricjax.io.atomic import write_text_atomic
from fricjax.units import AxisUnits, axis_unit, axis_units

DRIVES = ("measured", "harmonic")
FRICTION = ("coulomb", "viscous", "stribeck")
#: Default cutoff of the derivative filter [Hz], lowered to a fifth of the sampling rate
#: on slow recordings (it must stay below Nyquist with room for the roll-off).
CUTOFF_HZ = 100.0


@dataclass(frozen=True)
class Scale:
    """What the recording says about its own scale (preprocessed as the config will)."""

    v_max: float  # [m/s]
    inertial: float  # m·max|a| [N]
    force: float  # F_s [N]
    force_from: str  # where F_s came from, in words
    omega: float  # strongest line of x [rad/s]
    duration: float  # [s]
    signal: str | None  # "u", "F" or None
    gain: float | None  # least-squares gain [N per unit of u], u only


def _preprocess(rec: Recording) -> PreprocessSettings:
    fs = 1.0 / rec.dt
    cutoff = min(CUTOFF_HZ, 0.2 * fs)
    # trim the filter's end transients: three cutoff periods, at most 5 % of the record
    trim = min(math.ceil(3.0 * fs / cutoff), rec.n // 20)
    return PreprocessSettings(cutoff_hz=cutoff, stencil=4, trim=trim)


def recording_scale(rec: Recording, drive: str, settings: PreprocessSettings) -> Scale:
    """The :class:`Scale` of ``rec`` for a ``drive`` of kind ``"measured"``/``"harmonic"``."""
    m = require_mass(rec)
    src = rec.path or rec.name
    signal = None
    if drive == "measured":
        signal = "F" if rec.F is not None else "u" if rec.u is not None else None
        if signal is None:
            raise FricjaxError(
                f"{where(src, '/u or /F')}: --drive measured needs a recorded input or force; "
                "use --drive harmonic for a periodic drive that is not recorded"
            )
    d = derivatives(rec.t, rec.x, settings, u=rec.u, F=rec.F, source=src)
    v_max = float(np.max(np.abs(d.v)))
    if not v_max > 0:
        raise FricjaxError(f"{where(src, '/x')}: the body never moves (max |v| = 0)")
    inertial = m * float(np.max(np.abs(d.a)))
    gain = None
    if signal == "F":
        force, force_from = max(inertial, float(np.max(np.abs(d.F)))), "max |F|, m·max|a|"
    elif signal == "u" and d.u is not None:
        cols = np.stack([d.u, -np.ones_like(d.v), -np.sign(d.v), -d.v], axis=1)
        gain = float(np.linalg.lstsq(cols, m * d.a, rcond=None)[0][0])
        force = max(inertial, abs(gain) * float(np.max(np.abs(d.u))))
        force_from = f"max |ĝ·u| with least-squares ĝ = {gain:.4g}, m·max|a|"
    else:
        force, force_from = 3.0 * inertial, "3·m·max|a| (drive force not recorded)"
    xd = d.x - np.polyval(np.polyfit(d.t, d.x, 1), d.t)
    spectrum = np.abs(np.fft.rfft(xd * np.hanning(xd.shape[0])))
    freqs = np.fft.rfftfreq(xd.shape[0], rec.dt)
    k = 1 + int(np.argmax(spectrum[1:])) if spectrum.shape[0] > 1 else 0
    omega = 2.0 * math.pi * float(freqs[k]) if k else 2.0 * math.pi / rec.duration
    return Scale(v_max, inertial, force, force_from, omega, rec.duration, signal, gain)


def scaffold_config(
    recording: str | Path | Recording,
    *,
    drive: str = "measured",
    friction: Sequence[str] = ("coulomb", "viscous"),
    harmonics: int = 3,
    mass: float | None = None,
    axis: str | None = None,
    u_unit: str | None = None,
) -> str:
    """TOML text of a commented starting config for ``recording`` (module docstring).

    Args:
        recording: path or :class:`Recording`; needs a mass (attr, or ``mass``).
        drive: ``"measured"`` (``measured_input`` on ``/F`` if recorded, else ``/u``) or
            ``"harmonic"`` (``harmonic_drive`` with ``harmonics`` lines).
        friction: subset of ``coulomb``, ``viscous``, ``stribeck``; Coulomb is required
            (``coulomb_viscous``, or ``stribeck_friction`` with ``stribeck``); without
            ``viscous`` the viscous coefficient is fixed at 0.
        harmonics: number of harmonics of a harmonic drive (≥ 1).
        mass: moving mass [kg] (or moment of inertia [kg·m²]); overrides the recording's.
        axis: ``"linear"`` or ``"rotary"``; default: the recording's attr, else linear.
        u_unit: unit of ``/u`` (default: the recording's ``u_unit``; a CSV has none). A
            force unit of the axis (N, or N·m on a rotary axis) says ``u`` is a measured
            force (a load cell): its gain is then fixed at 1 instead of searched.

    Raises:
        FricjaxError: unknown drive or friction term, no Coulomb term, no mass, a
            measured drive without ``/u`` or ``/F``.
    """
    rec = recording if isinstance(recording, Recording) else read_recording(recording, mass=mass)
    if mass is not None and isinstance(recording, Recording):
        rec = dataclasses.replace(rec, mass=mass)
    if u_unit is not None:
        rec = dataclasses.replace(rec, u_unit=u_unit.strip())
    if drive not in DRIVES:
        raise FricjaxError(f"--drive: must be one of {', '.join(DRIVES)}, got {drive!r}")
    terms = [f.strip() for f in friction if f.strip()]
    for f in terms:
        if f not in FRICTION:
            raise FricjaxError(
                f"--friction: unknown term {f!r} (known: {', '.join(FRICTION)}; e.g. "
                "coulomb,viscous)"
            )
    if "coulomb" not in terms:
        raise FricjaxError("--friction: must include coulomb (e.g. coulomb,viscous)")
    if not isinstance(harmonics, int) or harmonics < 1:
        raise FricjaxError(f"--harmonics: must be an integer >= 1, got {harmonics!r}")
    units = axis_units(axis or rec.axis or "linear", source="--axis")
    if rec.axis and rec.axis != units.kind:
        raise FricjaxError(
            f"{where(rec.path, 'attr axis')}: recording is {rec.axis!r}, --axis {units.kind!r}"
        )
    settings = _preprocess(rec)
    scale = recording_scale(rec, drive, settings)
    mass_from = "from --mass" if mass is not None else "from the recording"
    text = _render(rec, units, settings, scale, drive, terms, harmonics, mass_from)
    parse_config(tomllib.loads(text), source="init-config")  # what is written is accepted
    return text


def write_scaffold(out: str | Path, text: str, *, force: bool = False) -> Path:
    """Write ``text`` to ``out`` atomically; an existing file is kept unless ``force``."""
    out = Path(out)
    if out.exists() and not force:
        raise FricjaxError(f"{where(out)}: exists; choose another --out or pass --force")
    return write_text_atomic(out, text)


def _g(value: float) -> str:
    return f"{value:.6g}"


def _render(
    rec: Recording,
    u: AxisUnits,
    pre: PreprocessSettings,
    s: Scale,
    drive: str,
    friction: list[str],
    harmonics: int,
    mass_from: str,
) -> str:
    def unit(linear: str) -> str:
        return axis_unit(linear, u)

    F, V, C = u.force, u.velocity, u.viscous
    name = rec.path or rec.name
    terms = []
    params: list[str] = []

    def param(key: str, un: str, lo: float, hi: float, init: float, why: str) -> None:
        params.append(
            f'{key} = {{ unit = "{un}", lower = {_g(lo)}, upper = {_g(hi)}, init = {_g(init)} }}'
            f"  # {why}"
        )

    if drive == "measured":
        terms.append("measured_input")
        if s.signal == "F":
            params.append(
                f'gain = {{ unit = "{F}/{F}", value = 1.0 }}  # /F is the force on the body; '
                "free it (e.g. 0.5..2) if the sensor's calibration is in doubt"
            )
        elif is_force_unit(rec.u_unit, u):
            params.append(
                f'gain = {{ unit = "{F}/{F}", value = 1.0 }}  # /u is a force in {rec.u_unit} '
                f"(a load cell); free it (e.g. 0.5..2) if its calibration is in doubt "
                f"(least squares on the record: {_g(s.gain or 0.0)})"
            )
        else:
            g = abs(s.gain or 0.0)
            hi = 10.0 * g if g > 0 else 1.0
            uu = rec.u_unit or "u"
            param(
                "gain",
                f"{F}/{uu}",
                0.0,
                hi,
                g if g > 0 else 0.5 * hi,
                f"[0, 10·ĝ], ĝ = {_g(g)} {F}/{uu} by least squares on the record",
            )
        param(
            "offset", F, -s.force, s.force, 0.0, f"±F_s, F_s = {_g(s.force)} {F} ({s.force_from})"
        )
    else:
        terms.append("harmonic_drive")
        param("F0", F, -s.force, s.force, 0.0, f"±F_s, F_s = {_g(s.force)} {F} ({s.force_from})")
        lo_w = max(0.5 * s.omega, math.pi / s.duration)
        param(
            "omega",
            "rad/s",
            lo_w,
            2.0 * s.omega,
            s.omega,
            f"[ω_d/2, 2·ω_d], ω_d = {_g(s.omega)} rad/s ({_g(s.omega / (2 * math.pi))} Hz), "
            "strongest line of x",
        )
        for i in range(1, harmonics + 1):
            param(f"Fp_{i}", F, 0.0, s.force, 0.5 * s.force, "[0, F_s]")
        for i in range(1, harmonics + 1):
            param(f"phi_{i}", "rad", -math.pi, math.pi, 0.0, "any phase")
    if mass_from == "from --mass":
        # the config carries the mass so that the printed next command needs no --mass
        params.append(
            f'mass = {{ unit = "{u.inertia}", value = {_g(float(rec.mass))} }}  # {mass_from}'
        )
    level = f"[0, F_s], F_s = {_g(s.force)} {F}"
    viscous_hi = s.force / s.v_max
    viscous_why = f"[0, F_s/v_max], v_max = {_g(s.v_max)} {V}: viscous force at top speed <= F_s"
    if "stribeck" in friction:
        terms.append("stribeck_friction")
        param("Fc", F, 0.0, s.force, 0.1 * s.force, level)
        param("Fs", F, 0.0, s.force, 0.15 * s.force, f"{level}; static level, >= Fc expected")
        param(
            "vs",
            V,
            s.v_max / 1000.0,
            s.v_max,
            0.1 * s.v_max,
            "[v_max/1000, v_max]: the drop happens at speeds the record reaches",
        )
        params.append(
            'delta = { unit = "1", value = 1.0 }  # Tustin shape; free it in [0.5, 2] to fit it'
        )
    else:
        terms.append("coulomb_viscous")
        param("Fc", F, 0.0, s.force, 0.1 * s.force, level)
    if "viscous" in friction:
        param("Fv", unit("N*s/m"), 0.0, viscous_hi, 0.1 * viscous_hi, viscous_why)
    else:
        params.append(f'Fv = {{ unit = "{C}", value = 0.0 }}  # no viscous term (--friction)')
    head = [
        f"# Starting config for {name}, written by `fricjax init-config` from the recording's",
        "# own scale (after the preprocessing below): every bound says where it came from.",
        f"# {u.kind} axis: {u.position}, {u.velocity}, {u.force}, {u.inertia}; "
        f"{u.inertia_word} {_g(float(rec.mass))} {u.inertia} {mass_from}.",
        f"# Record: {rec.n} samples at {_g(1.0 / rec.dt)} Hz ({_g(rec.duration)} s); "
        f"max |v| = {_g(s.v_max)} {V}; m·max|a| = {_g(s.inertial)} {F}.",
    ]
    if drive == "measured":
        what = "measured force /F [N]" if s.signal == "F" else f"drive input /u [{rec.u_unit}]"
        head.append(f"# Drive: measured_input on the {what}, filtered like m·a.")
        if s.signal == "u" and not rec.u_unit:
            head.append(
                f"# /u has no unit: if it is a force in {F} (a load cell), write the config "
                f"again with --u-unit {F.replace('·', '*')} to fix its gain at 1."
            )
    head.append("# Widen a bound that the identified value sits on; fix a parameter the record")
    head.append("# does not determine (identify's summary names them).")
    lines = [*head, "", "[model]", f"terms = {terms!r}".replace("'", '"')]
    if u.kind != "linear":
        lines.append(f'axis = "{u.kind}"')
    if drive == "measured" and s.signal == "F":
        lines += ["", "[model.measured_input]", 'signal = "F"   # read /F, not /u']
    if drive == "harmonic":
        lines += ["", "[model.harmonic_drive]", f"harmonics = {harmonics}"]
    lines += ["", "[params]", *params]
    lines += [
        "",
        "[preprocess]",
        "# zero-phase Butterworth on central differences; cutoff at most a fifth of the",
        "# sampling rate; trim drops three cutoff periods of end transient (<= 5 % of the record)",
        'method = "butterworth"',
        f"order = {pre.order}",
        f"cutoff_hz = {_g(pre.cutoff_hz)}",
        f"stencil = {pre.stencil}",
        f"trim = {pre.trim}",
        "",
        "[search]",
        "# variable projection: every term here is linear in its forces, so the chains search",
        "# only the nonlinear parameters (omega, vs) and the rest is solved exactly",
        'method = "csaa"',
        "chains = 16",
        "seed = 0",
        "refine_top = 4",
        "separable = true",
        "",
    ]
    nonlinear = (drive == "harmonic") + ("stribeck" in friction)
    if nonlinear:
        # the default schedule is sized for the seed's 26-D search; over one or two
        # nonlinear parameters a short one finds the same minimum in a fraction of the time
        lines += [
            "[search.separable_budget]",
            f"# {nonlinear} nonlinear parameter{'s' * (nonlinear > 1)}: a short schedule",
            "chains = 8",
            "steps_per_level = 4",
            "alpha = 0.7",
            "t_min_rel = 1e-3",
            "patience = 3",
            "",
        ]
    return "\n".join(lines)


def is_force_unit(unit: str, axis: AxisUnits) -> bool:
    """Whether ``unit`` is the axis's force unit (``N``; ``N·m``, ``N*m`` or ``Nm`` on a
    rotary axis)."""
    spelled = unit.strip().replace("*", "·").replace(" ", "")
    return bool(spelled) and spelled in (axis.force, axis.force.replace("·", ""))
