"""LightningModules of a student PAE and its frozen teacher APR: StudentEvaluator evaluates
them (pae-eval), StudentModule also trains the PAE."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from pae.core.geometry import normalize_pose
from pae.core.losses import LATENT_LOSSES, LearnedPoseLoss, latent_distance
from pae.lit.base import EvaluationModule, OptimizerFactory, PaeModule, SchedulerFactory
from pae.lit.eval_outputs import EVAL
from pae.lit.evaluation import PoseEvaluation
from pae.models.base import Latents, PoseRegressor
from pae.models.pae import PoseAutoEncoder

STUDENT_METHODS = ["teacher", "student", "student_gt", "mean_pose"]


class StudentEvaluator(EvaluationModule):
    """A frozen teacher and its PAE, evaluated (what `pae-eval` runs; no loss, no optimiser).

    Logs `teacher` (the teacher's estimate), `student` (the PAE encodes that estimate, the
    frozen heads regress it back), `student_gt` (the PAE encodes the ground truth) and the
    `mean_pose` baseline. During evaluation it keeps every query's teacher latents, estimate
    and dataset index in `eval_outputs` for the test-time refinement callback.
    """

    def __init__(
        self, teacher: PoseRegressor, pae: PoseAutoEncoder, scene_names: list[str]
    ) -> None:
        super().__init__()
        if pae.latent_dim != teacher.latent_dim:
            raise ValueError(
                f"pae.latent_dim={pae.latent_dim} does not match the teacher's latent size "
                f"{teacher.latent_dim}"
            )
        self.scene_names = list(scene_names)
        self.teacher = teacher.eval().requires_grad_(False)
        self.pae = pae
        self.evaluation = PoseEvaluation(STUDENT_METHODS, scene_names)
        self.register_mean_pose_baseline(len(scene_names))
        self.eval_outputs: list[dict[str, Tensor]] = []

    def train(self, mode: bool = True) -> StudentEvaluator:
        super().train(mode)
        self.teacher.eval()
        return self

    def on_validation_epoch_start(self) -> None:
        self.eval_outputs = []

    def on_test_epoch_start(self) -> None:
        self.eval_outputs = []

    def evaluate(self, batch: dict[str, Tensor], batch_idx: int, split: str) -> None:
        gt, scene, index = batch["pose"], batch["scene"], batch["index"]
        answer = self.teacher.estimate(batch["image"], scene)
        student_pose = self.teacher.regress(self.pae(answer.pose, answer.scene))
        student_gt_pose = self.teacher.regress(self.pae(gt, scene))
        predictions = {
            "teacher": answer.raw_pose,
            "student": student_pose,
            "student_gt": student_gt_pose,
            "mean_pose": self.mean_poses[scene],
        }
        for method, pred in predictions.items():
            self.evaluation.update(split, method, pred, gt, scene, index)
        self.eval_outputs.append(
            {
                "z": answer.latents.joint(),
                EVAL.estimate: answer.pose,
                EVAL.pose: gt,
                EVAL.scene: scene,
                EVAL.scene_estimate: answer.scene,
                EVAL.index: index,
            }
        )


class StudentModule(PaeModule, StudentEvaluator):
    """L = latent(z_x, ẑ_x) + latent(z_q, ẑ_q) + L_p(teacher.regress(ẑ), p_gt).

    The teacher is frozen (eval mode, no parameter gradients) but its heads stay in the graph,
    so the pose loss trains the PAE through them. Batches either carry cached teacher outputs
    (`z_x`, `z_q`, `teacher_pose`) or images, in which case the teacher runs on them; a
    multi-scene teacher's targets are the latents of the true scene.
    `pae_input` is "gt" (the ground-truth pose, paper) or "teacher" (the teacher's estimate).
    It evaluates as StudentEvaluator does; PaeModule adds the optimiser.
    """

    def __init__(
        self,
        teacher: PoseRegressor,
        pae: PoseAutoEncoder,
        loss: LearnedPoseLoss,
        optimizer: OptimizerFactory,
        scene_names: list[str],
        teacher_config: dict[str, Any],
        pae_config: dict[str, Any],
        scheduler: SchedulerFactory | None = None,
        latent_loss: str = "l2",
        pae_input: str = "gt",
    ) -> None:
        if pae_input not in ("gt", "teacher"):
            raise ValueError(f"unknown student.pae_input {pae_input!r}; choose 'gt' or 'teacher'")
        if latent_loss not in LATENT_LOSSES:
            raise ValueError(
                f"unknown student.latent_loss {latent_loss!r}; choose one of {LATENT_LOSSES}"
            )
        super().__init__(optimizer, scheduler, teacher=teacher, pae=pae, scene_names=scene_names)
        self.save_hyperparameters(
            {
                "teacher_config": teacher_config,
                "pae_config": pae_config,
                "scene_names": list(scene_names),
                "latent_loss": latent_loss,
                "pae_input": pae_input,
            }
        )
        self.loss = loss
        self.latent_loss = latent_loss
        self.pae_input = pae_input

    def student_loss(self, batch: dict[str, Tensor]) -> dict[str, Tensor]:
        """Loss terms for a cached-latent or image batch."""
        if "z_x" in batch:
            target = Latents(batch["z_x"], batch["z_q"])
            teacher_pose = batch["teacher_pose"]
        else:
            with torch.no_grad():
                teacher_pose, target = self.teacher(batch["image"], batch["scene"])
        source = batch["pose"] if self.pae_input == "gt" else normalize_pose(teacher_pose)
        latents = self.pae(source, batch["scene"])
        pred = self.teacher.regress(latents)
        terms = self.loss(pred, batch["pose"])
        latent_x = latent_distance(latents.x, target.x, self.latent_loss)
        latent_q = latent_distance(latents.q, target.q, self.latent_loss)
        return {
            "loss": latent_x + latent_q + terms.total,
            "latent_x": latent_x,
            "latent_q": latent_q,
            "pose": terms.total,
            "pos_loss": terms.position,
            "rot_loss": terms.orientation,
        }

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        terms = self.student_loss(batch)
        figures = {f"train/{k}": v for k, v in terms.items()}
        self.log_train(figures | {"train/s_x": self.loss.s_x, "train/s_q": self.loss.s_q})
        return terms["loss"]

    def trainable_parameters(self) -> list[nn.Parameter]:
        return list(self.pae.parameters()) + list(self.loss.parameters())
