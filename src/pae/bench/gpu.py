"""The GPU check (experiments/bench/gpu.sh): on a CUDA device, the figures of paper Table 5's
GPU column and the torch engine's render-and-compare answers checked against the CPU's.

``python -m pae.bench.gpu --out FILE`` writes one JSON object:

- ``bench/render_compare/...`` on the GPU (``pae-bench --only render_compare --device
  cuda``: the tensor engine) and, under ``cpu/``, the same benchmark on this machine's CPU
  (the compiled engine);
- ``bench/gpu/pae_latency_ms``: one PAE forward pass, batch 1 (Table 5: 1.22 ms, GTX 1080);
- ``bench/gpu/refine_latency_ms`` and ``refine_ms_per_query``: the kNN refinement's MLP weight
  model (k=3, 3 steps, the tensor path) for one query and per query of a batch of 500
  (Table 5: 7.51 ms);
- ``bench/gpu/engines/...``: ``answers_agree`` on 64 queries rendered in the render_compare
  benchmark's room (``engine_answers``), and ``bench/gpu/engines/agree`` (1 or 0);
- ``bench/gpu/stages/...``: where the torch engine's arithmetic on the GPU departs from its
  own on the CPU (``stage_differences``).

Without a CUDA device it prints ``no CUDA device: skipped`` and exits 0; it exits 1 where the
engines disagree beyond the tolerances.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch
from torch import Tensor

from pae.core.atomic import check_writable_file, write_json_atomic
from pae.render_compare.gate import RenderCompareResult
from pae.scene_model.voxel_grid import VoxelGridSceneModel

SCORE_MEDIAN_ATOL = 1e-3
"""How far the two engines' scores of the start poses may differ at the median (ZNCC, in
[-1, 1]): their arithmetic."""
SCORE_MAX_ATOL = 1e-2
"""How far they may differ at most: the trimmed ZNCC drops points by a threshold and a query
whose engines refine to different poses is scored against another reference rendering, so
single queries differ by more than the arithmetic (0.004 on an H200); TF32 convolutions
moved them by 0.08."""
SAME_POSE_M = 0.005
"""Refined positions closer than this (m) count as the same answer."""
SAME_POSE_DEG = 0.1
"""Refined orientations closer than this (deg) count as the same answer."""
MIN_SAME_SHARE = 0.9
"""The share of queries whose refined poses must be the same answer: the search keeps the
best of its candidates, and where two score within rounding of each other the engines may
keep different ones."""


def answers_agree(compiled: RenderCompareResult, tensor: RenderCompareResult) -> dict[str, float]:
    """Two engines' answers on the same queries (poses [B, 7], scores [B]): the largest
    difference of the start poses' scores (``initial_score_max_diff``) and of the refined
    poses' scores, the median and largest refined position (m) and orientation (deg)
    differences, the share of queries refined to the same pose (``same_pose_share``) and
    ``agree``: 1 where the start scores are within SCORE_MEDIAN_ATOL at the median and
    SCORE_MAX_ATOL at most and that share is at least MIN_SAME_SHARE, else 0."""
    from pae.core.geometry import pose_errors

    pos_m, rot_deg = pose_errors(tensor.poses.double(), compiled.poses.double())
    start_diffs = (tensor.initial_score - compiled.initial_score).abs()
    start_median, start_max = start_diffs.median().item(), start_diffs.max().item()
    same = ((pos_m <= SAME_POSE_M) & (rot_deg <= SAME_POSE_DEG)).double().mean().item()
    prefix = "bench/gpu/engines"
    return {
        f"{prefix}/queries": float(len(pos_m)),
        f"{prefix}/initial_score_median_diff": start_median,
        f"{prefix}/initial_score_max_diff": start_max,
        f"{prefix}/score_max_diff": (tensor.score - compiled.score).abs().max().item(),
        f"{prefix}/position_median_diff_m": pos_m.median().item(),
        f"{prefix}/position_max_diff_m": pos_m.max().item(),
        f"{prefix}/rotation_median_diff_deg": rot_deg.median().item(),
        f"{prefix}/rotation_max_diff_deg": rot_deg.max().item(),
        f"{prefix}/same_pose_share": same,
        f"{prefix}/agree": float(
            start_median <= SCORE_MEDIAN_ATOL
            and start_max <= SCORE_MAX_ATOL
            and same >= MIN_SAME_SHARE
        ),
    }


def engine_queries(
    queries: int, scenes: int = 2, crop: int = 56
) -> tuple[VoxelGridSceneModel, tuple[Tensor, Tensor, Tensor, Tensor]]:
    """The render_compare benchmark's room (pae.bench.render_compare) and ``queries`` queries
    in it: images [B, 3, crop, crop] the room's grid renders at the benchmark's start poses,
    their intrinsics [B, 4], starts [B, 7] 0.15 m and 3 degrees (std) away from those
    poses, scene ids [B]: a score that peaks at the truth, so that the answer does not hang
    on rounding between candidates that score alike."""
    from pae.bench.render_compare import bench_queries, room_grid
    from pae.core.pose_sampling import perturb

    model = room_grid(scenes)
    _, intrinsics, truth, scene_ids = bench_queries(queries, scenes, crop, seed=0)
    with torch.no_grad():
        images = model.render(truth, scene_ids, intrinsics, crop, crop).rgb.clamp(0, 1)
    generator = torch.Generator().manual_seed(1)
    steps = torch.randn(queries, 6, generator=generator) * torch.tensor(
        [0.15, 0.15, 0.15, 0.05, 0.05, 0.05]
    )
    return model, (images, intrinsics, perturb(truth, steps), scene_ids)


def engine_answers(
    queries: int = 64, device: str = "cuda"
) -> tuple[RenderCompareResult, RenderCompareResult]:
    """The refiner at its default settings on ``engine_queries``: its answers with
    ``engine="numba"`` on the CPU and with ``engine="torch"`` on ``device`` (brought back to
    the CPU)."""
    from pae.render_compare.refiner import RenderCompareRefiner

    model, inputs = engine_queries(queries)
    compiled = RenderCompareRefiner.configured(model, engine="numba")(*inputs)
    tensor = RenderCompareRefiner.configured(model.to(device), engine="torch")(
        *(t.to(device) for t in inputs)
    )
    return compiled, RenderCompareResult(*(t.cpu() for t in tensor))


def stage_differences(queries: int = 64, device: str = "cuda") -> dict[str, float]:
    """Where the torch engine's arithmetic on ``device`` departs from its own on the CPU, on
    ``engine_queries``: the largest difference of the band-passed query images the score
    compares against (per pyramid level, coarse to fine) and of the reference renderings at
    the start poses (grey level, and depth in m where both are opaque)."""
    from pae.render_compare.refiner import RenderCompareRefiner

    model, (images, intrinsics, starts, scenes) = engine_queries(queries)
    refiner = RenderCompareRefiner.configured(model, engine="torch")
    here = refiner.pyramid(images, intrinsics, scenes)
    figures = {}
    prefix = "bench/gpu/stages"
    with torch.no_grad():
        model.to(device)
        there = refiner.pyramid(images.to(device), intrinsics.to(device), scenes.to(device))
        for index, (a, b) in enumerate(zip(here, there, strict=True)):
            figures[f"{prefix}/target_level{index}_max_diff"] = (
                (a.target - b.target.cpu()).abs().max().item()
            )
        width = refiner.resolution
        on_device = refiner.reference(starts.to(device), there[-1], width, 1.0)
        model.to("cpu")
        on_cpu = refiner.reference(starts, here[-1], width, 1.0)
    both = (on_cpu.valid * on_device.valid.cpu()).bool()
    depth_cpu = (on_cpu.points - starts[:, None, :3]).norm(dim=-1)
    depth_device = (on_device.points.cpu() - starts[:, None, :3]).norm(dim=-1)
    figures[f"{prefix}/reference_grey_max_diff"] = (
        (on_cpu.image - on_device.image.cpu()).abs().max().item()
    )
    figures[f"{prefix}/reference_depth_max_diff_m"] = (
        (depth_cpu - depth_device)[both].abs().max().item()
    )
    return figures


def _milliseconds(run: Callable[[], object], device: str, repeats: int) -> float:
    """Milliseconds per call of ``run``, after 5 warm-up calls, the device synchronised."""
    for _ in range(5):
        run()
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    start = time.perf_counter()
    for _ in range(repeats):
        run()
    if device.startswith("cuda"):
        torch.cuda.synchronize()
    return 1000 * (time.perf_counter() - start) / repeats


def pae_and_refinement_times(device: str = "cuda", queries: int = 500) -> dict[str, float]:
    """Table 5's two GPU figures on ``device``: the PAE forward pass for one pose, and the
    MLP weight model's refinement (k=3 neighbours of 512-wide latents, 3 steps, the tensor
    path) for one query and per query of ``queries`` at once."""
    from pae.models.pae import PoseAutoEncoder
    from pae.refine.weights import refine_affine

    pae = PoseAutoEncoder(n_scenes=2).eval().to(device)
    pose = torch.tensor([[0.1, 0.2, 0.3, 1.0, 0.0, 0.0, 0.0]], device=device)
    scene = torch.tensor([1], device=device)
    with torch.no_grad():
        pae_ms = _milliseconds(lambda: pae(pose, scene), device, 200)
    generator = torch.Generator().manual_seed(0)
    query = torch.randn(queries, 512, generator=generator)
    neighbours = query.unsqueeze(1) + 0.3 * torch.randn(queries, 3, 512, generator=generator)
    poses = torch.randn(queries, 3, 7, generator=generator)
    query, neighbours, poses = query.to(device), neighbours.to(device), poses.to(device)

    def refine(rows: slice) -> object:
        return refine_affine(query[rows], neighbours[rows], poses[rows], engine="torch")

    one_ms = _milliseconds(lambda: refine(slice(0, 1)), device, 20)
    batch_ms = _milliseconds(lambda: refine(slice(0, queries)), device, 3)
    return {
        "bench/gpu/pae_latency_ms": pae_ms,
        "bench/gpu/refine_latency_ms": one_ms,
        "bench/gpu/refine_ms_per_query": batch_ms / queries,
    }


def render_compare_bench(device: str) -> dict[str, float]:
    """``pae-bench --only render_compare --device DEVICE`` in a fresh process: its figures."""
    command = [sys.executable, "-m", "pae.bench", "--only", "render_compare", "--device", device]
    result = subprocess.run(command, capture_output=True, text=True)
    if result.returncode != 0:
        raise RuntimeError(f"pae-bench --device {device} failed: {result.stderr[-2000:]}")
    return json.loads(result.stdout)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pae.bench.gpu", description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("outputs/bench/gpu.json"))
    args = parser.parse_args(argv)
    if not torch.cuda.is_available():
        print("no CUDA device: skipped")
        return 0
    from pae.core.threads import configure_threads

    check_writable_file(args.out, "--out")  # before any work

    print(configure_threads().summary(), file=sys.stderr)
    figures: dict[str, float | str] = {"bench/gpu/device": torch.cuda.get_device_name()}
    figures |= render_compare_bench("cuda")
    figures |= {f"cpu/{k}": v for k, v in render_compare_bench("cpu").items()}
    figures |= pae_and_refinement_times("cuda")
    figures |= answers_agree(*engine_answers(device="cuda"))
    figures |= stage_differences(device="cuda")
    write_json_atomic(args.out, figures)
    print(json.dumps(figures, indent=2, sort_keys=True))
    if not figures["bench/gpu/engines/agree"]:
        print(f"the torch engine on the GPU disagrees with the CPU's: {args.out}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
