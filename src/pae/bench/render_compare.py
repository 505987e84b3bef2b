"""Render-and-compare speed, side by side in one run: the refiner's milliseconds per query
(batched, as the callback runs it), the compiled scorer against the tensor one, and the
compiled volume renderer against the ``grid_sample`` one, and a step of the scene model's fit
compiled against the tensor one, on the same inputs.

The scene model is the default voxel grid (conf/scene_model/voxel_grid.yaml) over a room of
the benchmark's size whose walls are opaque and whose inside is empty, so that rays stop
where a trained grid's would (the speed depends on where rays stop, not on the colours).
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

from pae import CONFIG_DIR
from pae.core.geometry import matrix_to_quaternion
from pae.core.pose_sampling import perturb
from pae.render_compare.refiner import RenderCompareRefiner
from pae.scene_model.voxel_grid import VoxelGridSceneModel

ROOM_HALF_M = (3.5, 3.0)
"""Half the room's width and depth (m); the room spans z in [0, 2.8] m."""


def room_grid(
    scenes: int = 2, num_voxels: int | None = None, samples_per_ray: int | None = None
) -> VoxelGridSceneModel:
    """The default grid (conf/scene_model/voxel_grid.yaml; ``num_voxels``: another size, per
    scene; ``samples_per_ray``: another count) over bounds [-4, 4] x [-4, 4] x [-0.5, 3.3] m
    per scene, uncontracted, dense (raw density +8) outside the room and empty (-8) inside,
    colours random."""
    path = Path(CONFIG_DIR) / "scene_model" / "voxel_grid.yaml"
    settings = OmegaConf.to_container(OmegaConf.load(path).model)
    model = VoxelGridSceneModel(
        [[[-4.0, -4.0, -0.5], [4.0, 4.0, 3.3]]] * scenes,
        n_appearances=1,
        num_voxels=num_voxels or settings["num_voxels"],
        samples_per_ray=samples_per_ray or settings["samples_per_ray"],
        contract=False,
        near_m=settings["near_m"],
    )
    generator = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for grid in model.grids:
            nz, ny, nx = grid.grid.shape[2:]
            z = torch.linspace(float(grid.lo[2]), float(grid.hi[2]), nz)[:, None, None]
            y = torch.linspace(float(grid.lo[1]), float(grid.hi[1]), ny)[None, :, None]
            x = torch.linspace(float(grid.lo[0]), float(grid.hi[0]), nx)[None, None, :]
            inside = (x.abs() < ROOM_HALF_M[0]) & (y.abs() < ROOM_HALF_M[1]) & (z > 0) & (z < 2.8)
            grid.grid[0, 0] = torch.where(inside, -8.0, 8.0)
            grid.grid[0, 1:] = torch.randn(3, nz, ny, nx, generator=generator)
    return model


def bench_queries(n: int, scenes: int, size: int, seed: int) -> tuple[torch.Tensor, ...]:
    """Random query images [n, 3, size, size], their intrinsics, start poses inside the
    room (level cameras of random heading) and scene ids."""
    generator = torch.Generator().manual_seed(seed)
    images = torch.rand(n, 3, size, size, generator=generator)
    f = (size / 2) / math.tan(math.radians(65.0) / 2)
    intrinsics = torch.tensor([f, f, (size - 1) / 2, (size - 1) / 2]).expand(n, 4)
    axes = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    level = matrix_to_quaternion(axes)  # camera z along world x, camera y down
    position = torch.cat(
        [torch.rand(n, 2, generator=generator) * 2 - 1, torch.full((n, 1), 1.4)], 1
    )
    start = torch.cat([position, level.expand(n, 4)], 1)
    heading = torch.zeros(n, 6)
    heading[:, 4] = torch.rand(n, generator=generator) * 2 * math.pi  # about the camera y axis
    return images, intrinsics, perturb(start, heading), torch.arange(n) % scenes


def _seconds(run, device: str = "cpu") -> float:
    """Seconds ``run()`` takes, a CUDA device synchronised before and after."""
    synchronize = torch.cuda.synchronize if device.startswith("cuda") else (lambda: None)
    synchronize()
    start = time.perf_counter()
    run()
    synchronize()
    return time.perf_counter() - start


