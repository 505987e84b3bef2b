"""Poses moved around given poses: by given steps (``perturb``, the candidates of
render-and-compare), drawn as training starts and references for the relative regressors
(``perturb_poses``) and for the random-guess check of refinement (``perturb_positions``)."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from pae.core.geometry import (
    canonicalize_quaternion,
    normalize_quaternion,
    quaternion_multiply,
    rotation_vector_to_quaternion,
)


def perturb(poses: Tensor, steps: Tensor) -> Tensor:
    """Poses [..., 7] moved by steps [..., 6]: a world-frame translation (m) and a rotation
    vector (rad) in the camera frame (``R' = R · exp(ω)``)."""
    position = poses[..., :3] + steps[..., :3]
    q = quaternion_multiply(poses[..., 3:], rotation_vector_to_quaternion(steps[..., 3:]))
    return torch.cat([position, canonicalize_quaternion(normalize_quaternion(q))], -1)


def perturb_poses(
    poses: Tensor,
    position_m: float | Tensor,
    orientation_deg: float | Tensor,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Starting poses around poses [B, 7] (unit q): each moved by a distance uniform in
    [0, 2·position_m] (median position_m) in a uniformly random direction, and rotated by an
    angle uniform in [0, 2·orientation_deg] about a uniformly random axis -> [B, 7], qw >= 0.
    ``position_m`` and ``orientation_deg``: one for all, or one per pose [B]."""
    b, device, dtype = poses.shape[0], poses.device, poses.dtype

    def directions() -> Tensor:
        v = torch.randn(b, 3, generator=generator, dtype=dtype).to(device)
        return v / v.norm(dim=-1, keepdim=True).clamp_min(1e-12)

    def amounts(scale: float | Tensor) -> Tensor:
        if isinstance(scale, Tensor):
            scale = scale.to(dtype).reshape(-1, 1).cpu()
        return (2 * scale * torch.rand(b, 1, generator=generator, dtype=dtype)).to(device)

    translation = amounts(position_m) * directions()
    turn = amounts(orientation_deg) * (math.pi / 180.0) * directions()
    return perturb(poses, torch.cat([translation, turn], dim=-1))


def perturb_positions(
    poses: Tensor, sigma_m: float, generator: torch.Generator | None = None
) -> Tensor:
    """poses [B, 7] with N(0, sigma_m²) noise (m) added to each position coordinate.

    The orientation is kept: the random-guess check of the paper's supplementary (§1.4).
    """
    draw_device = generator.device if generator is not None else poses.device
    noise = torch.randn(
        poses.shape[0], 3, generator=generator, device=draw_device, dtype=poses.dtype
    )
    perturbed = poses.clone()
    perturbed[:, :3] += sigma_m * noise.to(poses.device)
    return perturbed
