"""The TensorBoard logger of pae runs: curves as scalar charts, final figures elsewhere."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from lightning.pytorch.loggers import TensorBoardLogger

FINAL_FIGURE_PREFIXES = ("test/", "bench/")
"""Keys logged once per run (test figures, timings): no scalar chart of one point each. They
reach TensorBoard as the TEXT table ``results`` (pae.runs.hparams.log_hparams), and
metrics.json holds them all."""


class CurvesTensorBoardLogger(TensorBoardLogger):
    """Lightning's TensorBoardLogger without scalar charts for FINAL_FIGURE_PREFIXES: the
    Scalars tab shows the curves (train/, val/, learning rate), whose last values the
    HParams tab shows."""

    def log_metrics(self, metrics: Mapping[str, Any], step: int | None = None) -> None:
        curves = {k: v for k, v in metrics.items() if not k.startswith(FINAL_FIGURE_PREFIXES)}
        if curves:
            super().log_metrics(curves, step)
