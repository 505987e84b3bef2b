"""Siamese relative pose regressor (paper §3.4): two images -> the query's pose relative to
the reference."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from pae.models.backbones import Backbone


class SiameseRPR(nn.Module):
    """Shared backbone on query and reference [B, 3, H, W]; concatenated features
    [B, 2C] -> FC (ReLU) to d -> heads: translation [B, 3] (m, world frame, query − reference)
    and relative rotation [B, 4] (not normalised)."""

    def __init__(self, backbone: Backbone, latent_dim: int = 256, dropout: float = 0.1) -> None:
        super().__init__()
        self.backbone = backbone
        self.encoder = nn.Sequential(nn.Linear(2 * backbone.out_dim, latent_dim), nn.ReLU())
        self.dropout = nn.Dropout(dropout)
        self.head_x = nn.Linear(latent_dim, 3)
        self.head_q = nn.Linear(latent_dim, 4)

    def forward(self, query: Tensor, reference: Tensor) -> Tensor:
        """-> relative pose [B, 7]: translation (m) and quaternion."""
        features = self.backbone(torch.cat([query, reference]))
        pair = torch.cat(features.chunk(2), dim=-1)
        latent = self.dropout(self.encoder(pair))
        return torch.cat([self.head_x(latent), self.head_q(latent)], dim=-1)
