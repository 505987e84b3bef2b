"""Evaluating test-time methods that read the query image (``pae.refine.ImageRefiner``) from
trained checkpoints: what `pae-eval method_ckpts=[...]` runs (no loss, no optimiser)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from torch import Tensor, nn

from pae.lit.base import EvaluationModule
from pae.lit.evaluation import PoseEvaluation
from pae.models.base import PoseRegressor
from pae.relative.refiners import ImageRefiner

MethodFactory = Callable[[Any], ImageRefiner]
"""Builds a method from the data module (its train poses and images, the method's store)."""


class ImageMethodEvaluator(EvaluationModule):
    """A frozen teacher and a test-time method built on the data: logs ``{split}/{name}/...``
    for the method's poses from the teacher's estimates. ``networks``: the method's trained
    networks, registered so they move with the module."""

    def __init__(
        self,
        teacher: PoseRegressor,
        name: str,
        factory: MethodFactory,
        networks: list[nn.Module],
        scene_names: list[str],
    ) -> None:
        super().__init__()
        self.teacher = teacher.eval().requires_grad_(False)
        self.networks = nn.ModuleList(n.eval().requires_grad_(False) for n in networks)
        self.name, self.factory = name, factory
        self.method: ImageRefiner | None = None
        self.evaluation = PoseEvaluation([name], scene_names)

    def setup(self, stage: str) -> None:
        self.method = self.factory(self.trainer.datamodule)

    def evaluate(self, batch: dict[str, Tensor], batch_idx: int, split: str) -> None:
        assert self.method is not None
        images, gt, scene = batch["image"], batch["pose"], batch["scene"]
        refined = self.method(images, self.teacher.estimate(images, scene)).poses
        self.evaluation.update(split, self.name, refined, gt, scene, batch.get("index"))
