"""LightningModule for virtual relative pose regression (paper §3.3): a Siamese RPR between
the query image and an image decoded from a train pose's PAE encoding."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Any, ClassVar

import torch
from torch import Tensor, nn

from pae.core.geometry import relative_pose
from pae.core.losses import LearnedPoseLoss
from pae.core.pose_sampling import perturb_poses
from pae.lit.base import OptimizerFactory, PaeModule, SchedulerFactory
from pae.lit.evaluation import PoseEvaluation
from pae.models.base import PoseRegressor
from pae.models.decoder import ImageDecoder
from pae.models.pae import PoseAutoEncoder
from pae.models.rpr import SiameseRPR
from pae.refine.index import PoseIndex
from pae.relative.refiners import VirtualRPR


def nearby_references(
    index: PoseIndex,
    poses: Tensor,
    scenes: Tensor,
    own: Tensor,
    count: int,
    around: Tensor | None = None,
) -> Tensor:
    """Training references: for each pose [B, 7] of the store's rows `own` [B], one of the
    `count` stored poses (same scene) nearest to it, or to `around` [B, 7] (e.g. the poses
    moved as a pose estimate errs), drawn at random, never the row itself -> indices [B]
    into `index.poses`."""
    poses = poses if around is None else around
    candidates = index.query(poses, scenes, count)[0].to(poses.device)
    itself = candidates == own.to(poses.device).unsqueeze(1)
    choice = torch.rand(candidates.shape, device=poses.device).masked_fill(itself, -1).argmax(1)
    return candidates.gather(1, choice[:, None])[:, 0]


class PairedRPRModule(PaeModule, ABC):
    """What the RPR modules share: a SiameseRPR trained on (query image, reference image)
    pairs against a frozen teacher, the references drawn among the train poses near the
    query's pose.

    Training references: one of the `pair_k` nearest train poses of the query's true pose
    (never the query's own row) — or, with `pair_offset` ({position_m, orientation_deg}),
    of that pose moved by `perturb_poses` as a teacher's estimate errs, so that the pairs'
    offsets resemble those met at test time. The RPR regresses the query's pose relative to
    the reference (``pae.core.geometry.relative_pose``). Subclasses give the reference images
    (``reference_images``), the evaluation and the methods it reports (``METHODS``).
    """

    METHODS: ClassVar[tuple[str, ...]]
    """The methods the evaluation reports."""

    def __init__(
        self,
        rpr: SiameseRPR,
        teacher: PoseRegressor,
        loss: LearnedPoseLoss,
        optimizer: OptimizerFactory,
        scene_names: list[str],
        configs: dict[str, Any],
        scheduler: SchedulerFactory | None = None,
        pair_k: int = 5,
        pair_offset: dict[str, float] | None = None,
    ) -> None:
        super().__init__(optimizer, scheduler)
        self.save_hyperparameters({**configs, "scene_names": list(scene_names)})
        self.rpr = rpr
        self.teacher = teacher.eval().requires_grad_(False)
        self.loss = loss
        self.pair_k = pair_k
        self.pair_offset = dict(pair_offset) if pair_offset else None
        self.evaluation = PoseEvaluation(list(self.METHODS), scene_names)
        self.index: PoseIndex | None = None
        self.pair_count = pair_k + 1

    def frozen(self) -> list[nn.Module]:
        """The networks that stay in evaluation mode while the RPR trains."""
        return [self.teacher]

    def train(self, mode: bool = True) -> PairedRPRModule:
        super().train(mode)
        for network in self.frozen():
            network.eval()
        return self

    def use_data(self, datamodule: Any) -> None:
        """Take the train poses (the retrieval store) from the data module."""
        poses, scenes = datamodule.train_poses()
        self.index = PoseIndex(poses, scenes)
        self.pair_count = min(self.pair_k + 1, int(torch.bincount(scenes).min()))

    def setup(self, stage: str) -> None:
        self.use_data(self.trainer.datamodule)

    def training_pairs(self, batch: dict[str, Tensor]) -> tuple[Tensor, Tensor]:
        """A train batch -> (reference rows [B] of the train split, reference poses [B, 7])."""
        assert self.index is not None
        pose = batch["pose"]
        around = perturb_poses(pose, **self.pair_offset) if self.pair_offset else None
        rows = nearby_references(
            self.index, pose, batch["scene"], batch["index"], self.pair_count, around
        )
        return rows, self.index.poses.to(pose.device)[rows]

    @abstractmethod
    def reference_images(self, rows: Tensor, poses: Tensor, scenes: Tensor, like: Tensor) -> Tensor:
        """Reference images [B, 3, crop, crop] shaped like the query images ``like``, for the
        train rows ``rows`` [B] at poses [B, 7] of scenes [B]."""

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        rows, reference = self.training_pairs(batch)
        images = self.reference_images(rows, reference, batch["scene"], batch["image"])
        terms = self.loss(self.rpr(batch["image"], images), relative_pose(reference, batch["pose"]))
        self.log_train({"train/loss": terms.total, "train/pos_loss": terms.position})
        return terms.total

    def trainable_parameters(self) -> list[nn.Parameter]:
        return list(self.rpr.parameters()) + list(self.loss.parameters())


class RPRModule(PairedRPRModule):
    """Trains a SiameseRPR on (query image, decoded image of a nearby train pose) pairs.

    The references (see ``PairedRPRModule``) are decoded by the frozen PAE + decoder: the
    same kind of reference the RPR sees at test time. Evaluation: the teacher estimates the
    pose, the nearest train pose of the estimate is decoded, and the relative translation
    moves that reference position: `vrpr` position = ``compose_pose(reference, relative)``'s
    (orientation: the teacher's).
    """

    METHODS = ("teacher", "vrpr")

    def __init__(
        self,
        rpr: SiameseRPR,
        teacher: PoseRegressor,
        pae: PoseAutoEncoder,
        decoder: ImageDecoder,
        **settings: Any,
    ) -> None:
        """``settings``: the rest of ``PairedRPRModule``'s arguments (loss, optimizer, ...)."""
        super().__init__(rpr, teacher, **settings)
        self.pae = pae.eval().requires_grad_(False)
        self.decoder = decoder.eval().requires_grad_(False)
        self.method: VirtualRPR | None = None

    def frozen(self) -> list[nn.Module]:
        return [self.teacher, self.pae, self.decoder]

    def use_data(self, datamodule: Any) -> None:
        """Take the train poses (the retrieval store) and build the test-time method on them."""
        super().use_data(datamodule)
        assert self.index is not None
        self.method = VirtualRPR(self.rpr, self.pae, self.decoder, self.index)

    def reference_images(self, rows: Tensor, poses: Tensor, scenes: Tensor, like: Tensor) -> Tensor:
        assert self.method is not None
        return self.method.reference_images(poses, scenes, like.shape[-1])

    def evaluate(self, batch: dict[str, Tensor], batch_idx: int, split: str) -> None:
        assert self.method is not None
        images, gt, scene = batch["image"], batch["pose"], batch["scene"]
        answer = self.teacher.estimate(images, scene)
        vrpr = self.method(images, answer).poses
        index = batch.get("index")
        self.evaluation.update(split, "teacher", answer.raw_pose, gt, scene, index)
        self.evaluation.update(split, "vrpr", vrpr, gt, scene, index)
