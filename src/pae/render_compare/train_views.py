"""The train views the correspondence stage retrieves (:mod:`pae.render_compare.correspondences`):
their global descriptors, their keypoints lifted once through the scene model's depth at their
poses, and the record of a call's queries at their match width."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor

from pae.core.features import Keypoints
from pae.core.geometry import quaternion_to_matrix
from pae.render_compare.keypoints import MatchSettings, detect, lift
from pae.scene_model.base import SceneModel

DESCRIPTOR_SIDE = 16
"""The classical global descriptor: a band-passed grey thumbnail this many px on its longer
side (:func:`thumbnail_descriptors`)."""

Describer = Callable[[Tensor], Tensor]
"""RGB images [B, 3, H, W] in [0, 1] -> global descriptors [B, G], unit length."""


class TrainViews(NamedTuple):
    """The train views the stage retrieves: keypoints [N, K, ...] lifted to world points
    [N, K, 3] (``lifted`` [N, K] where the scene model saw a surface), global descriptors
    [N, G], poses [N, 7] and scenes [N]."""

    keypoints: Keypoints
    points: Tensor
    lifted: Tensor
    descriptors: Tensor
    poses: Tensor
    scenes: Tensor


AXIS_M = 2.0
"""How the nearest train cameras weigh the optical axes' angle: metres per unit of
``1 - cos`` (30 degrees weigh as 0.27 m)."""


def nearest_cameras(
    poses: Tensor, scenes: Tensor, cameras: Tensor, camera_scenes: Tensor, count: int
) -> Tensor:
    """Rows [B, k] of the ``count`` cameras [N, 7] of each pose's scene (scenes [B], camera
    scenes [N]) nearest poses [B, 7]: by distance (m) plus ``AXIS_M`` × (1 - the cosine of
    the angle between the optical axes); nearest first."""
    distance = torch.cdist(poses[:, :3].float(), cameras[:, :3].float())
    axes = quaternion_to_matrix(poses[:, 3:].float())[:, :, 2]
    facing = axes @ quaternion_to_matrix(cameras[:, 3:].float())[:, :, 2].T
    cost = (distance + (1 - facing) * AXIS_M).masked_fill(
        scenes[:, None] != camera_scenes[None], math.inf
    )
    return cost.topk(min(count, cost.shape[1]), 1, largest=False).indices


def thumbnail_descriptors(images: Tensor) -> Tensor:
    """The classical global descriptor of RGB images [B, 3, H, W]: the grey image's
    band-pass (a blurred copy subtracted) area-downsampled to ``DESCRIPTOR_SIDE`` px on its
    longer side, zero-mean and unit length -> [B, G]."""
    grey = (0.299 * images[:, 0] + 0.587 * images[:, 1] + 0.114 * images[:, 2])[:, None]
    h, w = grey.shape[-2:]
    scale = DESCRIPTOR_SIDE / max(h, w)
    small = F.interpolate(
        grey, size=(max(2, round(h * scale)), max(2, round(w * scale))), mode="area"
    )
    smooth = F.avg_pool2d(F.pad(small, (2, 2, 2, 2), mode="replicate"), 5, stride=1)
    flat = (small - smooth).flatten(1)
    flat = flat - flat.mean(1, keepdim=True)
    return F.normalize(flat, dim=1)


def _lift_views(
    scene_model: SceneModel,
    keypoints: Keypoints,
    poses: Tensor,
    scenes: Tensor,
    intrinsics: Tensor,
    size: tuple[int, int],
    settings: MatchSettings,
    chunk: int = 64,
) -> tuple[Tensor, Tensor]:
    """The views' keypoints (px at ``size`` = (width, height)) lifted through the scene
    model's depth rendered at their poses, ``settings.depth_width`` px wide."""
    width, height = size
    depth_w = settings.depth_width
    depth_h = max(4, round(height * depth_w / width))
    scale = torch.tensor([depth_w / width, depth_h / height])
    small = intrinsics.clone()
    small[:, [0, 2]] = (intrinsics[:, [0, 2]] + torch.tensor([0.0, 0.5])) * scale[0]
    small[:, [1, 3]] = (intrinsics[:, [1, 3]] + torch.tensor([0.0, 0.5])) * scale[1]
    small[:, 2:] -= 0.5
    points, lifted = [], []
    for rows in torch.arange(len(poses)).split(chunk):
        rendering = scene_model.render(
            poses[rows], scenes[rows], small[rows], depth_w, depth_h, settings.surface_share
        )
        assert rendering.depth is not None and rendering.opacity is not None
        xy = (keypoints.xy[rows] + 0.5) * scale - 0.5
        world, seen = lift(xy, rendering.depth, rendering.opacity, poses[rows], small[rows])
        points.append(world)
        lifted.append(seen & keypoints.mask[rows])
    return torch.cat(points), torch.cat(lifted)


@torch.no_grad()
def train_views(
    scene_model: SceneModel,
    images: Tensor,
    intrinsics: Tensor,
    poses: Tensor,
    scenes: Tensor,
    settings: MatchSettings,
    describe: Describer | None = None,
) -> TrainViews:
    """The database of train views: their images [N, 3, H, W] (RGB in [0, 1], at the match
    width) with intrinsics [N, 4] (px of those images), poses [N, 7] and scenes [N] ->
    keypoints lifted through the scene model's depth, global descriptors (``describe``, else
    :func:`thumbnail_descriptors`)."""
    describe = describe or thumbnail_descriptors
    found = detect(images, settings)
    size = (images.shape[-1], images.shape[-2])
    points, lifted = _lift_views(
        scene_model, found, poses.float(), scenes, intrinsics.float(), size, settings
    )
    descriptors = torch.cat([describe(part) for part in images.split(256)])
    return TrainViews(found, points, lifted, descriptors, poses.float(), scenes)


