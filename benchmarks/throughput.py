"""Cost evaluations/s against chain count (float64, float32, numpy),
compile time, memory, 1 vs 2 host devices, the YNN flag, fraction of peak;
`fricjax bench throughput` as a script, writing benchmarks/results/throughput.md
(`python benchmarks/throughput.py --help` for the options)."""

import sys

from fricjax.cli import main

if __name__ == "__main__":
    sys.argv = ["fricjax", "bench", "throughput", *sys.argv[1:]]
    main()
