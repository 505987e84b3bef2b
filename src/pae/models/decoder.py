"""Image decoder: a PAE encoding -> a small RGB image (paper §3.3, "Virtual Relative Pose
Regression")."""

from __future__ import annotations

from collections.abc import Sequence

from torch import Tensor, nn

from pae.models.pae import mlp


class ImageDecoder(nn.Module):
    """MLP over [ẑ_x, ẑ_q] [B, 2d] -> image [B, 3, size, size] in [0, 1].

    Hidden widths 512, 1024, 2048 (ReLU) as in the paper (size 64), and a sigmoid output
    (not in the paper: the images lie in [0, 1]; docs/departures.md).
    """

    def __init__(
        self, latent_dim: int = 256, hidden: Sequence[int] = (512, 1024, 2048), size: int = 64
    ) -> None:
        super().__init__()
        self.latent_dim = latent_dim
        self.size = size
        self.net = mlp(2 * latent_dim, hidden, 3 * size * size)

    def forward(self, encoding: Tensor) -> Tensor:
        return self.net(encoding).sigmoid().view(-1, 3, self.size, self.size)
