"""Test-time methods that read the query image: virtual RPR (paper §3.3), the image RPR (its
bound, keeping the train images) and the iterative APR, behind one interface, ``ImageRefiner``.

Each is a plain class holding its trained networks and what it keeps at test time; the
Lightning modules (``pae.lit.rpr``, ``pae.lit.rpr_image``, ``pae.lit.iapr``) evaluate with them
and ``pae.bench.methods`` times them.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple, Protocol

import torch
from torch import Tensor, nn

from pae.core.geometry import compose_pose
from pae.data.transforms import ImageTransform
from pae.models.base import TeacherEstimate
from pae.refine.index import PoseIndex
from pae.refine.refiner import PoseEncoder

PoseNetwork = Callable[[Tensor, Tensor], Tensor]
"""A relative regressor: (query images [B, 3, H, W], its second input) -> pose [B, 7]."""


class RefinedPoses(NamedTuple):
    """poses [B, 7] refined; references [B, 7]: the poses the refinement moved from (the
    retrieved train pose, or the last iterate), or None."""

    poses: Tensor
    references: Tensor | None = None


class ImageRefiner(Protocol):
    """A test-time method: query images [B, 3, H, W] (network input) and the teacher's answer
    for them (pose, latents, scene) -> refined poses. Batched; no gradients needed."""

    def __call__(self, images: Tensor, estimate: TeacherEstimate) -> RefinedPoses: ...


def with_position(poses: Tensor, orientation_from: Tensor) -> Tensor:
    """[B, 7]: the positions of ``poses`` with the orientations of ``orientation_from``."""
    return torch.cat([poses[:, :3], orientation_from[:, 3:]], dim=-1)


def nearest_train_poses(index: PoseIndex, estimate: TeacherEstimate) -> tuple[Tensor, Tensor]:
    """(rows [B] into ``index.poses``, poses [B, 7]) of the train pose nearest each estimate
    in its scene."""
    rows = index.query(estimate.pose, estimate.scene, 1)[0][:, 0]
    device = estimate.pose.device
    return rows, index.poses.to(device)[rows.to(device)]


class VirtualRPR:
    """Virtual RPR: the train pose nearest the teacher's estimate is decoded to an image (PAE
    + decoder), the Siamese RPR regresses the query's pose relative to it, and the refined
    position is ``compose_pose(reference, relative)``'s; the orientation stays the teacher's.
    Keeps the train poses and the networks, no images."""

    def __init__(
        self, rpr: PoseNetwork, pae: PoseEncoder, decoder: nn.Module, index: PoseIndex
    ) -> None:
        self.rpr, self.pae, self.decoder, self.index = rpr, pae, decoder, index

    def reference_images(self, poses: Tensor, scenes: Tensor, crop: int) -> Tensor:
        """Decoded images of poses [B, 7] as network input [B, 3, crop, crop]."""
        with torch.no_grad():
            images = self.decoder(self.pae(poses, scenes).joint())
        images = nn.functional.interpolate(images, size=(crop, crop), mode="bilinear")
        return ImageTransform.normalize_batch(images)

    def __call__(self, images: Tensor, estimate: TeacherEstimate) -> RefinedPoses:
        _, reference = nearest_train_poses(self.index, estimate)
        decoded = self.reference_images(reference, estimate.scene, images.shape[-1])
        moved = compose_pose(reference, self.rpr(images, decoded))
        return RefinedPoses(with_position(moved, estimate.pose), reference)


class TrainImages:
    """The train split's images by row, as network input (evaluation pre-processing).

    Rows are read as one batch through the train dataset (a single indexing operation with
    the in-memory image cache, batched decoding otherwise).
    """

    def __init__(self, datamodule: Any) -> None:
        self.dataset = datamodule.datasets["train"]
        self.preprocess = datamodule.preprocess

    def __len__(self) -> int:
        return len(self.dataset)

    def __call__(self, rows: Tensor, device: torch.device | str) -> Tensor:
        """rows [B] long indices into the train split -> images [B, 3, crop, crop]."""
        batch = self.dataset.__getitems__(rows.cpu().tolist())
        return self.preprocess(batch["image"].to(device), train=False)


class ImageRPR:
    """RPR against real train images (the bound for virtual RPR: it keeps the train images):
    the train image of the train pose nearest the estimate is the reference, the refined
    position is ``compose_pose(reference, relative)``'s, the orientation the estimate's."""

    def __init__(
        self,
        rpr: PoseNetwork,
        index: PoseIndex,
        train_images: Callable[[Tensor, torch.device | str], Tensor],
    ) -> None:
        self.rpr, self.index, self.train_images = rpr, index, train_images

    def __call__(self, images: Tensor, estimate: TeacherEstimate) -> RefinedPoses:
        rows, reference = nearest_train_poses(self.index, estimate)
        moved = compose_pose(reference, self.rpr(images, self.train_images(rows, images.device)))
        return RefinedPoses(with_position(moved, estimate.pose), reference)


class IterativeAPRRefiner:
    """The iterative APR: from the estimate, ``iterations`` corrections, each regressed from
    the query image and the PAE encoding of the current pose and applied by
    ``compose_pose``. With refine_orientation=False only positions move. Keeps no store."""

    def __init__(
        self,
        iapr: PoseNetwork,
        pae: PoseEncoder,
        iterations: int = 3,
        refine_orientation: bool = True,
    ) -> None:
        self.iapr, self.pae = iapr, pae
        self.iterations, self.refine_orientation = iterations, refine_orientation

    def iterates(self, images: Tensor, start: Tensor, scene: Tensor) -> list[Tensor]:
        """The pose after each iteration from ``start`` [B, 7] (unit q), [B, 7] each."""
        poses, pose = [], start
        for _ in range(self.iterations):
            with torch.no_grad():
                encoding = self.pae(pose, scene).joint()
            moved = compose_pose(pose, self.iapr(images, encoding))
            pose = moved if self.refine_orientation else with_position(moved, start)
            poses.append(pose)
        return poses

    def __call__(self, images: Tensor, estimate: TeacherEstimate) -> RefinedPoses:
        poses = self.iterates(images, estimate.pose, estimate.scene)
        return RefinedPoses(poses[-1], poses[-2] if len(poses) > 1 else estimate.pose)
