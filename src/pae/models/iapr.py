"""Iterative APR (PAE-based relative pose regression): the query image against the PAE
encoding of the current pose estimate -> the correction that moves the estimate to the
query's pose. It needs no stored images or poses: the reference is *encoded*, not looked up."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from pae.models.backbones import Backbone


class IterativeAPR(nn.Module):
    """image [B, 3, H, W] + PAE encoding [B, 2d] of a pose estimate -> relative pose [B, 7]
    (world-frame translation query − estimate in m, rotation conj(q_est)·q_query, not
    normalised), the convention of `pae.core.geometry.relative_pose`.

    Image features (its own backbone) and the encoding are each projected to `hidden`
    (ReLU), concatenated and fused by an MLP; the heads start at the identity correction
    (zero translation, unit rotation), so an untrained model leaves the estimate unchanged.
    """

    def __init__(
        self,
        backbone: Backbone,
        latent_dim: int = 256,
        hidden: int = 256,
        dropout: float = 0.1,
    ) -> None:
        super().__init__()
        self.backbone = backbone
        self.latent_dim = latent_dim
        self.image_encoder = nn.Sequential(nn.Linear(backbone.out_dim, hidden), nn.ReLU())
        self.pose_encoder = nn.Sequential(nn.Linear(2 * latent_dim, hidden), nn.ReLU())
        self.fuse = nn.Sequential(
            nn.Linear(2 * hidden, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU()
        )
        self.dropout = nn.Dropout(dropout)
        self.head_x = nn.Linear(hidden, 3)
        self.head_q = nn.Linear(hidden, 4)
        for head in (self.head_x, self.head_q):
            nn.init.zeros_(head.weight)
            nn.init.zeros_(head.bias)
        with torch.no_grad():
            self.head_q.bias[0] = 1.0

    def forward(self, images: Tensor, encoding: Tensor) -> Tensor:
        """images (network input), encoding [B, 2d] = [ẑ_x, ẑ_q] -> relative pose [B, 7]."""
        features = torch.cat(
            [self.image_encoder(self.backbone(images)), self.pose_encoder(encoding)], dim=-1
        )
        latent = self.dropout(self.fuse(features))
        return torch.cat([self.head_x(latent), self.head_q(latent)], dim=-1)
