"""Training stops at the first non-finite loss: a diverged model is no result, and the
checkpoint of the last whole epoch stays as it was."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Mapping
from typing import Any

import lightning as L
import torch

from pae.core.errors import DivergenceError


def batch_loss(outputs: Any) -> torch.Tensor | None:
    """The loss of a training step's ``outputs`` (a tensor or a mapping with ``loss``), None
    where it has none (a skipped step)."""
    loss = outputs.get("loss") if isinstance(outputs, Mapping) else outputs
    return loss if isinstance(loss, torch.Tensor) else None


class TrainBatchEndCallback(L.Callback, ABC):
    """A callback that acts after every training batch: Lightning's batch-end hook hands
    ``after_train_batch`` the step's outputs and the batch's index."""

    def on_train_batch_end(
        self,
        trainer: L.Trainer,
        pl_module: L.LightningModule,
        outputs: Any,
        batch: Any,
        batch_idx: int,
    ) -> None:
        self.after_train_batch(trainer, outputs, batch_idx)

    @abstractmethod
    def after_train_batch(self, trainer: L.Trainer, outputs: Any, batch_idx: int) -> None:
        """After the training batch ``batch_idx``, whose step returned ``outputs``."""


class TrainLossCallback(TrainBatchEndCallback):
    """A callback that reads the loss of every training step: ``on_train_loss`` gets the
    step's loss (``batch_loss``) after each batch."""

    def after_train_batch(self, trainer: L.Trainer, outputs: Any, batch_idx: int) -> None:
        self.on_train_loss(trainer, batch_loss(outputs), batch_idx)

    @abstractmethod
    def on_train_loss(self, trainer: L.Trainer, loss: torch.Tensor | None, batch_idx: int) -> None:
        """The loss (a tensor, None for a skipped step) of the training batch ``batch_idx``."""


class StopOnNonFiniteLoss(TrainLossCallback):
    """After every training step, a NaN or infinite loss raises DivergenceError: one line
    naming the step, the loss, the epoch and the learning rate. `step` names the training
    step of the run (``teacher``, ``student``, ...), `lr_setting` the learning-rate setting
    to lower (``teacher.optimizer.lr=0.002``). Under DDP every process stops together."""

    def __init__(self, step: str, lr_setting: str) -> None:
        self.step = step
        self.lr_setting = lr_setting

    def on_train_loss(self, trainer: L.Trainer, loss: torch.Tensor | None, batch_idx: int) -> None:
        if loss is None:
            return
        diverged = not bool(torch.isfinite(loss.detach()).all())
        if not trainer.strategy.reduce_boolean_decision(diverged, all=False):
            return
        rates = [group["lr"] for opt in trainer.optimizers for group in opt.param_groups]
        rate = f", learning rate {rates[0]:.3g} at that step" if rates else ""
        value = loss.detach().float().item() if diverged else "not finite in another process"
        raise DivergenceError(
            f"{self.step}: training diverged: the loss is {value} at step "
            f"{trainer.global_step} (epoch {trainer.current_epoch}, batch {batch_idx}{rate}); "
            f"a learning rate too high is the common cause: lower {self.lr_setting}"
        )
