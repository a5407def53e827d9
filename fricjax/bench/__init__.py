"""Benchmarks of the search on the paper twin: convergence of the seed's algorithms, peer
optimisers (scipy, pycma) and raw cost throughput. Each writes a Markdown report (and
PNGs) atomically; ``fricjax bench …`` and ``benchmarks/*.py`` call the same functions."""