def machine_gflops(size: int = 1024, repeats: int = 5) -> float:
    """The machine's measured float32 throughput (GFLOP/s): the best of ``repeats``
    ``size``-square matrix products on torch's threads, the roof the kernels are put
    against."""
    a, b = torch.randn(size, size), torch.randn(size, size)
    a @ b
    best = min(_seconds(lambda: a @ b) for _ in range(repeats))
    return 2 * size**3 / best / 1e9


def fit_step_seconds(
    model: VoxelGridSceneModel, engine: str, steps: int = 10, device: str = "cpu"
) -> float:
    """Seconds per fit step of the scene model (on ``device``) on ``engine``: a batch of rays
    from inside the room rendered with jitter, their squared error and the grid's total
    variation (the batch and weight of ``conf/scene_model/base.yaml``), backward and one Adam
    step."""
    fit = OmegaConf.load(Path(CONFIG_DIR) / "scene_model" / "base.yaml")
    generator = torch.Generator().manual_seed(1)
    rays = int(fit.rays_per_batch)
    origins = torch.rand(rays, 3, generator=generator) * 2 - 1 + torch.tensor([0.0, 0.0, 1.4])
    directions = torch.randn(rays, 3, generator=generator)
    target = torch.rand(rays, 3, generator=generator)
    origins, directions, target = (t.to(device) for t in (origins, directions, target))
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    half = rays // len(model.grids)

    def step() -> None:
        loss = torch.zeros((), device=device)
        for i, grid in enumerate(model.grids):
            part = slice(i * half, (i + 1) * half)
            rgb, _, _ = grid.composite(
                origins[part], directions[part], model.samples_per_ray, model.near_m, True, engine
            )
            loss = loss + (rgb - target[part]).square().mean()
            loss = loss + fit.tv_weight * grid.total_variation(engine) / len(model.grids)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()

    step()
    return _seconds(lambda: [step() for _ in range(steps)], device) / steps


def bench_render_compare(
    queries: int = 250, scenes: int = 2, crop: int = 56, device: str = "cpu"
) -> dict[str, float]:
    """The refiner at its default settings, batched as the callback runs it, on ``device``:
    `bench/render_compare/ms_per_query` and its parts (the search's scores, the polish, the
    reference renderings), the kernels' counted work (`mflop_per_query`) and its rate against
    the machine's measured throughput (`roofline_fraction`); elsewhere a step of the scene
    model's fit there (the torch engine, `bench/scene_model/fit_step_ms`); on CPU the compiled
    scorer's and renderer's speed-ups over their tensor versions (same inputs)."""
    model = room_grid(scenes).to(device)
    images, intrinsics, start, scene_ids = (
        t.to(device) for t in bench_queries(queries, scenes, crop, seed=0)
    )
    RenderCompareRefiner.configured(model)(
        images[:4], intrinsics[:4], start[:4], scene_ids[:4]
    )  # compile
    refiner = RenderCompareRefiner.configured(model)
    seconds = _seconds(lambda: refiner(images, intrinsics, start, scene_ids), device)
    work = refiner.work
    kernel_s = work.score_s + work.polish_s
    prefix = "bench/render_compare"
    figures = {
        f"{prefix}/ms_per_query": 1000 * seconds / queries,
        f"{prefix}/search_ms_per_query": 1000 * work.score_s / queries,
        f"{prefix}/polish_ms_per_query": 1000 * work.polish_s / queries,
        f"{prefix}/render_ms_per_query": 1000 * work.render_s / queries,
        f"{prefix}/mflop_per_query": work.kernel_mflop / queries,
        f"{prefix}/kernel_gflops": work.kernel_mflop / kernel_s / 1000,
    }
    if device != "cpu":
        step_s = fit_step_seconds(room_grid(scenes).to(device), "torch", device=device)
        figures["bench/scene_model/fit_step_ms"] = 1000 * step_s
        return figures
    figures[f"{prefix}/machine_gflops"] = machine_gflops()
    figures[f"{prefix}/roofline_fraction"] = (
        figures[f"{prefix}/kernel_gflops"] / figures[f"{prefix}/machine_gflops"]
    )
    few = slice(0, 16)
    compiled, tensor = (
        _seconds(
            lambda engine=engine: RenderCompareRefiner.configured(model, engine=engine)(
                images[few], intrinsics[few], start[few], scene_ids[few]
            )
        )
        for engine in ("numba", "torch")
    )
    figures[f"{prefix}/compiled_engine_speedup"] = tensor / compiled
    grid = model.grids[0]
    rays = torch.randn(20_000, 3)
    origins = torch.zeros(20_000, 3) + torch.tensor([0.0, 0.0, 1.4])
    with torch.no_grad():
        grid.composite(origins[:10], rays[:10], 48, 0.05, False, "numba")
        fast, slow = (
            _seconds(lambda e=e: grid.composite(origins, rays, 48, 0.05, False, e))
            for e in ("numba", "torch")
        )
    figures[f"{prefix}/compiled_render_speedup"] = slow / fast
    compiled_step, tensor_step = (
        fit_step_seconds(room_grid(scenes), e) for e in ("numba", "torch")
    )
    figures["bench/scene_model/fit_step_ms"] = 1000 * compiled_step
    figures["bench/scene_model/compiled_fit_step_speedup"] = tensor_step / compiled_step
    figures["bench/deploy/render_compare/scene_model_bytes"] = sum(
        p.numel() * p.element_size() for p in model.parameters()
    )
    return figures


