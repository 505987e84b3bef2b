"""The camera pose auto-encoder: pose (+ scene index) -> latents matching a teacher APR's."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from omegaconf import DictConfig
from torch import Tensor, nn

from pae.core.checks import check_record
from pae.models.base import Latents
from pae.models.settings import PAE_DEFAULTS, PoseAutoEncoderSettings


class FourierFeatures(nn.Module):
    """gamma(p) = (p, sin(2^0 p), cos(2^0 p), ..., sin(2^{L-1} p), cos(2^{L-1} p)).

    [..., d0] -> [..., d0 * (2L + 1)] with the input included, [..., d0 * 2L] without;
    L = 0 returns the raw input. Order: the input p₁…p_d0, then band by band, coordinate by
    coordinate, sin then cos: sin(2⁰p₁), cos(2⁰p₁), sin(2⁰p₂), …, cos(2^{L−1}p_d0). (The
    public code orders each band as sin of all coordinates, then cos of all; see
    ``pae.models.convert.fourier_permutation``.)
    """

    def __init__(self, L: int = 6, include_input: bool = True) -> None:
        super().__init__()
        if L < 0:
            raise ValueError(f"FourierFeatures: L must be >= 0, got {L}")
        if L == 0 and not include_input:
            raise ValueError("FourierFeatures: L=0 needs include_input=True")
        self.L = L
        self.include_input = include_input
        self.register_buffer("frequencies", 2.0 ** torch.arange(L), persistent=False)

    def out_dim(self, in_dim: int) -> int:
        return in_dim * (2 * self.L + int(self.include_input))

    def forward(self, p: Tensor) -> Tensor:
        parts = [p] if self.include_input else []
        if self.L:
            angles = p.unsqueeze(-1) * self.frequencies  # [..., d0, L]
            sin_cos = torch.stack([angles.sin(), angles.cos()], dim=-1)  # [..., d0, L, 2]
            parts.append(sin_cos.transpose(-3, -2).flatten(-3))  # ordered by band, then sin/cos
        return torch.cat(parts, dim=-1)


def mlp(in_dim: int, hidden: Sequence[int], out_dim: int) -> nn.Sequential:
    """Linear+ReLU layers through `hidden`, then a linear output layer."""
    layers: list[nn.Module] = []
    for width in hidden:
        layers += [nn.Linear(in_dim, width), nn.ReLU()]
        in_dim = width
    layers.append(nn.Linear(in_dim, out_dim))
    return nn.Sequential(*layers)


class PoseAutoEncoder(nn.Module):
    """Two MLP branches: x [B, 3] -> z_x [B, d] and q [B, 4] -> z_q [B, d].

    With n_scenes > 1 the scene index [B] is Fourier-encoded with `scene_L` bands (whatever
    `L` is, as the public multi-scene encoder does) and concatenated to each branch's input.
    """

    def __init__(
        self,
        latent_dim: int = PAE_DEFAULTS.latent_dim,
        hidden: Sequence[int] = tuple(PAE_DEFAULTS.hidden),
        L: int = PAE_DEFAULTS.L,
        n_scenes: int = 1,
        scene_L: int = PAE_DEFAULTS.scene_L,
    ) -> None:
        super().__init__()
        self.latent_dim = latent_dim
        self.n_scenes = n_scenes
        self.fourier = FourierFeatures(L)
        self.scene_fourier = FourierFeatures(scene_L)
        scene_dim = self.scene_fourier.out_dim(1) if n_scenes > 1 else 0
        self.branch_x = mlp(self.fourier.out_dim(3) + scene_dim, hidden, latent_dim)
        self.branch_q = mlp(self.fourier.out_dim(4) + scene_dim, hidden, latent_dim)

    @classmethod
    def check_config(cls, cfg: DictConfig, key: str) -> None:
        """The ranges of its settings (:class:`PoseAutoEncoderSettings`) in the config at
        ``key``, a ConfigError naming the key."""
        check_record(cfg, key, PoseAutoEncoderSettings)

    def forward(self, poses: Tensor, scene: Tensor | None = None) -> Latents:
        """poses [B, 7] (m, unit quaternion), scene [B] long -> Latents(z_x, z_q) [B, d]."""
        enc_x = self.fourier(poses[..., :3])
        enc_q = self.fourier(poses[..., 3:])
        if self.n_scenes > 1:
            if scene is None:
                raise ValueError("a multi-scene PoseAutoEncoder needs the scene index")
            enc_s = self.scene_fourier(scene.to(poses.dtype).unsqueeze(-1))
            enc_x = torch.cat([enc_x, enc_s], dim=-1)
            enc_q = torch.cat([enc_q, enc_s], dim=-1)
        return Latents(self.branch_x(enc_x), self.branch_q(enc_q))
