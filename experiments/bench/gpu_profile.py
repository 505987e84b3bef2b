"""Where the tensor engine's time goes on a CUDA device: one batched refinement of the
render_compare benchmark's 250 queries (pae.bench.render_compare) under torch's profiler,
the 20 operators that take the most device time and the 20 that take the most host time.

    PYTHONPATH=src python experiments/bench/gpu_profile.py
"""

from __future__ import annotations

import sys

import torch
from torch.profiler import ProfilerActivity, profile

from pae.bench.render_compare import bench_queries, room_grid
from pae.render_compare.refiner import RenderCompareRefiner


def main() -> int:
    if not torch.cuda.is_available():
        print("no CUDA device: skipped")
        return 0
    model = room_grid(2).to("cuda")
    inputs = [t.to("cuda") for t in bench_queries(250, 2, 56, seed=0)]
    refiner = RenderCompareRefiner.configured(model)
    refiner(*(t[:4] for t in inputs))  # warm-up
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as run:
        refiner(*inputs)
        torch.cuda.synchronize()
    table = run.key_averages()
    print(table.table(sort_by="self_cuda_time_total", row_limit=20))
    print(table.table(sort_by="self_cpu_time_total", row_limit=20))
    print(refiner.work)
    return 0


if __name__ == "__main__":
    sys.exit(main())
