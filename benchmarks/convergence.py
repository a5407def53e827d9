"""Convergence of RDSA, CSAA, DSAA (+ variants, + separable) on the paper twin at an equal
evaluation budget -> benchmarks/results/convergence.md + PNGs; `fricjax bench convergence`
with the same options (`python benchmarks/convergence.py --help`)."""

import sys

from fricjax.cli import main

if __name__ == "__main__":
    sys.argv = ["fricjax", "bench", "convergence", *sys.argv[1:]]
    main()
