"""Siamese relative pose regressor (paper §3.4): two images -> the query's pose relative to
the reference."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from pae.models.backbones import Backbone


class SiameseRPR(nn.Module):
    """Shared backbone on query and reference [B, 3, H, W]; concatenated features
    [B, 2C] -> FC (ReLU) to d -> heads: translation [B, 3] (m, world frame, query − reference)
    and relative rotation [B, 4] (not normalised). One FC layer serves both heads; with
    separate_encoders each head has its own (the paper's PoseNet-like design)."""

    def __init__(
        self,
        backbone: Backbone,
        latent_dim: int = 256,
        dropout: float = 0.1,
        separate_encoders: bool = False,
    ) -> None:
        super().__init__()
        self.backbone = backbone
        self.encoder = nn.Sequential(nn.Linear(2 * backbone.out_dim, latent_dim), nn.ReLU())
        self.encoder_q = (
            nn.Sequential(nn.Linear(2 * backbone.out_dim, latent_dim), nn.ReLU())
            if separate_encoders
            else None
        )
        self.dropout = nn.Dropout(dropout)
        self.head_x = nn.Linear(latent_dim, 3)
        self.head_q = nn.Linear(latent_dim, 4)

    def forward(self, query: Tensor, reference: Tensor) -> Tensor:
        """-> relative pose [B, 7]: translation (m) and quaternion."""
        features = self.backbone(torch.cat([query, reference]))
        pair = torch.cat(features.chunk(2), dim=-1)
        latent_x = self.dropout(self.encoder(pair))
        latent_q = latent_x if self.encoder_q is None else self.dropout(self.encoder_q(pair))
        return torch.cat([self.head_x(latent_x), self.head_q(latent_q)], dim=-1)
