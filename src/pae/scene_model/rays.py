"""Training batches of camera rays for scene models: random pixels of the train images."""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.utils.data import DataLoader, Dataset

from pae.core import streams
from pae.core.camera import directions_through, scale_intrinsics
from pae.core.geometry import quaternion_to_matrix
from pae.data.datamodule import PoseDataModule
from pae.data.order import trainer_epoch
from pae.scene_model.sparse_depth import SparseDepths, sparse_depths

LOG = logging.getLogger(__name__)

READ_ROWS = 256
"""Train images read (and resized) at a time when the ray store is filled."""


def fit_images(dataset: Any, intrinsics: Tensor, shorter_edge: int | None) -> tuple[Tensor, Tensor]:
    """Every image of ``dataset`` resized so that its shorter edge is ``shorter_edge`` px
    (None: as the dataset holds them), read ``READ_ROWS`` at a time into one uint8 tensor
    [N, 3, h, w], and the intrinsics [N, 4] of that size (``intrinsics``: of the dataset's
    images). Memory: the result, plus one read's images."""
    n = len(dataset)
    if n == 0:
        raise ValueError("the scene model has no train images to fit to (the train split is empty)")
    images = None
    for start in range(0, n, READ_ROWS):
        rows = list(range(start, min(start + READ_ROWS, n)))
        batch = dataset.__getitems__(rows)["image"]
        if images is None:
            height, width = batch.shape[-2:]
            size = (height, width)
            if shorter_edge is not None and shorter_edge != min(height, width):
                scale = shorter_edge / min(height, width)
                size = (max(1, round(height * scale)), max(1, round(width * scale)))
            images = torch.empty((n, 3, *size), dtype=torch.uint8)
        if size != (height, width):
            small = F.interpolate(batch.float(), size=size, mode="area")
            batch = small.round().clamp(0, 255).to(torch.uint8)
        images[start : start + len(rows)] = batch
    return images, scale_intrinsics(intrinsics, size[1] / width, size[0] / height)


