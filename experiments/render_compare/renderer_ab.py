"""The compiled renderer of another commit against this checkout's, side by side in one
process on the same rays: its forward and backward passes over 256,000 rays (250 cameras of
32×32 px in the `render_compare` bench's room grid, 48 jittered samples each), best of three
rounds of five forward and three backward calls each, and how far their answers differ.

    PYTHONPATH=src python experiments/render_compare/renderer_ab.py COMMIT
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

import pae.scene_model.voxel_render as current
from pae.bench.render_compare import bench_queries, room_grid
from pae.core.camera import camera_rays

MODULE = "src/pae/scene_model/voxel_render.py"


def load_at(commit: str):
    """``pae.scene_model.voxel_render`` as it was at ``commit`` (a module of its own)."""
    shown = subprocess.run(["git", "show", f"{commit}:{MODULE}"], capture_output=True, text=True)
    if shown.returncode:
        sys.exit(f"renderer_ab: no {MODULE} at {commit!r}: {shown.stderr.strip()}")
    source = shown.stdout
    path = Path(tempfile.mkdtemp()) / "voxel_render_at_commit.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def seconds(run, repeats: int) -> float:
    start = time.perf_counter()
    for _ in range(repeats):
        run()
    return (time.perf_counter() - start) / repeats


def main(commit: str) -> None:
    model = room_grid(2)
    grid = model.grids[0]
    _, _, start, _ = bench_queries(250, 2, 56, seed=0)
    intrinsics = torch.tensor([38.4, 38.4, 15.5, 15.5]).expand(250, 4)
    origins, directions = (t.reshape(-1, 3) for t in camera_rays(start, intrinsics, 32, 32))
    with torch.no_grad():
        rays = grid.ray_bounds(origins, directions, model.near_m)
    n_rays, samples = len(origins), model.samples_per_ray
    geometry = current.GridGeometry(
        grid.lo.double().numpy(),
        grid.hi.double().numpy(),
        np.array([n - 1 for n in grid.shape], np.float64),
        1 / grid.voxel_m,
        False,
    )
    arrays = current.RaySegments(*(p.double().contiguous().numpy() for p in rays))
    offsets = np.random.default_rng(0).random((n_rays, samples)).astype(np.float32)
    march = current.March(
        grid.kernel_cells(), arrays, offsets, geometry, grid.density_shift, np.full(3, 0.5)
    )
    upstream = np.random.default_rng(1).random((n_rays, 3)).astype(np.float32)
    answers = {}
    for name, module in ((commit, load_at(commit)), ("this checkout", current)):
        out = [np.empty((n_rays, 3), np.float32), np.empty(n_rays, np.float32)]
        out += [np.empty(n_rays, np.float32), np.empty(n_rays, np.int64)]
        grad = np.zeros((2, *march.grid.shape), np.float32)
        background = np.zeros((2, 3))

        def forward(module=module, out=out) -> None:
            module.render_forward(march, *out)

        def backward(module=module, out=out, grad=grad, background=background) -> None:
            grad[:] = 0
            module.render_backward(march, out[0], out[3], upstream, grad, background)

        forward(), backward()  # compile
        times = [(seconds(forward, 5), seconds(backward, 3)) for _ in range(3)]
        best = [min(t[i] for t in times) for i in range(2)]
        print(f"{name}: forward {1e3 * best[0]:.1f} ms, backward {1e3 * best[1]:.1f} ms")
        answers[name] = (out[0].copy(), grad.sum(0))
    (rgb_a, grad_a), (rgb_b, grad_b) = answers.values()
    print(
        f"largest difference: rgb {np.abs(rgb_a - rgb_b).max():.2e}, gradient "
        f"{np.abs(grad_a - grad_b).max() / np.abs(grad_a).max():.2e} of its largest entry"
    )


if __name__ == "__main__":
    main(sys.argv[1])
