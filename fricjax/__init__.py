"""fricjax: friction-model identification and missing-physics diagnosis in JAX."""

from __future__ import annotations

import jax

# Identification costs are sums of ~1e3 squared forces of ~1e3 N: float32 loses the
# differences that annealing and Levenberg-Marquardt compare, so float64 is the default.
jax.config.update("jax_enable_x64", True)

__version__ = "0.1.0"
