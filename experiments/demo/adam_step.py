"""One Adam step over the demo scene model's parameters (two voxel grids of 300,000 cells,
raw density and RGB, stored channels last), with torch's three CPU implementations: the
multi-tensor default (``foreach``), the per-tensor loop and the fused kernel, best of three
blocks of 50 steps each, side by side in one process.

    PYTHONPATH=src python experiments/demo/adam_step.py
"""

from __future__ import annotations

import time

import torch


def main() -> None:
    torch.manual_seed(0)
    grids = [
        torch.nn.Parameter(torch.randn(1, 4, 60, 70, 72).to(memory_format=torch.channels_last_3d))
        for _ in range(2)
    ]
    for grid in grids:
        grid.grad = torch.randn_like(grid)
    for name, option in (
        ("foreach", {"foreach": True}),
        ("loop", {"foreach": False}),
        ("fused", {"fused": True}),
    ):
        optimizer = torch.optim.Adam(grids, lr=0.1, betas=(0.9, 0.99), **option)
        for _ in range(5):
            optimizer.step()
        best = float("inf")
        for _ in range(3):
            start = time.perf_counter()
            for _ in range(50):
                optimizer.step()
            best = min(best, (time.perf_counter() - start) / 50)
        print(f"{name:8s} {1000 * best:.2f} ms per step")


if __name__ == "__main__":
    main()
