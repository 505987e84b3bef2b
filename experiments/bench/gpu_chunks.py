"""The tensor engine's milliseconds per query on a CUDA device against the refiner's gpu_chunk
(queries refined at once): the render_compare benchmark's 1,000 queries
(pae.bench.render_compare) refined with each chunk, best of two calls, and the largest
difference of their answers from the first chunk's (the draws do not depend on the chunk).

    PYTHONPATH=src python experiments/bench/gpu_chunks.py [CHUNK ...]
"""

from __future__ import annotations

import sys
import time

import torch

from pae.bench.render_compare import bench_queries, room_grid
from pae.render_compare.refiner import RenderCompareRefiner


def main(argv: list[str]) -> int:
    if not torch.cuda.is_available():
        print("no CUDA device: skipped")
        return 0
    chunks = [int(a) for a in argv] or [64, 256, 1024]
    model = room_grid(2).to("cuda")
    inputs = [t.to("cuda") for t in bench_queries(1000, 2, 56, seed=0)]
    first = None
    for chunk in chunks:
        refiner = RenderCompareRefiner.configured(model, gpu_chunk=chunk)
        refiner(*(t[:4] for t in inputs))  # warm-up
        best = float("inf")
        for _ in range(2):
            torch.cuda.synchronize()
            start = time.perf_counter()
            result = refiner(*inputs)
            torch.cuda.synchronize()
            best = min(best, time.perf_counter() - start)
        first = result.poses if first is None else first
        diff = (result.poses - first).abs().max().item()
        memory = torch.cuda.max_memory_allocated() / 2**20
        print(
            f"chunk {chunk:5d}: {1000 * best / len(inputs[0]):.3f} ms per query, "
            f"answers differ from the first chunk's by {diff:.2e}, peak {memory:.0f} MiB"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
