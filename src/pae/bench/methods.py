"""What each localisation method costs a deployment, side by side in one run: the bytes it
must keep (networks, train poses, train images) and milliseconds per query (batch 1, CPU).

The networks are the configured defaults (conf/train.yaml: small_cnn backbone, PoseNet
teacher, Fourier PAE, MLP decoder, Siamese RPR, iterative APR) with untrained weights: size
and speed do not depend on the weights. The store is the default synthetic benchmark's
(`scenes` x `train_frames` poses and images of `size` px, uint8), so the figures are
comparable with the paper's storage table (suppl.), which assumes 10 scenes of 2000 images.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import torch
from torch import Tensor, nn

from pae.data.transforms import ImageTransform
from pae.models.backbones import Backbone
from pae.models.decoder import ImageDecoder
from pae.models.iapr import IterativeAPR
from pae.models.pae import PoseAutoEncoder
from pae.models.posenet import PoseNet
from pae.models.rpr import SiameseRPR
from pae.refine.index import PoseIndex
from pae.refine.weights import refine_affine
from pae.relative.refiners import (
    ImageRefiner,
    ImageRPR,
    IterativeAPRRefiner,
    RefinedPoses,
    VirtualRPR,
)


def network_bytes(*modules: nn.Module) -> int:
    """Bytes of the parameters and buffers a deployment loads for these networks."""
    tensors = [t for m in modules for t in (*m.parameters(), *m.buffers())]
    return sum(t.numel() * t.element_size() for t in tensors)


def _ms_per_query(run: Callable[[int], object], queries: int, warmup: int = 3) -> float:
    """Mean milliseconds of run(i) over `queries` calls (after `warmup` calls)."""
    with torch.no_grad():
        for i in range(warmup):
            run(i)
        start = time.perf_counter()
        for i in range(queries):
            run(i)
    return 1000 * (time.perf_counter() - start) / queries


def bench_methods(
    scenes: int = 2,
    train_frames: int = 1600,
    size: int = 64,
    crop: int = 56,
    queries: int = 50,
    iapr_iterations: int = 3,
    seed: int = 0,
) -> dict[str, float]:
    """`bench/deploy/{method}/{networks,poses,images,total}_bytes` and `.../ms_per_query`
    for teacher, refined (affine, k=3, 3 iterations), vrpr, rpr_image and iapr_{n}."""
    generator = torch.Generator().manual_seed(seed)
    n = scenes * train_frames
    positions = 5 * torch.rand(n, 3, generator=generator)
    quaternions = nn.functional.normalize(
        torch.randn(n, 4, generator=generator) * 0.1 + torch.tensor([1.0, 0, 0, 0]), dim=-1
    )
    poses = torch.cat([positions, quaternions], dim=-1)
    scene_ids = torch.arange(n) * scenes // n
    store_images = torch.randint(0, 256, (n, 3, size, size), dtype=torch.uint8, generator=generator)
    queries_images = torch.randint(
        0, 256, (queries + 3, 3, size, size), dtype=torch.uint8, generator=generator
    )

    def backbone() -> Backbone:
        return Backbone("small_cnn", pool="flatten", spatial=2)

    teacher = PoseNet(backbone(), n_scenes=scenes).eval()
    pae = PoseAutoEncoder(n_scenes=scenes).eval()
    decoder = ImageDecoder().eval()
    rpr = SiameseRPR(backbone()).eval()
    iapr = IterativeAPR(backbone()).eval()
    index = PoseIndex(poses, scene_ids)
    transform = ImageTransform(crop)

    def image(i: int) -> Tensor:
        return transform(queries_images[i : i + 1])

    def teacher_only(i: int):
        return teacher.estimate(image(i), torch.zeros(1, dtype=torch.long))

    def refined(i: int) -> Tensor:
        answer = teacher_only(i)
        rows = index.query(answer.pose, answer.scene, 3)[0][0]
        neighbours = pae(poses[rows], scene_ids[rows]).joint()
        with torch.enable_grad():
            fit = refine_affine(answer.latents.joint(), neighbours[None], poses[rows][None])
        return fit.weights

    def with_method(method: ImageRefiner) -> Callable[[int], RefinedPoses]:
        def refine(i: int) -> RefinedPoses:
            query = image(i)
            return method(query, teacher.estimate(query, torch.zeros(1, dtype=torch.long)))

        return refine

    def train_images(rows: Tensor, device: torch.device | str) -> Tensor:
        return transform(store_images[rows.cpu()]).to(device)

    vrpr = with_method(VirtualRPR(rpr, pae, decoder, index))
    rpr_image = with_method(ImageRPR(rpr, index, train_images))
    iapr_n = with_method(IterativeAPRRefiner(iapr, pae, iapr_iterations))

    pose_bytes = index.memory_bytes
    image_bytes = store_images.numel() * store_images.element_size()
    methods = {
        "teacher": (teacher_only, (teacher,), 0, 0),
        "refined": (refined, (teacher, pae), pose_bytes, 0),
        "vrpr": (vrpr, (teacher, pae, decoder, rpr), pose_bytes, 0),
        "rpr_image": (rpr_image, (teacher, rpr), pose_bytes, image_bytes),
        f"iapr_{iapr_iterations}": (iapr_n, (teacher, pae, iapr), 0, 0),
    }
    figures: dict[str, float] = {}
    for name, (run, networks, kept_poses, kept_images) in methods.items():
        key = f"bench/deploy/{name}"
        weights = network_bytes(*networks)
        figures[f"{key}/networks_bytes"] = weights
        figures[f"{key}/poses_bytes"] = kept_poses
        figures[f"{key}/images_bytes"] = kept_images
        figures[f"{key}/total_bytes"] = weights + kept_poses + kept_images
        figures[f"{key}/ms_per_query"] = _ms_per_query(run, queries)
    # the paper's storage table's setting: 10 scenes x 2000 images, here as 64 px uint8
    # images (the benchmark's) and as 256 px ones (the paper's pre-processing)
    figures["bench/deploy/paper_setting/images_64px_bytes"] = 10 * 2000 * 3 * 64 * 64
    figures["bench/deploy/paper_setting/images_256px_bytes"] = 10 * 2000 * 3 * 256 * 256
    figures["bench/deploy/paper_setting/poses_bytes"] = 10 * 2000 * 7 * 4
    return figures