class TrainImages:
    """The train views a correspondence stage retrieves: images [N, 3, H, W] (uint8, or RGB
    in [0, 1]) at the match width with intrinsics [N, 4] (px of those images), poses [N, 7]
    and scenes [N]; ``describe``: their global descriptor (None:
    :func:`thumbnail_descriptors`). Their keypoints and lifted points (:func:`train_views`)
    are made on first use for each scene model and each detector setting, then kept."""

    def __init__(
        self,
        images: Tensor,
        intrinsics: Tensor,
        poses: Tensor,
        scenes: Tensor,
        describe: Describer | None = None,
    ) -> None:
        self.images, self.intrinsics = images, intrinsics
        self.poses, self.scenes, self.describe = poses, scenes, describe
        self._made: dict[tuple, TrainViews] = {}
        self._descriptors: Tensor | None = None

    def views(self, scene_model: SceneModel, settings: MatchSettings) -> TrainViews:
        """The views' keypoints lifted through ``scene_model`` (:func:`train_views`)."""
        detection = (settings.detector, settings.keypoints, settings.contrast)
        key = (id(scene_model), *detection, settings.depth_width, settings.surface_share)
        if key not in self._made:
            parts = [
                train_views(
                    scene_model,
                    self._float(rows),
                    self.intrinsics[rows],
                    self.poses[rows],
                    self.scenes[rows],
                    settings,
                    self.describe,
                )
                for rows in torch.arange(len(self.poses)).split(512)
            ]
            self._made[key] = _joined(parts)
        return self._made[key]

    @property
    def descriptors(self) -> Tensor:
        """The views' global descriptors [N, G] (made on first use)."""
        if self._descriptors is None:
            describe = self.describe or thumbnail_descriptors
            rows = torch.arange(len(self.poses)).split(512)
            self._descriptors = torch.cat([describe(self._float(part)) for part in rows])
        return self._descriptors

    def nearest(self, images: Tensor, scenes: Tensor, count: int) -> Tensor:
        """Rows [B, k] of the ``count`` views of each query's scene (scenes [B]) whose
        descriptors are nearest those of images [B, 3, H, W] (RGB in [0, 1]; k: at most
        ``count``, fewer where the scenes have fewer views), most similar first."""
        describe = self.describe or thumbnail_descriptors
        similarity = describe(unit_rgb(images)) @ self.descriptors.T
        similarity = similarity.masked_fill(scenes[:, None] != self.scenes[None], -math.inf)
        return similarity.topk(min(count, similarity.shape[1]), 1).indices

    def _float(self, rows: Tensor) -> Tensor:
        return unit_rgb(self.images[rows])


def unit_rgb(images: Tensor) -> Tensor:
    """Images as uint8 (0-255) or float in [0, 1] -> float32 in [0, 1]."""
    return images.float() / 255 if images.dtype == torch.uint8 else images.float()


def _joined(parts: Sequence[TrainViews]) -> TrainViews:
    """Views made in parts -> one record (keypoints padded to the longest)."""
    size = max(part.points.shape[1] for part in parts)
    dim = max(part.keypoints.descriptors.shape[2] for part in parts)

    def padded(t: Tensor, last: int | None = None) -> Tensor:  # [n, k, ...] -> [n, size, ...]
        rest = list(t.shape[2:])
        if last is not None:
            rest[-1] = last
        out = t.new_zeros(t.shape[0], size, *rest)
        out[(slice(None), *(slice(0, n) for n in t.shape[1:]))] = t
        return out

    keypoints = Keypoints(
        torch.cat([padded(p.keypoints.xy) for p in parts]),
        torch.cat([padded(p.keypoints.descriptors, dim) for p in parts]),
        torch.cat([p.keypoints.count for p in parts]),
    )
    return TrainViews(
        keypoints,
        torch.cat([padded(p.points) for p in parts]),
        torch.cat([padded(p.lifted) for p in parts]),
        torch.cat([p.descriptors for p in parts]),
        torch.cat([p.poses for p in parts]),
        torch.cat([p.scenes for p in parts]),
    )


class MatchQueries(NamedTuple):
    """What the correspondence stage reads of the queries beyond the refiner's: their images
    [B, 3, H, W] (RGB, uint8 or float in [0, 1]; held as uint8, a quarter of the memory) at
    the match width with intrinsics [B, 4] (px of those images), and the train views to
    retrieve (None: the rendering at the start only)."""

    images: Tensor
    intrinsics: Tensor
    train: TrainImages | None = None

    def views(self, scene_model: SceneModel, settings: MatchSettings) -> TrainViews | None:
        if not settings.uses_views:
            return None
        if self.train is None:
            raise ValueError(
                "render_compare.match.views and near_views need the train views "
                "(MatchQueries.train)"
            )
        return self.train.views(scene_model, settings)

    @property
    def describe(self) -> Describer | None:
        return None if self.train is None else self.train.describe
