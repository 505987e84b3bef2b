"""PoseNet-style APR: backbone, two FC encoders to z_x / z_q, dropout, regression heads."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from pae.models.backbones import Backbone
from pae.models.base import Latents, PoseRegressor


class PoseNet(PoseRegressor):
    """image [B, 3, H, W] -> z_x, z_q [B, d] -> x [B, 3] (m), q [B, 4].

    With n_scenes > 1 a linear scene classifier on the backbone features fills
    `Latents.scene_logits` (a multi-scene PoseNet that tells its scene, like MS-Transformer).
    """

    def __init__(
        self, backbone: Backbone, latent_dim: int = 256, dropout: float = 0.1, n_scenes: int = 1
    ) -> None:
        super().__init__()
        self.backbone = backbone
        self.latent_dim = latent_dim
        self.n_scenes = n_scenes
        self.encoder_x = nn.Sequential(nn.Linear(backbone.out_dim, latent_dim), nn.ReLU())
        self.encoder_q = nn.Sequential(nn.Linear(backbone.out_dim, latent_dim), nn.ReLU())
        self.scene_head = nn.Linear(backbone.out_dim, n_scenes) if n_scenes > 1 else None
        self.dropout = nn.Dropout(dropout)
        self.head_x = nn.Linear(latent_dim, 3)
        self.head_q = nn.Linear(latent_dim, 4)

    def encode(self, images: Tensor, scene: Tensor | None = None) -> Latents:
        features = self.backbone(images)
        logits = self.scene_head(features) if self.scene_head is not None else None
        return Latents(self.encoder_x(features), self.encoder_q(features), logits)

    def regress(self, latents: Latents) -> Tensor:
        x = self.head_x(self.dropout(latents.x))
        q = self.head_q(self.dropout(latents.q))
        return torch.cat([x, q], dim=-1)
