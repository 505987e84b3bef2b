"""Pose losses: the learned-uncertainty pose loss (Kendall & Cipolla 2017) and latent losses."""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor, nn


class PoseLossTerms(NamedTuple):
    """total (scalar) and its parts: position L_x (m) and orientation L_q, both batch means."""

    total: Tensor
    position: Tensor
    orientation: Tensor


class LearnedPoseLoss(nn.Module):
    """L_p = L_x·exp(−s_x) + s_x + L_q·exp(−s_q) + s_q.

    L_x = ‖x0 − x‖₂, L_q = ‖q0 − q/‖q‖‖₂, averaged over the batch. With learnable=False
    s_x, s_q stay at their initial values (a fixed-weight loss).
    """

    def __init__(self, s_x: float = -3.0, s_q: float = -6.5, learnable: bool = True) -> None:
        super().__init__()
        self.s_x = nn.Parameter(torch.tensor(float(s_x)), requires_grad=learnable)
        self.s_q = nn.Parameter(torch.tensor(float(s_q)), requires_grad=learnable)

    def forward(self, pred: Tensor, target: Tensor) -> PoseLossTerms:
        """pred [B, 7] (q not normalised), target [B, 7] -> PoseLossTerms."""
        position = torch.linalg.vector_norm(target[:, :3] - pred[:, :3], dim=-1).mean()
        q = nn.functional.normalize(pred[:, 3:], dim=-1)
        orientation = torch.linalg.vector_norm(target[:, 3:] - q, dim=-1).mean()
        total = (
            position * torch.exp(-self.s_x)
            + self.s_x
            + orientation * torch.exp(-self.s_q)
            + self.s_q
        )
        return PoseLossTerms(total, position, orientation)


LATENT_LOSSES = ("l2", "mse")


def latent_distance(pred: Tensor, target: Tensor, kind: str = "l2") -> Tensor:
    """Batch-mean latent loss between [B, d] codes: "l2" = ‖·‖₂ (paper), "mse" (public code)."""
    if kind == "l2":
        return torch.linalg.vector_norm(pred - target, dim=-1).mean()
    if kind == "mse":
        return nn.functional.mse_loss(pred, target)
    raise ValueError(f"unknown latent loss {kind!r}; choose one of {LATENT_LOSSES}")
