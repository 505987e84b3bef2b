"""The interface every teacher implements, so students, refinement and RPR work with any teacher."""

from __future__ import annotations

from typing import NamedTuple

import torch
from omegaconf import DictConfig
from torch import Tensor, nn

from pae.core.checks import integer, present
from pae.core.geometry import normalize_pose


class Latents(NamedTuple):
    """Latent pose codes of a batch.

    x: [B, d] position latent; q: [B, d] orientation latent;
    scene_logits: [B, n_scenes] for multi-scene teachers, else None.
    """

    x: Tensor
    q: Tensor
    scene_logits: Tensor | None = None

    def joint(self) -> Tensor:
        """[B, 2d] concatenation [x, q], the vector refinement matches."""
        return torch.cat([self.x, self.q], dim=-1)


class TeacherEstimate(NamedTuple):
    """A regressor's answer for a batch: pose [B, 7] as regressed, the same with a unit
    quaternion, its latents, and the scene index [B] it assigns (its classifier's argmax, or
    the given scene for single-scene regressors)."""

    raw_pose: Tensor
    pose: Tensor
    latents: Latents
    scene: Tensor


class PoseRegressor(nn.Module):
    """An APR split into encoders (image -> latents) and heads (latents -> pose)."""

    latent_dim: int

    @classmethod
    def check_config(cls, cfg: DictConfig, key: str) -> None:
        """The latent size its signature cannot bound: an integer >= 1."""
        if present(cfg, f"{key}.latent_dim"):
            integer(cfg, f"{key}.latent_dim", 1)

    def encode(self, images: Tensor, scene: Tensor | None = None) -> Latents:
        """images [B, 3, H, W] normalised -> Latents with x, q of [B, latent_dim]."""
        raise NotImplementedError

    def regress(self, latents: Latents) -> Tensor:
        """Latents -> pose [B, 7] = x, y, z (m), qw, qx, qy, qz (not normalised)."""
        raise NotImplementedError

    def forward(self, images: Tensor, scene: Tensor | None = None) -> tuple[Tensor, Latents]:
        """images -> (pose [B, 7], latents)."""
        latents = self.encode(images, scene)
        return self.regress(latents), latents

    def estimate(self, images: Tensor, scene: Tensor) -> TeacherEstimate:
        """images [B, 3, H, W], scene [B] (used only when there is no scene classifier)."""
        raw_pose, latents = self(images)
        logits = latents.scene_logits
        scene = scene if logits is None else logits.argmax(-1)
        return TeacherEstimate(raw_pose, normalize_pose(raw_pose), latents, scene)

    def scene_poses(self, images: Tensor) -> Tensor | None:
        """images [B, 3, H, W] -> the pose [B, S, 7] (unit quaternions) it regresses for each
        of its S scenes, for teachers that classify the scene; None for the others."""
        return None

    def scene_latents(self, images: Tensor) -> Tensor | None:
        """images [B, 3, H, W] -> its latents [B, S, 2d] ([z_x, z_q]) for each of its S scenes,
        for teachers that classify the scene; None for the others."""
        return None
