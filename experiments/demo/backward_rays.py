"""The compiled renderer's cost per sample in a trained grid, forward and backward, for batches
of random rays (the fit's kind: random origins within 1 m of the grid's centre, random
directions) of several sizes: best of ten calls each, 48 jittered samples per ray; and what
the backward's per-thread copies of the grid's gradient cost alone (zeroed, two threads'
worth, summed as ``CompiledComposite.backward`` does; best of 50).

    PYTHONPATH=src python experiments/demo/backward_rays.py [SCENE_MODEL_CKPT]
    # default: outputs/demo/scene_model/checkpoints/last.ckpt, its first scene's grid
"""

from __future__ import annotations

import sys
import time

import numpy as np
import torch

from pae.core.checkpoints import load_scene_model


def main(path: str = "outputs/demo/scene_model/checkpoints/last.ckpt") -> None:
    grid = load_scene_model(path).model.grids[0]
    generator = torch.Generator().manual_seed(1)
    centre = (grid.lo + grid.hi) / 2
    for rays in (512, 2048, 8192, 32768):
        origins = centre + (torch.rand(rays, 3, generator=generator) - 0.5) * 2
        directions = torch.randn(rays, 3, generator=generator)
        forward = backward = float("inf")
        for _ in range(10):
            start = time.perf_counter()
            rgb, _, _ = grid.composite(origins, directions, 48, 0.05, True, "numba")
            forward = min(forward, time.perf_counter() - start)
            start = time.perf_counter()
            torch.autograd.grad(rgb.sum(), grid.grid)
            backward = min(backward, time.perf_counter() - start)
        per_sample = 1e9 / rays / 48
        print(
            f"{rays} rays: forward {1e3 * forward:.2f} ms ({forward * per_sample:.1f} ns per "
            f"sample), backward {1e3 * backward:.2f} ms ({backward * per_sample:.1f} ns)"
        )
    shape = tuple(grid.kernel_cells().shape)
    print(f"zeroing and summing two gradient copies of {shape}: {gradient_copies_ms(shape):.2f} ms")


def gradient_copies_ms(shape: tuple[int, ...], threads: int = 2, repeats: int = 50) -> float:
    """Milliseconds to zero ``threads`` copies of a gradient of ``shape`` and sum them."""
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        np.zeros((threads, *shape), np.float32).sum(0)
        best = min(best, time.perf_counter() - start)
    return 1e3 * best


if __name__ == "__main__":
    main(*sys.argv[1:2])
