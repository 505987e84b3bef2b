"""The trainer's TensorBoard loggers and the figures callbacks log to them."""

from __future__ import annotations

import lightning as L
import numpy as np
from lightning.pytorch.loggers import TensorBoardLogger


def tensorboard_loggers(trainer: L.Trainer) -> list[TensorBoardLogger]:
    """The trainer's TensorBoard loggers (none: nothing to draw for)."""
    return [lg for lg in trainer.loggers if isinstance(lg, TensorBoardLogger)]


def log_figure(loggers: list[TensorBoardLogger], tag: str, image: np.ndarray, step: int) -> None:
    """Log an RGB figure [H, W, 3] under ``tag`` at ``step`` to each of ``loggers``."""
    for logger in loggers:
        logger.experiment.add_image(tag, image, step, dataformats="HWC")
