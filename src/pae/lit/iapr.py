"""LightningModule for the iterative APR: trained on train images with starting poses drawn
around the truth, evaluated from the teacher's estimate for 1..n iterations."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from pae.core.geometry import canonicalize_quaternion, relative_pose
from pae.core.losses import LearnedPoseLoss
from pae.core.pose_sampling import perturb_poses
from pae.lit.base import OptimizerFactory, PaeModule, SchedulerFactory
from pae.lit.evaluation import PoseEvaluation
from pae.models.base import PoseRegressor
from pae.models.iapr import IterativeAPR
from pae.models.pae import PoseAutoEncoder
from pae.relative.refiners import IterativeAPRRefiner


class IAPRModule(PaeModule):
    """Trains an IterativeAPR with a frozen PAE (and evaluates it from the frozen teacher's
    estimates).

    Training: a train image (augmented) and a starting pose drawn around its true pose by
    `perturb_poses(position_m, orientation_deg)`; the target is the relative pose from the
    start to the truth. No test pose or image is read. Evaluation: the teacher estimates
    the pose (and scene), `iapr_{i}` is the pose after i = 1..iterations corrections; each
    reports position and orientation (with refine_orientation=False the teacher's
    orientation is kept).
    """

    def __init__(
        self,
        iapr: IterativeAPR,
        teacher: PoseRegressor,
        pae: PoseAutoEncoder,
        loss: LearnedPoseLoss,
        optimizer: OptimizerFactory,
        scene_names: list[str],
        configs: dict[str, Any],
        scheduler: SchedulerFactory | None = None,
        position_m: float = 0.5,
        orientation_deg: float = 8.0,
        iterations: int = 3,
        refine_orientation: bool = True,
    ) -> None:
        super().__init__(optimizer, scheduler)
        if iapr.latent_dim != pae.latent_dim:
            raise ValueError(
                f"iapr latent_dim={iapr.latent_dim} does not match the PAE's {pae.latent_dim}"
            )
        self.save_hyperparameters({**configs, "scene_names": list(scene_names)})
        self.iapr = iapr
        self.teacher = teacher.eval().requires_grad_(False)
        self.pae = pae.eval().requires_grad_(False)
        self.loss = loss
        self.position_m = position_m
        self.orientation_deg = orientation_deg
        self.iterations = iterations
        self.refine_orientation = refine_orientation
        methods = ["teacher", *(f"iapr_{i}" for i in range(1, iterations + 1))]
        self.evaluation = PoseEvaluation(methods, scene_names)

    def train(self, mode: bool = True) -> IAPRModule:
        super().train(mode)
        self.teacher.eval()
        self.pae.eval()
        return self

    def starting_poses(self, batch: dict[str, Tensor]) -> Tensor:
        """A train batch -> starting poses [B, 7] around its true poses."""
        return perturb_poses(batch["pose"], self.position_m, self.orientation_deg)

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        start = self.starting_poses(batch)
        with torch.no_grad():
            encoding = self.pae(start, batch["scene"]).joint()
        target = relative_pose(start, batch["pose"])
        target = torch.cat([target[:, :3], canonicalize_quaternion(target[:, 3:])], dim=-1)
        terms = self.loss(self.iapr(batch["image"], encoding), target)
        self.log_train({"train/loss": terms.total, "train/pos_loss": terms.position})
        return terms.total

    def trainable_parameters(self) -> list[nn.Parameter]:
        return list(self.iapr.parameters()) + list(self.loss.parameters())

    def evaluate(self, batch: dict[str, Tensor], batch_idx: int, split: str) -> None:
        images, gt, scene, index = batch["image"], batch["pose"], batch["scene"], batch.get("index")
        answer = self.teacher.estimate(images, scene)
        self.evaluation.update(split, "teacher", answer.raw_pose, gt, scene, index)
        method = IterativeAPRRefiner(self.iapr, self.pae, self.iterations, self.refine_orientation)
        steps = method.iterates(images, answer.pose, answer.scene)
        for i, pose in enumerate(steps, start=1):
            self.evaluation.update(split, f"iapr_{i}", pose, gt, scene, index)
