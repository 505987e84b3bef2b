"""Progress lines of training, for runs whose output goes to a log (no progress bar): one per
epoch, and within an epoch at most every `every_s` seconds."""

from __future__ import annotations

import time

import lightning as L
import torch

from pae.callbacks.finite_loss import TrainLossCallback
from pae.core.console import duration, say
from pae.report.tables import step_figures


class EpochProgress(TrainLossCallback):
    """``teacher: epoch 3/40, loss 0.412, val teacher 0.52 m / 9.1°, 0:21 elapsed, ETA 4:33``
    after every training epoch, a line when training starts, and, in an epoch that runs
    longer than ``every_s`` seconds since the last line, ``teacher: epoch 3/40, batch
    40/83, loss ...`` (slow hardware, busy cores, large datasets); silent while a progress
    bar is shown. ``step`` names the step (the pipeline sets it); the loss is the mean of
    the epoch's training steps so far; the validation figures appear after epochs that
    validate; the ETA extrapolates the batches of this run (a resumed run counts from where
    it continued)."""

    def __init__(self, step: str = "train", every_s: float = 30.0) -> None:
        super().__init__()
        self.step = step
        self.every_s = every_s
        self._said_at = 0.0
        self._started = 0.0
        self._first_epoch = 0
        self._loss_sum: torch.Tensor | None = None
        self._batches = 0
        self._validated = False

    @staticmethod
    def _shown(trainer: L.Trainer) -> bool:
        return trainer.progress_bar_callback is None and not trainer.sanity_checking

    def _say(self, line: str) -> None:
        self._said_at = time.perf_counter()
        say(line)

    def on_train_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._started = time.perf_counter()
        self._first_epoch = trainer.current_epoch
        if self._shown(trainer):
            start = f" from epoch {trainer.current_epoch}" if trainer.current_epoch else ""
            epochs = "1 epoch" if trainer.max_epochs == 1 else f"{trainer.max_epochs} epochs"
            self._say(
                f"{self.step}: training {epochs} of {trainer.num_training_batches} batches{start}"
            )

    def on_train_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._loss_sum, self._batches, self._validated = None, 0, False

    def on_train_loss(self, trainer: L.Trainer, loss: torch.Tensor | None, batch_idx: int) -> None:
        if loss is not None:
            loss = loss.detach().float()
            self._loss_sum = loss if self._loss_sum is None else self._loss_sum + loss
            self._batches += 1
        now = time.perf_counter()
        batches = trainer.num_training_batches
        if (
            now - self._said_at < self.every_s
            or not self._shown(trainer)
            or batch_idx + 1 >= batches
        ):
            return
        epoch = trainer.current_epoch + 1
        parts = [
            f"{self.step}: epoch {epoch}/{trainer.max_epochs}, batch {batch_idx + 1}/{batches}"
        ]
        if self._loss_sum is not None:
            parts.append(f"loss {float(self._loss_sum) / self._batches:.4g}")
        done = trainer.current_epoch - self._first_epoch + (batch_idx + 1) / batches
        left = trainer.max_epochs - trainer.current_epoch - (batch_idx + 1) / batches
        elapsed = now - self._started
        parts += [f"{duration(elapsed)} elapsed", f"ETA {duration(elapsed / done * left)}"]
        self._say(", ".join(parts))

    def on_validation_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._validated = not trainer.sanity_checking

    def on_train_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        if not self._shown(trainer):
            return
        epoch = trainer.current_epoch + 1
        parts = [f"{self.step}: epoch {epoch}/{trainer.max_epochs}"]
        if self._loss_sum is not None:
            parts.append(f"loss {float(self._loss_sum) / self._batches:.4g}")
        if self._validated:
            figures = {k: float(v) for k, v in trainer.callback_metrics.items()}
            shown = step_figures(self.step, figures, "val")
            if shown:
                parts.append(f"val {shown}")
        elapsed = time.perf_counter() - self._started
        parts.append(f"{duration(elapsed)} elapsed")
        done = epoch - self._first_epoch
        if done > 0 and epoch < trainer.max_epochs:
            parts.append(f"ETA {duration(elapsed / done * (trainer.max_epochs - epoch))}")
        self._say(", ".join(parts))