class RayBatches(Dataset):
    """Batches of ``rays_per_batch`` random pixels of the train images: item ``i`` is batch
    ``n = epoch() × batches + i`` of the run (``epoch``: the epoch under way when the item is
    read, e.g. the trainer's), drawn from a generator seeded with (``seed``, n) alone
    (:mod:`pae.core.streams`), so a batch is the same whatever ran before it: a resumed run draws
    what an uninterrupted one would, and under DDP each process its share. Each is ``{"origins":
    [R, 3], "directions": [R, 3] (camera z = 1), "rgb": [R, 3] in [0, 1], "pixels": [R, 2]
    (the pixel's column and row scaled to [0, 1]), "scene": [R], "appearance": [R], "seed":
    int}``, ``seed`` the one for the draws rendering the batch
    makes (its samples' jitter). With ``depths`` and ``depth_rays`` > 0, each batch also
    holds ``"depth": {"origins", "directions", "scene", "target"}``: ``depth_rays`` rays
    through the triangulated keypoints, drawn after the pixels, and their depths [R] (m along
    the optical axis, the directions' units).

    images: uint8 [N, 3, H, W] as the dataset holds them; poses [N, 7]; intrinsics [N, 4] of
    those images; scenes, appearance: ids [N]; ``batches``: per epoch; depths: keypoints
    in px of ``images`` (:func:`pae.scene_model.sparse_depth.sparse_depths`).
    """

    def __init__(
        self,
        images: Tensor,
        poses: Tensor,
        intrinsics: Tensor,
        scenes: Tensor,
        appearance: Tensor,
        rays_per_batch: int,
        batches: int,
        seed: int = 0,
        epoch: Callable[[], int] = lambda: 0,
        depths: SparseDepths | None = None,
        depth_rays: int = 0,
    ) -> None:
        super().__init__()
        self.images = images
        self.rotations = quaternion_to_matrix(poses[:, 3:].double()).float()
        self.positions = poses[:, :3].float()
        self.intrinsics = intrinsics.float()
        self.scenes = scenes
        self.appearance = appearance
        self.rays_per_batch = rays_per_batch
        self.batches = batches
        self.seed = seed
        self.epoch = epoch
        self.depths = depths
        self.depth_rays = depth_rays if depths is not None and len(depths.row) else 0

    def release(self) -> None:
        """Drop the images once the fit has ended (a later batch is an IndexError): the
        trainer keeps its train loader, and with it this store, until the step ends."""
        self.images = self.images[:0]

    def __len__(self) -> int:
        return self.batches

    def __getitem__(self, index: int) -> dict[str, Any]:
        """Batch ``index`` of the epoch under way."""
        n, _, h, w = self.images.shape
        r = self.rays_per_batch
        number = self.epoch() * self.batches + index
        draws = streams.generator(self.seed, "rays", number)
        row = torch.randint(n, (r,), generator=draws)
        v, u = torch.randint(h, (r,), generator=draws), torch.randint(w, (r,), generator=draws)
        batch = {
            **self._rays(row, u, v),
            "rgb": self.images[row, :, v, u].float() / 255.0,
            "pixels": torch.stack([u / max(w - 1, 1), v / max(h - 1, 1)], -1).float(),
            "appearance": self.appearance[row],
            "seed": streams.derived_seed(self.seed, "render", number),
        }
        if self.depth_rays:
            depths = self.depths
            pick = torch.randint(len(depths.row), (self.depth_rays,), generator=draws)
            rays = self._rays(depths.row[pick], depths.u[pick], depths.v[pick])
            batch["depth"] = {**rays, "target": depths.depth[pick]}
        return batch

    def _rays(self, row: Tensor, u: Tensor, v: Tensor) -> dict[str, Tensor]:
        """World rays through pixels u, v [R] (px) of images ``row`` [R], and their scenes."""
        local = directions_through(u, v, self.intrinsics[row])
        return {
            "origins": self.positions[row],
            "directions": torch.einsum("rij,rj->ri", self.rotations[row], local),
            "scene": self.scenes[row],
        }


@dataclass(frozen=True)
class RayLoader:
    """A scene model's train batches, as a PoseDataModule's ``train_batches``: ``batches``
    batches of ``rays_per_batch`` random pixels (:class:`RayBatches`, drawn from ``seed`` and
    the data module's trainer's epoch under way, so a resumed run draws what an uninterrupted
    one would) of the train images at ``image_size`` px shorter edge (:func:`fit_images`;
    None: as the data holds them), each ray keyed on its image's appearance ``appearance``
    (``sequence`` or ``image``, :meth:`PoseDataModule.appearance_ids`); ``depth_rays`` > 0:
    that many more rays per batch through the keypoints triangulated between the train
    views (:func:`pae.scene_model.sparse_depth.sparse_depths`, on the fit's images)."""

    rays_per_batch: int
    batches: int
    image_size: int | None = None
    appearance: str = "sequence"
    seed: int = 0
    depth_rays: int = 0

    def __call__(self, data: PoseDataModule) -> DataLoader:
        """The loader of ray batches from ``data``'s train split."""
        dataset = data.datasets["train"]
        appearance, _ = data.appearance_ids("train", self.appearance)
        intrinsics = data.intrinsics("train", crop=False)
        images, intrinsics = fit_images(dataset, intrinsics, self.image_size)
        depths = None
        if self.depth_rays:
            depths = sparse_depths(images, dataset.poses, intrinsics, dataset.scenes)
            images_with = len(depths.row.unique())
            LOG.info("depth: %d keypoints in %d train images", len(depths.row), images_with)
            if not len(depths.row):
                LOG.warning("scene_model.depth_rays: no keypoint triangulated; fit without depth")
        rays = RayBatches(
            images,
            dataset.poses,
            intrinsics,
            dataset.scenes,
            appearance,
            self.rays_per_batch,
            self.batches,
            self.seed,
            lambda: trainer_epoch(data),
            depths,
            self.depth_rays,
        )
        return DataLoader(rays, batch_size=None)
