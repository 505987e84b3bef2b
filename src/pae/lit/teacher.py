"""LightningModule that trains a teacher APR with the learned pose loss."""

from __future__ import annotations

from typing import Any

from torch import Tensor, nn
from torchmetrics.classification import MulticlassAccuracy

from pae.core.losses import LearnedPoseLoss
from pae.lit.base import OptimizerFactory, PaeModule, SchedulerFactory
from pae.lit.evaluation import EVAL_SPLITS, PoseEvaluation
from pae.models.base import PoseRegressor


class TeacherModule(PaeModule):
    """Wires a PoseRegressor, LearnedPoseLoss (+ scene cross-entropy for multi-scene teachers),
    the optimiser and pose-error metrics for `teacher` and the `mean_pose` baseline; teachers
    with a scene classifier also log `{split}/teacher/scene_accuracy` (fraction of images
    assigned their true scene)."""

    def __init__(
        self,
        teacher: PoseRegressor,
        loss: LearnedPoseLoss,
        optimizer: OptimizerFactory,
        scene_names: list[str],
        teacher_config: dict[str, Any],
        scheduler: SchedulerFactory | None = None,
        scene_loss_weight: float = 1.0,
    ) -> None:
        super().__init__(optimizer, scheduler)
        self.save_hyperparameters(
            {"teacher_config": teacher_config, "scene_names": list(scene_names)}
        )
        self.teacher = teacher
        self.loss = loss
        self.scene_loss_weight = scene_loss_weight
        self.evaluation = PoseEvaluation(["teacher", "mean_pose"], scene_names)
        self.register_mean_pose_baseline(len(scene_names))
        n_scenes = max(len(scene_names), 2)
        self.scene_accuracy = nn.ModuleDict(
            {split: MulticlassAccuracy(n_scenes, average="micro") for split in EVAL_SPLITS}
        )

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        pred, latents = self.teacher(batch["image"], batch["scene"])
        terms = self.loss(pred, batch["pose"])
        loss = terms.total
        figures: dict[str, Tensor] = {}
        if latents.scene_logits is not None:
            scene_loss = nn.functional.cross_entropy(latents.scene_logits, batch["scene"])
            loss = loss + self.scene_loss_weight * scene_loss
            figures["train/scene_loss"] = scene_loss
        self.log_train(
            figures
            | {
                "train/loss": loss,
                "train/pos_loss": terms.position,
                "train/rot_loss": terms.orientation,
                "train/s_x": self.loss.s_x,
                "train/s_q": self.loss.s_q,
            }
        )
        return loss

    def trainable_parameters(self) -> list[nn.Parameter]:
        return list(self.parameters())

    def evaluate(self, batch: dict[str, Tensor], batch_idx: int, split: str) -> None:
        pred, latents = self.teacher(batch["image"])
        gt, scene, index = batch["pose"], batch["scene"], batch.get("index")
        self.evaluation.update(split, "teacher", pred, gt, scene, index)
        if latents.scene_logits is not None:
            self.scene_accuracy[split].update(latents.scene_logits, scene)
        self.evaluation.update(split, "mean_pose", self.mean_poses[scene], gt, scene, index)

    def _log_scene_accuracy(self, split: str) -> None:
        metric = self.scene_accuracy[split]
        if metric.update_called:
            self.log(f"{split}/teacher/scene_accuracy", metric.compute())
            metric.reset()

    def on_validation_epoch_end(self) -> None:
        super().on_validation_epoch_end()
        self._log_scene_accuracy("val")

    def on_test_epoch_end(self) -> None:
        super().on_test_epoch_end()
        self._log_scene_accuracy("test")
