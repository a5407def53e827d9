"""Write ``examples/axis.csv``: a linear axis pushed by a measured force, as a test rig logs it.

The plant is a body of mass m on a guide with Coulomb, viscous and Stribeck friction,

    m·ẍ = F(t) − ([Fc + (Fs − Fc)·exp(−|ẋ|/vs)]·sgn(ẋ) + Fv·ẋ)      [N]

driven by a force F(t) that a load cell measures (the CSV's ``u`` column, newtons). It is
integrated by scipy's ``solve_ivp`` (RK45, rtol 1e-10) phase by phase: sliding until the
velocity crosses zero, then sticking while the force stays within the static limit Fs,
then sliding again, each switch located by an event. The encoder reads x with white noise
of 1 µm, the load cell F with 0.05 N; 2 s at 1 kHz.

Two runs of the rig: ``axis.csv`` (identification) and ``axis_validation.csv`` (another
force profile and noise draw, to check the model on data it was not fitted to).

Usage: ``python examples/make_axis_csv.py [FOLDER]`` (default: beside this script);
``python examples/make_axis_csv.py --run PROFILE.csv --out RUN.csv [--seed S]`` runs the same
rig under a force profile (columns ``t,u``, e.g. what ``fricjax design`` writes, linearly
interpolated) and writes the recording it would log. The noise
has fixed seeds, so a run writes the same files bit for bit on one machine; another CPU may
round the integration's last digits differently (about 1e-13 m, far below the 1 µm noise).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp

MASS = 12.0  # kg
FC, FS, VS, FV = 8.0, 14.0, 0.02, 60.0  # N, N, m/s, N·s/m
RATE, DURATION = 1000.0, 2.0  # Hz, s
NOISE_X, NOISE_F = 1e-6, 0.05  # m, N
#: file name -> (noise seed, force profile: (amplitude [N], frequency [Hz], phase [rad]) of
#: each sine), so that the axis reverses and stops a few times in each run.
RUNS = {
    "axis.csv": (0, ((30.0, 1.0, 0.0), (12.0, 2.3, 1.0))),
    "axis_validation.csv": (1, ((26.0, 0.8, 0.5), (14.0, 2.9, 0.3))),
}


Profile = tuple[tuple[float, float, float], ...] | tuple[np.ndarray, np.ndarray]


def force(t: np.ndarray | float, profile: Profile) -> np.ndarray:
    """Measured force F(t) [N]: a sum of sines A·sin(2πf·t + φ), or samples ``(t_k, F_k)``
    interpolated linearly."""
    if len(profile) == 2 and isinstance(profile[0], np.ndarray):
        return np.interp(t, profile[0], profile[1])
    return sum(a * np.sin(2 * math.pi * f * np.asarray(t) + p) for a, f, p in profile)


def friction(v: float) -> float:
    """Sliding friction F_f(v) [N], odd in v."""
    return (FC + (FS - FC) * math.exp(-abs(v) / VS)) * math.copysign(1.0, v) + FV * v


def simulate(t_eval: np.ndarray, profile: Profile) -> np.ndarray:
    """Exact motion x(t) [m] at ``t_eval`` [s] under ``force(t, profile)``, from rest at 0."""

    def drive(s: float) -> float:
        return float(force(s, profile))

    x_out = np.empty_like(t_eval)
    t, x, v = float(t_eval[0]), 0.0, 0.0
    t_end = float(t_eval[-1])
    while t < t_end:
        if v == 0.0 and abs(drive(t)) <= FS:
            # stuck: x stays until the force exceeds the static limit
            def breakaway(s: float, y: np.ndarray) -> float:
                return abs(drive(s)) - FS

            breakaway.terminal = True  # type: ignore[attr-defined]
            sol = solve_ivp(lambda s, y: [0.0], (t, t_end), [x], events=breakaway, max_step=1e-3)
            t_next = float(sol.t_events[0][0]) if sol.t_events[0].size else t_end
            x_out[(t_eval >= t) & (t_eval <= t_next)] = x
            direction = math.copysign(1.0, drive(t_next + 1e-9))
            t, v = t_next, 1e-12 * direction
            continue
        direction = math.copysign(1.0, v if v != 0.0 else drive(t))

        def rhs(s: float, y: np.ndarray, d: float = direction) -> list[float]:
            return [y[1], (drive(s) - friction(y[1] if y[1] != 0.0 else d)) / MASS]

        def stop(s: float, y: np.ndarray, d: float = direction) -> float:
            return y[1] * d

        stop.terminal = True  # type: ignore[attr-defined]
        stop.direction = -1  # type: ignore[attr-defined]
        mask = t_eval >= t
        sol = solve_ivp(
            rhs,
            (t, t_end),
            [x, v if v != 0.0 else 1e-12 * direction],
            t_eval=t_eval[mask],
            events=stop,
            rtol=1e-10,
            atol=1e-13,
        )
        x_out[np.nonzero(mask)[0][: sol.t.size]] = sol.y[0]
        if sol.status == 1:  # the velocity reached zero
            t, x, v = float(sol.t_events[0][0]), float(sol.y_events[0][0][0]), 0.0
        else:
            break
    return x_out


def record(t: np.ndarray, profile: Profile, seed: int, path: Path) -> None:
    """Run the rig under ``profile`` and write what it logs: ``t,x,u`` with the noise of
    encoder and load cell."""
    x = simulate(t, profile)
    rng = np.random.default_rng(seed)
    x_meas = x + rng.normal(0.0, NOISE_X, t.size)
    f_meas = force(t, profile) + rng.normal(0.0, NOISE_F, t.size)
    rows = "\n".join(
        f"{a:.17g},{b:.17g},{c:.17g}" for a, b, c in zip(t, x_meas, f_meas, strict=True)
    )
    path.write_text("t,x,u\n" + rows + "\n")
    print(f"wrote {path}: {t.size} samples, x in [{x.min():.4f}, {x.max():.4f}] m")


def main(folder: Path) -> None:
    """Write the two runs of RUNS into ``folder``."""
    t = np.arange(round(RATE * DURATION)) / RATE
    for name, (seed, profile) in RUNS.items():
        record(t, profile, seed, folder / name)


def run_profile(profile_csv: Path, out: Path, seed: int = 2) -> None:
    """Run the rig under the force profile of ``profile_csv`` (columns t, u) into ``out``."""
    given = np.loadtxt(profile_csv, delimiter=",", skiprows=1)
    record(given[:, 0], (given[:, 0], given[:, 1]), seed, out)


if __name__ == "__main__":
    argv = sys.argv[1:]
    if argv[:1] == ["--run"]:
        flags = dict(zip(argv[::2], argv[1::2], strict=False))
        run_profile(Path(flags["--run"]), Path(flags["--out"]), int(flags.get("--seed", 2)))
    else:
        main(Path(argv[0]) if argv else Path(__file__).parent)
