"""What the benchmarks ran on: CPU model and SIMD flags, cores, memory, load, versions.

Also the nominal float64 peak of the CPU, used to express measured throughput as a fraction
of it::

    peak [FLOP/s] = cores × f [Hz] × FMA units × SIMD width [doubles] × 2 (an FMA is 2 FLOPs)

with the width read from the ``/proc/cpuinfo`` flags (``avx512f`` → 8 doubles, ``avx2`` +
``fma`` → 4, ``avx`` → 4 without FMA, else SSE2 → 2) and 2 FMA units per core.
"""

from __future__ import annotations

import os
import platform
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

#: Flags worth naming in a report (the full list is a few hundred entries).
SIMD_FLAGS: tuple[str, ...] = (
    "sse2",
    "avx",
    "avx2",
    "fma",
    "avx512f",
    "avx512dq",
    "avx512vl",
    "avx512_bf16",
    "amx_tile",
)


@dataclass(frozen=True)
class Machine:
    """Host description: ``cpu`` model name, ``mhz`` (per ``/proc/cpuinfo``, 0 if unknown),
    ``flags`` (the :data:`SIMD_FLAGS` present), ``cores`` (usable by this process),
    ``ram_gib``, ``load`` (1/5/15-minute load averages), ``versions`` (package → version),
    ``xla_flags`` (the ``XLA_FLAGS`` environment variable as this process sees it)."""

    cpu: str
    mhz: float
    flags: tuple[str, ...]
    cores: int
    ram_gib: float
    load: tuple[float, float, float]
    versions: dict[str, str]
    xla_flags: str

    @property
    def simd_doubles(self) -> int:
        return simd_width(self.flags)

    @property
    def peak_flops(self) -> float:
        """Nominal float64 peak [FLOP/s] (module docstring); 0 if the clock is unknown."""
        return peak_flops(self.cores, self.mhz * 1e6, self.flags)

    def markdown(self) -> str:
        """A Markdown bullet list (for the head of a report)."""
        versions = ", ".join(f"{k} {v}" for k, v in self.versions.items())
        peak = self.peak_flops
        return "\n".join(
            [
                f"- CPU: {self.cpu}, {self.mhz:.0f} MHz (per /proc/cpuinfo), "
                f"{self.cores} cores usable",
                f"- SIMD flags: {' '.join(self.flags) or 'none of ' + ' '.join(SIMD_FLAGS)} "
                f"→ {self.simd_doubles} doubles per vector",
                f"- nominal float64 peak: {peak / 1e9:.1f} GFLOP/s "
                f"({self.cores} cores × {self.mhz / 1e3:.2f} GHz × 2 FMA units × "
                f"{self.simd_doubles} doubles × 2)",
                f"- RAM: {self.ram_gib:.1f} GiB",
                f"- load average at start (1/5/15 min): "
                f"{self.load[0]:.2f} / {self.load[1]:.2f} / {self.load[2]:.2f}"
                + (" — other jobs shared the cores" if self.load[0] > 0.5 * self.cores else ""),
                f"- {versions}, Python {platform.python_version()}",
                f"- XLA_FLAGS: `{self.xla_flags or '(empty)'}`",
            ]
        )


def simd_width(flags: tuple[str, ...] | list[str] | set[str]) -> int:
    """float64 lanes of the widest vector unit named by the cpuinfo ``flags``."""
    have = set(flags)
    if "avx512f" in have:
        return 8
    if "avx2" in have or "avx" in have:
        return 4
    return 2


def peak_flops(cores: int, hz: float, flags: tuple[str, ...] | list[str] | set[str]) -> float:
    """``cores × hz × 2 FMA units × width × 2`` [FLOP/s]; without FMA one add and one
    multiply unit per core give the same count (2 units × width × 1 FLOP)."""
    have = set(flags)
    per_unit = 2 if ("fma" in have or "avx512f" in have) else 1
    return float(cores) * hz * 2 * simd_width(flags) * per_unit


def _cpuinfo(path: Path = Path("/proc/cpuinfo")) -> tuple[str, float, tuple[str, ...]]:
    try:
        text = path.read_text()
    except OSError:
        return platform.processor() or "unknown", 0.0, ()
    model, mhz, flags = "unknown", 0.0, ()
    for line in text.splitlines():
        key, _, value = line.partition(":")
        key = key.strip()
        if key == "model name" and model == "unknown":
            model = value.strip()
        elif key == "cpu MHz" and mhz == 0.0:
            try:
                mhz = float(value)
            except ValueError:
                mhz = 0.0
        elif key == "flags" and not flags:
            present = set(value.split())
            flags = tuple(f for f in SIMD_FLAGS if f in present)
    return model, mhz, flags


def _ram_gib(path: Path = Path("/proc/meminfo")) -> float:
    try:
        for line in path.read_text().splitlines():
            if line.startswith("MemTotal:"):
                return float(line.split()[1]) / 2**20
    except (OSError, ValueError, IndexError):
        pass
    return float("nan")


def _versions(packages: tuple[str, ...]) -> dict[str, str]:
    out = {}
    for pkg in packages:
        try:
            out[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            out[pkg] = "not installed"
    return out


def describe(
    packages: tuple[str, ...] = ("fricjax", "jax", "jaxlib", "numpy", "scipy"),
) -> Machine:
    """Describe this host now (reads /proc; no JAX call)."""
    cpu, mhz, flags = _cpuinfo()
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:
        cores = os.cpu_count() or 1
    try:
        load = os.getloadavg()
    except OSError:
        load = (float("nan"),) * 3
    return Machine(
        cpu=cpu,
        mhz=mhz,
        flags=flags,
        cores=cores,
        ram_gib=_ram_gib(),
        load=(float(load[0]), float(load[1]), float(load[2])),
        versions=_versions(packages),
        xla_flags=os.environ.get("XLA_FLAGS", ""),
    )
