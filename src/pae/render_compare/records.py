"""The records render-and-compare passes between its steps: a pyramid level of queries, a
reference rendering, its surface as a level compares it, and the hypotheses per query."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import torch
from torch import Tensor


class Level(NamedTuple):
    """One chunk of queries prepared for scoring at one pyramid level."""

    target: Tensor  # [B, C, h, w] band-passed grey query (or its feature maps)
    intrinsics: Tensor  # [B, 4] of the level's images
    scenes: Tensor  # [B]
    sigmas: tuple[float, ...]  # blur, high-pass and contrast sigma (px of this level)


class Reference(NamedTuple):
    """The scene model rendered once per query: its surface and its grey image (or RGB)."""

    points: Tensor  # [B, P, 3] world
    image: Tensor  # [B, 1, h, w] grey (RGB [B, 3, h, w] for the features score)
    valid: Tensor  # [B, P] float: the model explains that pixel
    focal: Tensor  # [B] fx of the rendering (px)


class Surface(NamedTuple):
    """A reference as one level compares it."""

    points: Tensor  # [B, P, 3] world
    values: Tensor  # [B, C, P] of the rendering at those points, filtered as the level
    valid: Tensor  # [B, P]


@dataclass
class Hypotheses:
    """K poses per query [B, K, 7], their scores [B, K] and search steps [B, K, 6]."""

    poses: Tensor
    scores: Tensor
    steps: Tensor = field(default_factory=lambda: torch.empty(0))

    def best(self) -> tuple[Tensor, Tensor]:
        """The best pose [B, 7] and its score [B]."""
        score, pick = self.scores.max(1)
        return self.poses[torch.arange(len(pick)), pick], score

    def top(self, k: int) -> Hypotheses:
        """The ``k`` best hypotheses of every query, best first."""
        k = min(k, self.scores.shape[1])
        scores, pick = self.scores.topk(k, dim=1)
        poses = self.poses.gather(1, pick[..., None].expand(-1, -1, 7))
        return Hypotheses(poses, scores)
