"""LightningModule for relative pose regression against *real* train images: the bound for
virtual RPR (it keeps the train images at test time, the storage PAEs avoid)."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from pae.lit.base import OptimizerFactory, SchedulerFactory
from pae.lit.rpr import PairedRPRModule
from pae.losses import LearnedPoseLoss
from pae.models.base import PoseRegressor
from pae.models.rpr import SiameseRPR


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


class ImageRPRModule(PairedRPRModule):
    """Trains a SiameseRPR on pairs of real train images and evaluates it as a refinement.

    Training pairs: the query is a train image (augmented), its reference the real train
    image of a train pose near its pose (``PairedRPRModule``).

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
        methods = ["teacher", "rpr_image", "rpr_reference"]
        methods += ["rpr_image_test_store", "rpr_reference_test_store"]
        super().__init__(
            rpr,
            teacher,
            loss,
            optimizer,
            scene_names,
            configs,
            methods,
            scheduler,
            pair_k,
            pair_offset,
        )
        self.images: TrainImages | None = None

    def use_data(self, datamodule: Any) -> None:
        """Take the train poses (the retrieval store) and train images from the data module."""
        super().use_data(datamodule)
        self.images = TrainImages(datamodule)

    def reference_images(self, rows: Tensor, poses: Tensor, scenes: Tensor, like: Tensor) -> Tensor:
        assert self.images is not None
        return self.images(rows, like.device)

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
