"""LightningModule that trains a teacher APR with the learned pose loss."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import lightning as L
import torch
from torch import Tensor, nn

from pae.lit.evaluation import PoseEvaluation
from pae.losses import LearnedPoseLoss
from pae.metrics import mean_pose_per_scene
from pae.models.base import PoseRegressor

OptimizerFactory = Callable[..., torch.optim.Optimizer]
SchedulerFactory = Callable[..., Any]


def step_scheduler(module: L.LightningModule, optimizer: torch.optim.Optimizer) -> dict[str, Any]:
    """The module's scheduler factory over all of the run's optimiser steps (e.g. OneCycleLR)."""
    total_steps = int(module.trainer.estimated_stepping_batches)
    scheduler = module.scheduler_factory(optimizer=optimizer, total_steps=total_steps)
    return {"scheduler": scheduler, "interval": "step"}


class TeacherModule(L.LightningModule):
    """Wires a PoseRegressor, LearnedPoseLoss (+ scene cross-entropy for multi-scene teachers),
    the optimiser and pose-error metrics for `teacher` and the `mean_pose` baseline."""

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
        super().__init__()
        self.save_hyperparameters(
            {"teacher_config": teacher_config, "scene_names": list(scene_names)}
        )
        self.teacher = teacher
        self.loss = loss
        self.optimizer_factory = optimizer
        self.scheduler_factory = scheduler
        self.scene_loss_weight = scene_loss_weight
        self.evaluation = PoseEvaluation(["teacher", "mean_pose"], scene_names)
        self.register_buffer("mean_poses", torch.zeros(len(scene_names), 7))

    def on_fit_start(self) -> None:
        self._set_mean_poses()

    def on_test_start(self) -> None:
        self._set_mean_poses()

    def _set_mean_poses(self) -> None:
        poses, scenes = self.trainer.datamodule.train_poses()
        self.mean_poses.copy_(mean_pose_per_scene(poses, scenes, len(self.mean_poses)))

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        pred, latents = self.teacher(batch["image"], batch["scene"])
        terms = self.loss(pred, batch["pose"])
        loss = terms.total
        if latents.scene_logits is not None:
            scene_loss = nn.functional.cross_entropy(latents.scene_logits, batch["scene"])
            loss = loss + self.scene_loss_weight * scene_loss
            self.log("train/scene_loss", scene_loss)
        self.log_dict(
            {
                "train/loss": loss,
                "train/pos_loss": terms.position,
                "train/rot_loss": terms.orientation,
                "train/s_x": self.loss.s_x,
                "train/s_q": self.loss.s_q,
            },
            prog_bar=False,
        )
        return loss

    def _evaluate(self, batch: dict[str, Tensor], split: str) -> None:
        pred, _ = self.teacher(batch["image"])
        self.evaluation.update(split, "teacher", pred, batch["pose"], batch["scene"])
        baseline = self.mean_poses[batch["scene"]]
        self.evaluation.update(split, "mean_pose", baseline, batch["pose"], batch["scene"])

    def validation_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        self._evaluate(batch, "val")

    def test_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        self._evaluate(batch, "test")

    def on_validation_epoch_end(self) -> None:
        self.evaluation.log(self, "val")

    def on_test_epoch_end(self) -> None:
        self.evaluation.log(self, "test")

    def configure_optimizers(self) -> Any:
        optimizer = self.optimizer_factory(params=self.parameters())
        if self.scheduler_factory is None:
            return optimizer
        return {"optimizer": optimizer, "lr_scheduler": step_scheduler(self, optimizer)}
