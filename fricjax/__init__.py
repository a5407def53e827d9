"""fricjax: friction-model identification and missing-physics diagnosis in JAX."""

from __future__ import annotations

import os

# XLA's CPU backend fuses the elementwise chains of the cost (harmonic recurrence, Stribeck
# curve) far better with the YNN fusion pass disabled: 18k -> 107k cost evaluations/s on
# the paper twin (benchmarks/throughput.py). It must be set before jax starts its backend;
# an explicit setting in XLA_FLAGS wins, and FRICJAX_XLA_DEFAULTS=0 turns this off.
_YNN = "--xla_cpu_experimental_ynn_fusion_type="
if os.environ.get("FRICJAX_XLA_DEFAULTS", "1") != "0" and "ynn_fusion_type" not in os.environ.get(
    "XLA_FLAGS", ""
):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {_YNN}".strip()

import jax  # noqa: E402

# Identification costs are sums of ~1e3 squared forces of ~1e3 N: float32 loses the
# differences that annealing and Levenberg-Marquardt compare, so float64 is the default.
jax.config.update("jax_enable_x64", True)

__version__ = "0.1.0"
