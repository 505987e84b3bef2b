"""LightningModule for relative pose regression against *real* train images: the bound for
virtual RPR (it keeps the train images at test time, the storage PAEs avoid)."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from pae.geometry import relative_pose
from pae.lit.base import OptimizerFactory, PaeModule, SchedulerFactory
from pae.lit.evaluation import PoseEvaluation
from pae.lit.rpr import nearby_references, perturb_poses
from pae.losses import LearnedPoseLoss
from pae.models.base import PoseRegressor
from pae.models.rpr import SiameseRPR
from pae.refine.index import PoseIndex


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


class ImageRPRModule(PaeModule):
    """Trains a SiameseRPR on pairs of real train images and evaluates it as a refinement.

    Training pairs: the query is a train image (augmented), its reference the real train
    image of one of the `pair_k` train poses nearest to its pose (never itself) — or, with
    `pair_offset` ({position_m, orientation_deg}), nearest to its pose moved by
    `perturb_poses` as a teacher's estimate errs, so the pairs' offsets resemble those met at
    test time; the target is `relative_pose(reference pose, query pose)`.

    Evaluation (each method's orientation is reported; only positions are refined, so the
    RPR methods keep the teacher's orientation):
    - `rpr_image`: the teacher estimates the pose, the train image of the nearest train pose
      to that estimate is the reference; position = reference position + translation.
    - `rpr_reference`: that retrieved train pose itself used as the estimate (position and
      orientation), so one sees what the RPR adds to retrieval.
    - `rpr_image_test_store`, `rpr_reference_test_store`: the same with the train pose
      nearest to the *true* test pose (reads the test labels: an audit of how good the
      RPR is with the best stored reference, not a result).
    """

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
        self.evaluation = PoseEvaluation(
            [
                "teacher",
                "rpr_image",
                "rpr_reference",
                "rpr_image_test_store",
                "rpr_reference_test_store",
            ],
            scene_names,
        )
        self.index: PoseIndex | None = None
        self.images: TrainImages | None = None
        self.pair_count = pair_k + 1

    def train(self, mode: bool = True) -> ImageRPRModule:
        super().train(mode)
        self.teacher.eval()
        return self

    def use_data(self, datamodule: Any) -> None:
        """Take the train poses (the retrieval store) and train images from the data module."""
        poses, scenes = datamodule.train_poses()
        self.index = PoseIndex(poses, scenes)
        self.images = TrainImages(datamodule)
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

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        assert self.images is not None
        rows, reference = self.training_pairs(batch)
        images = self.images(rows, batch["image"].device)
        terms = self.loss(self.rpr(batch["image"], images), relative_pose(reference, batch["pose"]))
        self.log_dict(
            {"train/loss": terms.total, "train/pos_loss": terms.position},
            batch_size=len(reference),
        )
        return terms.total

    def trainable_parameters(self) -> list[nn.Parameter]:
        return list(self.rpr.parameters()) + list(self.loss.parameters())

    def refine(self, images: Tensor, estimate: Tensor, scene: Tensor) -> tuple[Tensor, Tensor]:
        """Query images and pose estimates [B, 7] (unit q) -> (refined poses [B, 7]: the
        reference position + the RPR's translation and the estimate's orientation, the
        reference poses [B, 7] retrieved for the estimates)."""
        assert self.index is not None and self.images is not None
        rows = self.index.query(estimate, scene, 1)[0][:, 0]
        reference = self.index.poses.to(estimate.device)[rows.to(estimate.device)]
        relative = self.rpr(images, self.images(rows, images.device))
        position = reference[:, :3] + relative[:, :3]
        return torch.cat([position, estimate[:, 3:]], dim=-1), reference

    def evaluate(self, batch: dict[str, Tensor], batch_idx: int, split: str) -> None:
        images, gt, scene, index = batch["image"], batch["pose"], batch["scene"], batch.get("index")
        answer = self.teacher.estimate(images, scene)
        refined, reference = self.refine(images, answer.pose, answer.scene)
        # the audit: retrieval by the true pose (and scene); the teacher's orientation kept
        oracle, oracle_reference = self.refine(images, gt, scene)
        oracle = torch.cat([oracle[:, :3], answer.pose[:, 3:]], dim=-1)
        update = self.evaluation.update
        update(split, "teacher", answer.raw_pose, gt, scene, index)
        update(split, "rpr_image", refined, gt, scene, index)
        update(split, "rpr_reference", reference, gt, scene, index)
        update(split, "rpr_image_test_store", oracle, gt, scene, index)
        update(split, "rpr_reference_test_store", oracle_reference, gt, scene, index)
