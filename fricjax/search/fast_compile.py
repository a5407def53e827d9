"""XLA compiler options for programs that are compile-bound rather than run-bound.

A cold ``fricjax identify`` on the separable path spends seconds compiling programs that
then run for tenths of a second: the one-program variable-projection search
(:func:`fricjax.search.chains.run_chains_fused`), the Levenberg–Marquardt polish
(:func:`fricjax.refine.refine`) and the Jacobian of the uncertainty
(:func:`fricjax.refine.value_and_jacobian`). :data:`FAST_COMPILE` is passed to those
programs alone (``jax.jit(..., compiler_options=...)``), never set globally: the 26-D
annealing level and the throughput benchmark's kernel run ~10⁵ cost evaluations and keep
XLA's defaults.

* ``xla_cpu_use_fusion_emitters = False``: XLA:CPU's MLIR fusion emitters lower every
  fusion through an MLIR pipeline before LLVM, which dominated the compile time of these
  programs (~3 s of the one-program search's ~4 s at optimisation level 0); the classic
  elemental IR emitter skips it.
* ``xla_backend_optimization_level = 0``: LLVM's optimisation off.
* :data:`FAST_COMPILE_LOOPS` also skips two HLO passes, ``while-loop-invariant-code-motion``
  and ``simplify-while-loops``: with the two options above they took ~0.4 s of the ~0.6 s
  of HLO passes of the one-program search (nested while loops: levels, the active-set
  solve, the PRNG), each run ~14 times by the simplification pipeline. Its run time did
  not grow (measured); the LM polish's did (~100 → ~175 ms), so it keeps them.

Measured on 2 shared CPU cores (paper twin, compile / warm run, same load):
one-program search 5.2 s / 65-75 ms with XLA's defaults, 4.1-5.0 s / 200-230 ms at level 0
alone, 1.2-1.5 s / 160-250 ms with both, 0.6-0.85 s / 140-185 ms with
:data:`FAST_COMPILE_LOOPS`; LM polish (26 parameters, 200 steps) 3.2-3.8 s /
44-50 ms with the defaults, 2.4-2.6 s / 97-101 ms at level 0 alone, 0.75 s / 140-148 ms
with both (the fusion emitters off alone: 2.3 s / 40-53 ms).
"""

from __future__ import annotations

from typing import Any

import jax

#: The classic elemental emitter instead of XLA:CPU's MLIR fusion emitters, LLVM's
#: optimisation kept: for a program whose run time matters too (the output-error fit:
#: ~20 % less compile time, the same run time, measured in docs/output-error.md).
#: XLA of jax 0.11 has no classic CPU emitter left to fall back on and refuses the option
#: by name, so it is passed only to the XLA that knows it.
CLASSIC_EMITTERS: dict[str, Any] = (
    {"xla_cpu_use_fusion_emitters": False} if jax.__version_info__ < (0, 11) else {}
)
#: ``compiler_options`` of a compile-bound program (see the module docstring).
FAST_COMPILE: dict[str, Any] = {"xla_backend_optimization_level": 0, **CLASSIC_EMITTERS}
#: :data:`FAST_COMPILE` without the while-loop passes (programs of nested while loops).
FAST_COMPILE_LOOPS: dict[str, Any] = {
    **FAST_COMPILE,
    "xla_disable_hlo_passes": "while-loop-invariant-code-motion,simplify-while-loops",
}
