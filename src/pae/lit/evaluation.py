"""Evaluation wiring: pose-error metrics per split and method, logged as `{split}/{method}/...`."""

from __future__ import annotations

import lightning as L
from torch import Tensor, nn

from pae.core.metrics import PoseErrorMetric

EVAL_SPLITS = ("val", "test")


class PoseEvaluation(nn.Module):
    """One PoseErrorMetric per (split, method); `log` writes `{split}/{method}/{figure}`."""

    def __init__(self, methods: list[str], scene_names: list[str]) -> None:
        super().__init__()
        self.methods = list(methods)
        self.metrics = nn.ModuleDict(
            {
                f"{split}_{method}": PoseErrorMetric(scene_names)
                for split in EVAL_SPLITS
                for method in methods
            }
        )

    def update(
        self,
        split: str,
        method: str,
        pred: Tensor,
        target: Tensor,
        scene: Tensor,
        index: Tensor | None = None,
    ) -> None:
        """pred, target [B, 7]; scene [B]; index [B] dataset indices (each counted once)."""
        self.metrics[f"{split}_{method}"].update(pred, target, scene, index)

    def log(self, module: L.LightningModule, split: str) -> None:
        for method in self.methods:
            metric = self.metrics[f"{split}_{method}"]
            if not metric.update_called:
                continue
            figures = {f"{split}/{method}/{key}": value for key, value in metric.compute().items()}
            module.log_dict(figures, sync_dist=False)
            metric.reset()
