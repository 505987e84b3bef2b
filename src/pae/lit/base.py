"""What every pae LightningModule shares: evaluation hooks (EvaluationModule) and, for the
modules that train, optimiser wiring (PaeModule)."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import lightning as L
import torch
from torch import Tensor, nn

from pae.core.checkpoints import DATA_FINGERPRINT_KEY
from pae.core.metrics import mean_pose_per_scene
from pae.lit.evaluation import PoseEvaluation

OptimizerFactory = Callable[..., torch.optim.Optimizer]
SchedulerFactory = Callable[..., Any]


class EvaluationModule(L.LightningModule):
    """Evaluation hooks every pae module shares. Subclasses implement
    `evaluate(batch, batch_idx, split)`; pose metrics collected in a `self.evaluation`
    PoseEvaluation are logged after each epoch."""

    def register_mean_pose_baseline(self, n_scenes: int) -> None:
        """Keep `mean_poses` [n_scenes, 7], the mean train pose per scene (the `mean_pose`
        baseline), filled from the data module when fitting, validating or testing starts."""
        self.register_buffer("mean_poses", torch.zeros(n_scenes, 7))

    def _fill_mean_poses(self) -> None:
        if hasattr(self, "mean_poses"):
            poses, scenes = self.trainer.datamodule.train_poses()
            self.mean_poses.copy_(mean_pose_per_scene(poses, scenes, len(self.mean_poses)))

    def on_fit_start(self) -> None:
        self._fill_mean_poses()

    def on_validation_start(self) -> None:
        self._fill_mean_poses()

    def on_test_start(self) -> None:
        self._fill_mean_poses()

    def evaluate(self, batch: dict[str, Tensor], batch_idx: int, split: str) -> None:
        raise NotImplementedError

    def validation_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        self.evaluate(batch, batch_idx, "val")

    def test_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        self.evaluate(batch, batch_idx, "test")

    def _log_evaluation(self, split: str) -> None:
        evaluation = getattr(self, "evaluation", None)
        if isinstance(evaluation, PoseEvaluation):
            evaluation.log(self, split)

    def on_validation_epoch_end(self) -> None:
        self._log_evaluation("val")

    def on_test_epoch_end(self) -> None:
        self._log_evaluation("test")


class PaeModule(EvaluationModule):
    """A module that trains: subclasses also implement `trainable_parameters()`. The scheduler
    factory gets the run's total optimiser steps (e.g. OneCycleLR); checkpoints record the
    training data's fingerprint."""

    def __init__(
        self, optimizer: OptimizerFactory, scheduler: SchedulerFactory | None = None, **kwargs: Any
    ) -> None:
        super().__init__(**kwargs)  # a second base's arguments (StudentModule: StudentEvaluator)
        self.optimizer_factory = optimizer
        self.scheduler_factory = scheduler

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Record the fingerprint of the training data (scenes, train poses) in the checkpoint."""
        datamodule = getattr(self.trainer, "datamodule", None)
        if datamodule is not None and hasattr(datamodule, "fingerprint"):
            checkpoint[DATA_FINGERPRINT_KEY] = datamodule.fingerprint()

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        """Resuming with another number of epochs: keep the schedule built for this run's total
        steps (e.g. a longer OneCycleLR) and continue it from the restored step count."""
        for state in checkpoint.get("lr_schedulers", []):
            if "total_steps" in state:
                state.pop("total_steps")
                state.pop("_schedule_phases", None)

    def trainable_parameters(self) -> Iterable[nn.Parameter]:
        raise NotImplementedError

    def log_train(self, figures: dict[str, Tensor | float], prog_bar: bool = False) -> None:
        """Log a training step's scalar ``figures`` (also to the progress bar with
        ``prog_bar``) on the steps whose figures the loggers write (every
        ``trainer.log_every_n_steps``-th and the one before a stop, as Lightning decides for
        on-step figures); on the others Lightning would only keep each as the latest value,
        at about 0.4 ms a figure a step. Outside a Trainer nothing is logged."""
        trainer = self._trainer
        if trainer is None:
            return
        if trainer._logger_connector.should_update_logs or trainer.fast_dev_run:
            self.log_dict(figures, prog_bar=prog_bar)

    def scheduled_steps(self) -> int:
        """The optimiser steps a schedule built now spans: the run's."""
        return int(self.trainer.estimated_stepping_batches)

    def configure_optimizers(self) -> Any:
        optimizer = self.optimizer_factory(params=list(self.trainable_parameters()))
        if self.scheduler_factory is None:
            return optimizer
        scheduler = self.scheduler_factory(optimizer=optimizer, total_steps=self.scheduled_steps())
        return {
            "optimizer": optimizer,
            "lr_scheduler": {"scheduler": scheduler, "interval": "step"},
        }
