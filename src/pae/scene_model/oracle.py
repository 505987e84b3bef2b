"""The synthetic benchmark's own renderer as a scene model: the render-and-compare bound."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from pae.core.camera import camera_rays
from pae.core.errors import ConfigError
from pae.scene_model.base import SceneModel, SceneModelInputs, SceneRendering
from pae.synthetic import SyntheticScene, shade_rays


class OracleSceneModel(SceneModel):
    """Exact renderings (linear colour, no camera response) and depths of the true scenes,
    one per scene id: it knows the scene, so what it reaches is a bound, not a method.
    Built from data that knows its true scenes (the synthetic benchmark); nothing to train."""

    has_depth = True
    from_run = ("scenes",)

    def __init__(self, scenes: list[SyntheticScene]) -> None:
        super().__init__()
        self.scenes = list(scenes)

    @classmethod
    def build(
        cls, config: dict[str, Any], inputs: SceneModelInputs
    ) -> tuple[SceneModel, dict[str, Any] | None]:
        scenes = getattr(inputs.data, "oracle_scenes", None)
        if scenes is None:
            raise ConfigError(
                "scene_model=oracle renders the synthetic benchmark's true scenes; this data "
                "has none (use scene_model=voxel_grid)"
            )
        return cls(scenes(), **config), None

    @torch.no_grad()
    def render(
        self,
        poses: Tensor,
        scenes: Tensor,
        intrinsics: Tensor,
        width: int,
        height: int,
        surface_share: float = 0.0,
    ) -> SceneRendering:
        origins, directions = camera_rays(poses.double(), intrinsics.double(), width, height)
        b, pixels = origins.shape[:2]
        rgb = np.zeros((b, pixels, 3), np.float32)
        depth = np.zeros((b, pixels), np.float32)
        scene_ids = scenes.cpu().numpy()
        for scene in np.unique(scene_ids).tolist():
            rows = np.flatnonzero(scene_ids == scene)
            colour, t = shade_rays(
                self.scenes[scene],
                origins[rows].reshape(-1, 3).cpu().numpy(),
                directions[rows].reshape(-1, 3).cpu().numpy(),
            )
            rgb[rows] = colour.reshape(len(rows), pixels, 3)
            depth[rows] = t.reshape(len(rows), pixels)
        image = torch.from_numpy(rgb).clamp(0, 1).view(b, height, width, 3).permute(0, 3, 1, 2)
        depths = torch.from_numpy(depth).view(b, height, width)
        return SceneRendering(
            image.to(poses.device), depths.to(poses.device), torch.ones_like(depths)
        )
