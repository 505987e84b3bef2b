"""The camera's geometry in ``pae.core.camera``: intrinsics through a resize, and rays."""

from __future__ import annotations

import torch

from pae.core.camera import Intrinsics, camera_rays, scale_intrinsics
from pae.core.geometry import normalize_quaternion
from pae.scene_model.rays import RayBatches


def test_a_resized_camera_matches_its_scaled_intrinsic_vector_exactly() -> None:
    camera = Intrinsics(fx=1171.3, fy=1169.9, cx=959.7, cy=539.2, width=1920, height=1080)
    for width, height in ((455, 256), (256, 144), (1920, 1080), (641, 359)):
        resized = camera.resized(width, height)
        vector = torch.tensor([camera.vector()], dtype=torch.float64)
        scaled = scale_intrinsics(vector, width / camera.width, height / camera.height)
        assert scaled[0].tolist() == resized.vector()
        assert (resized.width, resized.height) == (width, height)


def test_training_rays_are_the_camera_rays_of_their_pixels() -> None:
    n, h, w = 2, 4, 5
    generator = torch.Generator().manual_seed(3)
    poses = torch.cat(
        [
            torch.randn(n, 3, generator=generator),
            normalize_quaternion(torch.randn(n, 4, generator=generator)),
        ],
        -1,
    )
    intrinsics = torch.tensor([[6.0, 5.0, 2.2, 1.4], [4.0, 7.0, 1.9, 1.6]])
    pixel = torch.arange(n * h * w, dtype=torch.uint8).view(n, 1, h, w)  # the ray's pixel index
    images = pixel.expand(-1, 3, -1, -1).contiguous()
    ids = torch.arange(n)
    batch = RayBatches(images, poses, intrinsics, ids, ids, rays_per_batch=64, batches=1)[0]
    origins, directions = camera_rays(poses, intrinsics, w, h)
    index = (batch["rgb"][:, 0] * 255).round().long()
    row, within = index // (h * w), index % (h * w)
    assert torch.allclose(batch["origins"], origins[row, within])
    assert torch.allclose(batch["directions"], directions[row, within], atol=1e-6)
    column, line = (batch["pixels"] * torch.tensor([w - 1, h - 1])).round().long().unbind(-1)
    assert torch.equal(line * w + column, within)  # each ray's pixel, scaled to [0, 1]
    assert batch["pixels"].min() >= 0 and batch["pixels"].max() <= 1
