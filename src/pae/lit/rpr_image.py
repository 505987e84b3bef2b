"""LightningModule for relative pose regression against *real* train images: the bound for
virtual RPR (it keeps the train images at test time, the storage PAEs avoid)."""

from __future__ import annotations

from typing import Any

from torch import Tensor

from pae.lit.rpr import PairedRPRModule
from pae.relative.refiners import ImageRPR, TrainImages, with_position


class ImageRPRModule(PairedRPRModule):
    """Trains a SiameseRPR on pairs of real train images and evaluates it as a refinement.

    Training pairs: the query is a train image (augmented), its reference the real train
    image of a train pose near its pose (``PairedRPRModule``).

    Evaluation (each method's orientation is reported; only positions are refined, so the
    RPR methods keep the teacher's orientation):
    - `rpr_image`: ``pae.refine.ImageRPR`` from the teacher's estimate (the train image of
      the train pose nearest the estimate is the reference).
    - `rpr_reference`: that retrieved train pose itself used as the estimate (position and
      orientation), so one sees what the RPR adds to retrieval.
    - `rpr_image_test_store`, `rpr_reference_test_store`: the same with the train pose
      nearest to the *true* test pose (reads the test labels: an audit of how good the
      RPR is with the best stored reference, not a result).
    """

    METHODS = (
        "teacher",
        "rpr_image",
        "rpr_reference",
        "rpr_image_test_store",
        "rpr_reference_test_store",
    )
    images: TrainImages | None = None
    method: ImageRPR | None = None

    def use_data(self, datamodule: Any) -> None:
        """Take the train poses (the retrieval store) and train images from the data module."""
        super().use_data(datamodule)
        assert self.index is not None
        self.images = TrainImages(datamodule)
        self.method = ImageRPR(self.rpr, self.index, self.images)

    def reference_images(self, rows: Tensor, poses: Tensor, scenes: Tensor, like: Tensor) -> Tensor:
        assert self.images is not None
        return self.images(rows, like.device)

    def evaluate(self, batch: dict[str, Tensor], batch_idx: int, split: str) -> None:
        assert self.method is not None
        images, gt, scene, index = batch["image"], batch["pose"], batch["scene"], batch.get("index")
        answer = self.teacher.estimate(images, scene)
        refined, reference = self.method(images, answer)
        # the audit: retrieval by the true pose (and scene); the teacher's orientation kept
        oracle, oracle_reference = self.method(images, answer._replace(pose=gt, scene=scene))
        oracle = with_position(oracle, answer.pose)
        update = self.evaluation.update
        update(split, "teacher", answer.raw_pose, gt, scene, index)
        update(split, "rpr_image", refined, gt, scene, index)
        update(split, "rpr_reference", reference, gt, scene, index)
        update(split, "rpr_image_test_store", oracle, gt, scene, index)
        update(split, "rpr_reference_test_store", oracle_reference, gt, scene, index)
