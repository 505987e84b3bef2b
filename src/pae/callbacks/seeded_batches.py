"""Training draws from (seed, epoch, batch): a resumed run trains on what an uninterrupted
one would (data order, augmentation, dropout), to the last digit with the same threads."""

from __future__ import annotations

from typing import Any

import lightning as L

from pae.callbacks.finite_loss import TrainBatchEndCallback
from pae.core.streams import seed_global_for_batch


class SeededBatches(TrainBatchEndCallback):
    """Seeds torch's global generators (:func:`pae.core.streams.seed_global_for_batch`) when a
    training epoch starts, before its loader draws the epoch's order, and after each batch for
    the next one, before the batch is fetched and augmented, so that nothing drawn before (an
    earlier epoch, validation, the run's start) reaches them. ``step`` names the step's
    stream."""

    def __init__(self, seed: int, step: str) -> None:
        self.seed = seed
        self.step = step

    def _seed(self, trainer: L.Trainer, batch: int) -> None:
        seed_global_for_batch(
            self.seed, self.step, trainer.current_epoch, batch, trainer.global_rank
        )

    def on_train_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._seed(trainer, -1)

    def after_train_batch(self, trainer: L.Trainer, outputs: Any, batch_idx: int) -> None:
        self._seed(trainer, batch_idx + 1)
