"""Whether the order of a fit batch's rays changes the compiled renderer's backward time: 2,048
random rays inside the `render_compare` bench's room grid (one scene), rendered with jitter,
backward of their summed colour, best of 20, in random order and sorted by the coarse cell
(8 per axis) each passes 2 m from its origin.

    PYTHONPATH=src python experiments/demo/backward_order.py
"""

from __future__ import annotations

import time

import torch

from pae.bench.render_compare import room_grid


def main(rays: int = 2048, repeats: int = 20) -> None:
    grid = room_grid(1).grids[0]
    generator = torch.Generator().manual_seed(1)
    origins = torch.rand(rays, 3, generator=generator) * 2 - 1 + torch.tensor([0.0, 0.0, 1.4])
    directions = torch.randn(rays, 3, generator=generator)
    middle = origins + 2.0 * directions / directions.norm(dim=1, keepdim=True)
    cell = ((middle - grid.lo) / (grid.hi - grid.lo) * 8).clamp(0, 7).long()
    by_cell = (cell[:, 2] * 64 + cell[:, 1] * 8 + cell[:, 0]).argsort()
    for name, order in (("random order", torch.arange(rays)), ("sorted by cell", by_cell)):
        best = float("inf")
        for _ in range(repeats):
            rgb, _, _ = grid.composite(origins[order], directions[order], 48, 0.05, True, "numba")
            start = time.perf_counter()
            torch.autograd.grad(rgb.sum(), grid.grid)
            best = min(best, time.perf_counter() - start)
        print(f"{name}: backward {1e3 * best:.2f} ms")


if __name__ == "__main__":
    main()
