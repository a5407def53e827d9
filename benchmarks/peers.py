"""fricjax against scipy differential_evolution / dual_annealing and pycma's
CMA-ES on the paper twin (same cost, box, target): time and evaluations to 1 % of c*;
`fricjax bench peers` as a script, writing benchmarks/results/peers.md
(`python benchmarks/peers.py --help` for the options)."""

import sys

from fricjax.cli import main

if __name__ == "__main__":
    sys.argv = ["fricjax", "bench", "peers", *sys.argv[1:]]
    main()
