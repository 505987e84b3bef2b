"""LightningModule of a scene model (render-and-compare): trained on train-image rays,
evaluated with a frozen teacher whose estimates the RenderCompareCallback refines."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor, nn

from pae.core.camera import scale_intrinsics
from pae.core.streams import seeded_global
from pae.data.transforms import ImageTransform
from pae.lit.base import OptimizerFactory, PaeModule, SchedulerFactory
from pae.lit.eval_outputs import EVAL
from pae.lit.evaluation import PoseEvaluation
from pae.models.base import PoseRegressor
from pae.models.latents import compute_teacher_latents
from pae.render_compare.images import compare_size
from pae.render_compare.scene_starts import latent_starts
from pae.scene_model.base import SceneModel
from pae.scene_model.rays import RayBatches

SCENE_MODEL_METHODS = ["teacher", "mean_pose"]


def compare_queries(rgb: Tensor, intrinsics: Tensor, width: int | None) -> tuple[Tensor, Tensor]:
    """Query images RGB [B, 3, h, w] in [0, 1] and their intrinsics [B, 4] (px) -> the same
    area-resized to ``width`` px wide (render-and-compare's compare width, the height kept in
    proportion) with the intrinsics of that size; ``width`` None: as they are."""
    if width is None:
        return rgb, intrinsics
    h, w = rgb.shape[-2:]
    size = compare_size(h, w, width)
    small = nn.functional.interpolate(rgb, size=size, mode="area")
    return small, scale_intrinsics(intrinsics, size[1] / w, size[0] / h)


class SceneModelModule(PaeModule):
    """Trains ``scene_model`` (when it has parameters) on ray batches (pae.scene_model.rays: each
    with the seed its rendering draws from): the mean squared error
    of its renderings, as each ray's train image's appearance saw them, plus ``tv_weight``
    times its total variation. ``fit_trim``: from epoch ``fit_trim_from_epoch`` (0-based) on,
    the share of each batch's rays with the largest errors left out of the mean (what the
    grid cannot explain: occluders, glare); ``depth_weight``: times the mean depth error
    (``SceneModel.depth_error``) of the batch's rays through triangulated keypoints, where it
    has them (``scene_model.depth_rays``); ``appearance_lr``: the appearance codes' learning
    rate (None: the optimiser's). Evaluates with the frozen ``teacher``: logs ``teacher`` and
    ``mean_pose`` and keeps every query for the refinement callback (``eval_outputs``, keyed by
    ``pae.lit.eval_outputs.EVAL``: its
    image area-resized to ``query_width`` px wide, the refiner's compare width, with the
    intrinsics of that size; None: as evaluated); without a teacher (a fit alone) it logs
    ``mean_pose`` and keeps nothing. The model's quality at the split's poses
    is a callback's (``pae.callbacks.scene_quality``).
    """

    def __init__(
        self,
        scene_model: SceneModel,
        teacher: PoseRegressor | None,
        optimizer: OptimizerFactory,
        scene_names: list[str],
        configs: dict[str, Any],
        scheduler: SchedulerFactory | None = None,
        tv_weight: float = 1e-3,
        fit_trim: float = 0.0,
        fit_trim_from_epoch: int = 1,
        depth_weight: float = 0.0,
        appearance_lr: float | None = None,
        query_width: int | None = None,
    ) -> None:
        super().__init__(optimizer, scheduler)
        self.save_hyperparameters({**configs, "scene_names": list(scene_names)})
        self.scene_model = scene_model
        self.teacher = None if teacher is None else teacher.eval().requires_grad_(False)
        self.scene_names = list(scene_names)
        self.tv_weight = tv_weight
        self.fit_trim = fit_trim
        self.fit_trim_from_epoch = fit_trim_from_epoch
        self.depth_weight = depth_weight
        self.appearance_lr = appearance_lr
        self.query_width = query_width
        methods = SCENE_MODEL_METHODS if teacher is not None else ["mean_pose"]
        self.evaluation = PoseEvaluation(methods, scene_names)
        self.register_mean_pose_baseline(len(scene_names))
        self.eval_outputs: list[dict[str, Tensor]] = []
        self._split_intrinsics: dict[str, Tensor] = {}
        self._store: dict[str, Tensor] | None = None  # the teacher's train latents

    def train(self, mode: bool = True) -> SceneModelModule:
        super().train(mode)
        if self.teacher is not None:
            self.teacher.eval()
        return self

    def on_train_epoch_start(self) -> None:
        """The model's stage of the fit (:meth:`SceneModel.fit_stage`: the voxel grid grows);
        the optimiser built again where its parameters changed."""
        if self.scene_model.fit_stage(self.current_epoch, fresh=self.global_step == 0):
            self.trainer.strategy.setup_optimizers(self.trainer)

    def scheduled_steps(self) -> int:
        """The steps left: an optimiser built again when the grid grows schedules the rest of
        the fit (the learning rate starts over when the grid grows)."""
        return max(1, super().scheduled_steps() - self.global_step)

    def on_train_end(self) -> None:
        """Release the ray store's images (:meth:`RayBatches.release`): the evaluation after
        the fit does not read them (333 MB at 7-Scenes size)."""
        loader = self.trainer.train_dataloader
        if isinstance(getattr(loader, "dataset", None), RayBatches):
            loader.dataset.release()

    def trainable_parameters(self) -> list[nn.Parameter] | list[dict[str, Any]]:
        appearance = getattr(self.scene_model, "appearance", None)
        if self.appearance_lr is None or appearance is None:
            return list(self.scene_model.parameters())
        codes = set(appearance.parameters())
        rest = [p for p in self.scene_model.parameters() if p not in codes]
        return [{"params": rest}, {"params": list(codes), "lr": self.appearance_lr}]

    def training_step(self, batch: dict[str, Any], batch_idx: int) -> Tensor:
        with seeded_global(batch["seed"], self.device):  # the samples' jitter: the batch's own
            rgb, _, _ = self.scene_model.render_rays(
                batch["origins"], batch["directions"], batch["scene"], jitter=True
            )
            depth = batch.get("depth")
            if depth is not None:
                depth_error = self.scene_model.depth_error(
                    depth["origins"], depth["directions"], depth["scene"], depth["target"]
                ).mean()
        rgb = self.scene_model.with_appearance(rgb, batch["appearance"], batch.get("pixels"))
        errors = (rgb - batch["rgb"]).square().mean(1)  # [R]
        mse = errors.mean()
        loss = mse
        if self.fit_trim and self.current_epoch >= self.fit_trim_from_epoch:
            keep = len(errors) - int(self.fit_trim * len(errors))
            loss = errors.topk(keep, largest=False, sorted=False).values.mean()
        tv = self.scene_model.total_variation()
        logged = {"train/mse": mse, "train/psnr_db": -10 * torch.log10(mse), "train/tv": tv}
        if depth is not None:
            logged["train/depth_error"] = depth_error
            loss = loss + self.depth_weight * depth_error
        self.log_train(logged, prog_bar=True)
        return loss + self.tv_weight * tv

    def scene_starts(self, images: Tensor, scene_poses: Tensor) -> Tensor:
        """Render-and-compare's starts [B, S, K, 7] in every scene for a multi-scene teacher's
        queries (:func:`pae.render_compare.scene_starts.latent_starts`, from the teacher's
        poses for every scene [B, S, 7] and its latents of the train images, computed once)."""
        if self._store is None:
            data = self.trainer.datamodule
            self._store = compute_teacher_latents(self.teacher, data, self.device).tensors
        store = {key: value.to(self.device) for key, value in self._store.items()}
        joint = torch.cat([store["z_x"], store["z_q"]], -1)
        latents = self.teacher.scene_latents(images)
        return latent_starts(scene_poses, latents, joint, store["pose"], store["scene"])

    def _intrinsics(self, split: str, index: Tensor) -> Tensor:
        """Intrinsics [B, 4] of the split's rows ``index`` [B] (the split's table computed
        once per evaluation epoch)."""
        if split not in self._split_intrinsics:
            self._split_intrinsics[split] = self.trainer.datamodule.intrinsics(split)
        return self._split_intrinsics[split][index.cpu()]

    def on_validation_epoch_start(self) -> None:
        self.eval_outputs, self._split_intrinsics = [], {}

    def on_test_epoch_start(self) -> None:
        self.on_validation_epoch_start()

    def evaluate(self, batch: dict[str, Tensor], batch_idx: int, split: str) -> None:
        gt, scene, index = batch["pose"], batch["scene"], batch["index"]
        self.evaluation.update(split, "mean_pose", self.mean_poses[scene], gt, scene, index)
        if self.teacher is None:
            return
        answer = self.teacher.estimate(batch["image"], scene)
        self.evaluation.update(split, "teacher", answer.raw_pose, gt, scene, index)
        rgb = ImageTransform.unnormalize_batch(batch["image"])
        intrinsics = self._intrinsics(split, index).to(rgb.device)
        query, intrinsics = compare_queries(rgb, intrinsics, self.query_width)
        outputs = {
            EVAL.image: query,
            EVAL.intrinsics: intrinsics,
            EVAL.estimate: answer.pose,
            EVAL.scene_estimate: answer.scene,
            EVAL.pose: gt,
            EVAL.scene: scene,
            EVAL.index: index,
        }
        scene_poses = self.teacher.scene_poses(batch["image"])
        if scene_poses is not None:
            outputs[EVAL.scene_poses] = self.scene_starts(batch["image"], scene_poses)
            outputs[EVAL.scene_logits] = answer.latents.scene_logits
        self.eval_outputs.append(outputs)
