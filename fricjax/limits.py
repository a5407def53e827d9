"""Sizes that cannot fit in this machine's memory or in reasonable time, refused up front.

Each limit is an estimate with its reasoning here, in one place, and the refusal states the
estimate, so a user can tell a typo (``--chains 1000000000``) from a run that is merely big.

- **Chains** (:func:`check_chains`): every chain evaluates the cost over the whole record
  at once (vmapped), and on the separable path solves a least-squares problem whose
  design matrix is ``[n, d]``; the one-program search also keeps its ``[levels, chains]``
  history of best cost, current cost and acceptance. Per chain that is at least
  ``8 B × (n × (d + SIGNALS) + 3 × levels)``; chains whose total exceeds the memory the
  operating system reports available cannot run, and the run is refused before it
  allocates anything (a larger count would swap, then be killed).
- **RK4 sub-steps** (:func:`check_substeps`): memory is ``O(n)``, time is
  ``n × substeps`` sub-steps at about ``RK4_STEPS_PER_S`` (measured for the paper model:
  ~10⁴/s on a loaded 2-core machine,
  docs/robustness.md). ``MAX_RK4_STEPS`` = 10⁸ is hours of stepping at that rate, while
  RK4's truncation error falls as ``substeps⁻⁴``: 4 → 64 sub-steps already divides it by
  65 536, so a run past the cap is a typo rather than a need.
- **Decimation** (:func:`check_decimation`): the zero-phase anti-alias filter of
  :func:`fricjax.data.decimate.antialias_kernel` has a half length of at least
  ``HALF_LENGTH_PER_Q × q`` samples (measured: 1545 at q = 10, 15222 at q = 100, never
  below 152·q), and decimation needs more samples than that.
"""

from __future__ import annotations

import os

from fricjax.errors import FricjaxError, where

#: Bytes of one float64.
F64 = 8
#: Record-long float64 signals a chain's cost keeps live besides its design matrix
#: (x, v, a, u, force, residual and the terms' intermediates).
SIGNALS = 8
#: Total RK4 sub-steps (``n × substeps``) a simulation may take (module docstring).
MAX_RK4_STEPS = 10**8
#: Measured RK4 sub-steps per second of the paper model (order of magnitude, for messages).
RK4_STEPS_PER_S = 10**4
#: Lower bound on the anti-alias filter's half length per unit of the factor q.
HALF_LENGTH_PER_Q = 152


def available_memory() -> int:
    """Bytes of memory the operating system reports available (MemAvailable), or the
    physical memory where that is not reported."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def _size(n_bytes: float) -> str:
    for unit, scale in (("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if n_bytes >= scale:
            return f"{n_bytes / scale:.3g} {unit}"
    return f"{n_bytes:.0f} B"


def chain_bytes(n_samples: int, n_params: int, levels: int) -> int:
    """Estimated bytes one search chain needs (module docstring)."""
    return F64 * (n_samples * (n_params + SIGNALS) + 3 * levels)


def check_chains(
    chains: int,
    n_samples: int,
    n_params: int,
    levels: int,
    source: object,
    memory: int | None = None,
) -> None:
    """Refuse a chain count whose estimated memory exceeds ``memory`` (default: what is
    available now), naming the estimate and the largest count that fits."""
    memory = available_memory() if memory is None else memory
    per_chain = chain_bytes(n_samples, n_params, levels)
    need = chains * per_chain
    if need > memory:
        raise FricjaxError(
            f"{where(source, 'chains')}: {chains} chains need about {_size(need)} "
            f"({_size(per_chain)} each for {n_samples} samples and {n_params} parameters), "
            f"more than the {_size(memory)} available; at most {memory // per_chain} fit"
        )


def check_substeps(substeps: int, n_samples: int, source: object) -> None:
    """Refuse a simulation of more than :data:`MAX_RK4_STEPS` RK4 sub-steps in all."""
    steps = substeps * max(n_samples - 1, 1)
    if steps > MAX_RK4_STEPS:
        raise FricjaxError(
            f"{where(source, 'substeps')}: {substeps} sub-steps over {n_samples} samples is "
            f"{steps:.3g} RK4 steps, about {steps / RK4_STEPS_PER_S / 3600:.3g} h at "
            f"~{RK4_STEPS_PER_S:.0e} steps/s, more than the {MAX_RK4_STEPS:.0e} allowed "
            "(RK4's error falls as substeps^-4: a few dozen are plenty); use at most "
            f"{max(MAX_RK4_STEPS // max(n_samples - 1, 1), 1)}"
        )


def check_decimation(q: int, n_samples: int, source: object) -> None:
    """Refuse a decimation factor whose anti-alias filter is longer than the record."""
    if q > 1 and q * HALF_LENGTH_PER_Q >= n_samples:
        raise FricjaxError(
            f"{where(source, 'decimate')}: decimating {n_samples} samples by {q} needs more "
            f"than {HALF_LENGTH_PER_Q}·q = {q * HALF_LENGTH_PER_Q} samples (the anti-alias "
            f"filter's half length); use at most {max((n_samples - 1) // HALF_LENGTH_PER_Q, 1)}"
        )