DEMO_HARD_SEARCH = {"levels": 2, "reference_size": 32, "rounds": 8, "candidates": 24}
"""``experiment=demo_hard``'s wider search (conf/experiment/demo_hard.yaml), with its
``hypotheses: 8``."""


def bench_other_starts(
    queries: int = 100, train_views: int = 400, match_width: int = 256
) -> dict[str, float]:
    """Per image at ``experiment=demo_hard``'s refiner settings (64-px queries, the wider
    search), side by side on the same queries: the refinement from the APR's start alone,
    with the other starts of the stages demo_hard tries (4 train views nearest by descriptor,
    4 nearest the start, a round of 4 nearest the best pose), and with keypoint
    correspondences against a
    ``match_width``-px rendering too, and that stage with only the 2 other starts a short
    search scores highest refined in full (``screened``; its rendering at half the width:
    ``screened_half_render``): ms per query (the train views' descriptors and keypoints made
    once before, as a run makes them once)."""
    from pae.render_compare import Calibration, Queries, refine
    from pae.render_compare.correspondences import MatchQueries, MatchSettings, TrainImages

    model = room_grid(2)
    settings = DEMO_HARD_SEARCH | {"hypotheses": 8}
    images, intrinsics, start, scenes = bench_queries(queries, 2, 64, seed=0)
    large, large_k, _, _ = bench_queries(queries, 2, match_width, seed=0)
    views, views_k, view_poses, view_scenes = bench_queries(train_views, 2, match_width, seed=1)
    train = TrainImages((views * 255).to(torch.uint8), views_k, view_poses, view_scenes)
    every = Queries(images, intrinsics, scenes, matching=MatchQueries(large, large_k, train))
    few_matching = MatchQueries(large[:2], large_k[:2], train)
    few = Queries(images[:2], intrinsics[:2], scenes[:2], matching=few_matching)
    stages = {
        "alone": MatchSettings(),
        "other_starts": MatchSettings(
            width=match_width, start_views=4, near_start_views=4, near_best_rounds=1
        ),
        "keypoints": MatchSettings(
            width=match_width, start_views=4, near_start_views=4, near_best_rounds=1,
            render_width=match_width, min_inliers=10, iterations=1,
        ),
    }  # fmt: skip
    stages["screened"] = dataclasses.replace(stages["keypoints"], screen_keep=2)
    stages["screened_half_render"] = dataclasses.replace(
        stages["screened"], render_width=match_width // 2
    )
    figures = {}
    for name, match in stages.items():
        calibration = Calibration(match=match)
        refine(model, few, start[:2], calibration, settings=settings)
        seconds = _seconds(lambda c=calibration: refine(model, every, start, c, settings=settings))
        figures[f"bench/render_compare_per_image/{name}_ms_per_query"] = 1000 * seconds / queries
    alone = figures["bench/render_compare_per_image/alone_ms_per_query"]
    for name in list(stages)[1:]:
        key = f"bench/render_compare_per_image/{name}_ms_per_query"
        figures[f"bench/render_compare_per_image/{name}_cost_ratio"] = figures[key] / alone
    return figures
