"""Benchmarks: `make bench` / `pae-bench` (``cli``) and the timing harnesses it runs
(``refinement``: weight fitting, the first layer's series, the pose index). Library modules
hold no benchmark code."""

from pae.bench.cli import main

__all__ = ["main"]
