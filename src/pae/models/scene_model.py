"""The interface of scene models: what render-and-compare refinement renders at a pose."""

from __future__ import annotations

from typing import NamedTuple

from torch import Tensor, nn


class SceneRendering(NamedTuple):
    """Images rendered at ``B`` poses.

    rgb: [B, 3, H, W] in [0, 1]; depth: [B, H, W] metres along the optical axis, or None for
    models that know no geometry; opacity: [B, H, W] in [0, 1] (how much of each pixel the
    model explains), or None.
    """

    rgb: Tensor
    depth: Tensor | None = None
    opacity: Tensor | None = None


class SceneModel(nn.Module):
    """A model of the scenes a dataset shows, rendered at camera poses.

    ``has_depth``: whether renderings carry depth (render-and-compare then projects the
    rendered surface into candidate cameras instead of rendering every candidate).
    """

    has_depth: bool = True

    def render(
        self, poses: Tensor, scenes: Tensor, intrinsics: Tensor, width: int, height: int
    ) -> SceneRendering:
        """Render ``B`` cameras: poses [B, 7] (camera-to-world), scene ids [B], intrinsics
        [B, 4] (fx, fy, cx, cy in px of ``width × height`` images)."""
        raise NotImplementedError


class PaeDecoderSceneModel(SceneModel):
    """The paper's image decoder over PAE encodings as a scene model: a 2-D model that
    knows no geometry and no camera. It renders the view its decoder was trained on (the
    evaluation crop), resized to the requested size; ``intrinsics`` are not read."""

    has_depth = False

    def __init__(self, pae: nn.Module, decoder: nn.Module) -> None:
        super().__init__()
        self.pae = pae
        self.decoder = decoder

    def render(
        self, poses: Tensor, scenes: Tensor, intrinsics: Tensor, width: int, height: int
    ) -> SceneRendering:
        images = self.decoder(self.pae(poses, scenes).joint())
        if images.shape[-2:] != (height, width):
            images = nn.functional.interpolate(images, size=(height, width), mode="area")
        return SceneRendering(images)
