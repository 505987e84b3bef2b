"""LightningModule of a scene model (render-and-compare): trained on train-image rays,
evaluated with a frozen teacher whose estimates the RenderCompareRefinement callback refines."""

from __future__ import annotations

from typing import Any

import torch
import torchvision
from lightning.pytorch.loggers import TensorBoardLogger
from torch import Tensor, nn

from pae.data.camera import scale_intrinsics
from pae.data.transforms import ImageTransform
from pae.errors import ConfigError
from pae.lit.base import OptimizerFactory, PaeModule, SchedulerFactory
from pae.lit.evaluation import PoseEvaluation
from pae.models.base import PoseRegressor
from pae.models.scene_model import SceneModel
from pae.refine.render_compare import compare_size, grey, zncc

SCENE_MODEL_METHODS = ["teacher", "mean_pose"]
MEAN_IMAGE_ROWS = 1024
"""Train images (evenly spaced) averaged into the mean-image baseline."""


def fitted_psnr_db(rendered: Tensor, target: Tensor) -> Tensor:
    """PSNR [B] (dB) of renderings [B, 3, h, w] against targets after a least-squares gain
    and bias per image and channel (the appearance a scene model cannot know)."""
    x, y = rendered.flatten(2), target.flatten(2)
    xc, yc = x - x.mean(-1, keepdim=True), y - y.mean(-1, keepdim=True)
    gain = (xc * yc).sum(-1, keepdim=True) / xc.square().sum(-1, keepdim=True).clamp_min(1e-9)
    mse = (gain * xc - yc).square().mean((1, 2))
    return -10.0 * torch.log10(mse.clamp_min(1e-10))


def grey_zncc(rendered: Tensor, target: Tensor) -> Tensor:
    """ZNCC [B] of the grey images of renderings and targets [B, 3, h, w]."""
    a, b = grey(rendered).flatten(1), grey(target).flatten(1)
    return zncc(a, b, torch.ones_like(a))


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
    """Trains ``scene_model`` (when it has parameters) on ray batches: the mean squared error
    of its renderings, as each ray's train image's appearance saw them, plus ``tv_weight``
    times its total variation. ``fit_trim``: from epoch ``fit_trim_from_epoch`` (0-based) on,
    the share of each batch's rays with the largest errors left out of the mean (what the
    grid cannot explain: occluders, glare); ``appearance_lr``: the appearance codes' learning
    rate (None: the optimiser's). Evaluates with the frozen ``teacher``: logs ``teacher`` and
    ``mean_pose``, the model's quality at the split's poses (``{split}/scene_model/psnr_db`` after a
    per-image gain and bias fit, ``.../zncc`` of grey images, and ``.../mean_image_psnr_db``
    for the mean train image, a model that ignores the pose) on the first ``quality_images``
    queries at ``quality_size`` px, and keeps every query for the refinement callback
    (``eval_outputs``: its image area-resized to ``query_width`` px wide, the refiner's
    compare width, with the intrinsics of that size; None: as evaluated). The quality
    figures read the split's poses and images: they measure the scene model, they steer
    nothing.
    """

    def __init__(
        self,
        scene_model: SceneModel,
        teacher: PoseRegressor,
        optimizer: OptimizerFactory,
        scene_names: list[str],
        configs: dict[str, Any],
        scheduler: SchedulerFactory | None = None,
        tv_weight: float = 1e-3,
        fit_trim: float = 0.0,
        fit_trim_from_epoch: int = 1,
        appearance_lr: float | None = None,
        quality_size: int = 24,
        quality_images: int = 128,
        gallery_size: int = 8,
        query_width: int | None = None,
    ) -> None:
        super().__init__(optimizer, scheduler)
        self.save_hyperparameters({**configs, "scene_names": list(scene_names)})
        self.scene_model = scene_model
        self.teacher = teacher.eval().requires_grad_(False)
        self.scene_names = list(scene_names)
        self.tv_weight = tv_weight
        if not 0.0 <= fit_trim < 1.0:
            raise ConfigError(f"scene_model.fit_trim must be in [0, 1), got {fit_trim}")
        self.fit_trim = fit_trim
        self.fit_trim_from_epoch = fit_trim_from_epoch
        self.appearance_lr = appearance_lr
        self.quality_size = quality_size
        self.quality_images = quality_images
        self.gallery_size = gallery_size
        self.query_width = query_width
        self.evaluation = PoseEvaluation(SCENE_MODEL_METHODS, scene_names)
        self.register_mean_pose_baseline(len(scene_names))
        self.register_buffer("mean_image", torch.zeros(3, quality_size, quality_size), False)
        self.eval_outputs: list[dict[str, Tensor]] = []
        self._quality: list[Tensor] = []
        self._gallery: list[Tensor] = []
        self._split_intrinsics: dict[str, Tensor] = {}

    def train(self, mode: bool = True) -> SceneModelModule:
        super().train(mode)
        self.teacher.eval()
        return self

    def trainable_parameters(self) -> list[nn.Parameter] | list[dict[str, Any]]:
        appearance = getattr(self.scene_model, "appearance", None)
        if self.appearance_lr is None or appearance is None:
            return list(self.scene_model.parameters())
        codes = set(appearance.parameters())
        rest = [p for p in self.scene_model.parameters() if p not in codes]
        return [{"params": rest}, {"params": list(codes), "lr": self.appearance_lr}]

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        rgb, _, _ = self.scene_model.render_rays(
            batch["origins"], batch["directions"], batch["scene"], jitter=True
        )
        rgb = self.scene_model.with_appearance(rgb, batch["appearance"])
        errors = (rgb - batch["rgb"]).square().mean(1)  # [R]
        mse = errors.mean()
        loss = mse
        if self.fit_trim and self.current_epoch >= self.fit_trim_from_epoch:
            keep = len(errors) - int(self.fit_trim * len(errors))
            loss = errors.topk(keep, largest=False, sorted=False).values.mean()
        tv = self.scene_model.total_variation()
        self.log_dict(
            {"train/mse": mse, "train/psnr_db": -10 * torch.log10(mse), "train/tv": tv},
            prog_bar=True,
        )
        return loss + self.tv_weight * tv

    def _fill_mean_image(self) -> None:
        """The mean of at most ``MEAN_IMAGE_ROWS`` evenly spaced train images at
        ``quality_size`` px, read 256 rows at a time."""
        data = self.trainer.datamodule
        dataset = data.datasets["train"]
        count = min(len(dataset), MEAN_IMAGE_ROWS)
        picked = torch.linspace(0, len(dataset) - 1, count).round().long().tolist()
        total = torch.zeros_like(self.mean_image, dtype=torch.float64)
        for start in range(0, count, 256):
            rows = picked[start : start + 256]
            images = data.preprocess(dataset.__getitems__(rows)["image"], train=False)
            rgb = ImageTransform.unnormalize_batch(images)
            small = nn.functional.interpolate(rgb, size=self.mean_image.shape[1:], mode="area")
            total += small.double().sum(0)
        self.mean_image.copy_(total / max(count, 1))

    def _intrinsics(self, split: str, index: Tensor) -> Tensor:
        """Intrinsics [B, 4] of the split's rows ``index`` [B] (the split's table computed
        once per evaluation epoch)."""
        if split not in self._split_intrinsics:
            self._split_intrinsics[split] = self.trainer.datamodule.intrinsics(split)
        return self._split_intrinsics[split][index.cpu()]

    def on_validation_epoch_start(self) -> None:
        self.eval_outputs, self._quality, self._gallery = [], [], []
        self._split_intrinsics = {}
        if not self.mean_image.any():
            self._fill_mean_image()

    def on_test_epoch_start(self) -> None:
        self.on_validation_epoch_start()

    @torch.no_grad()
    def _measure_quality(self, rgb: Tensor, batch: dict[str, Tensor], split: str) -> None:
        """Render the first ``quality_images`` queries at their true poses and compare."""
        seen = sum(len(q) for q in self._quality)
        keep = min(len(rgb), self.quality_images - seen)
        if keep <= 0:
            return
        size = self.quality_size
        target = nn.functional.interpolate(rgb[:keep], size=(size, size), mode="area")
        h, w = rgb.shape[-2:]
        intrinsics = self._intrinsics(split, batch["index"][:keep])
        rendering = self.scene_model.render(
            batch["pose"][:keep],
            batch["scene"][:keep],
            scale_intrinsics(intrinsics.to(rgb.device), size / w, size / h),
            size,
            size,
        )
        mean_image = self.mean_image.expand_as(target)
        self._quality.append(
            torch.stack(
                [
                    fitted_psnr_db(rendering.rgb, target),
                    grey_zncc(rendering.rgb, target),
                    fitted_psnr_db(mean_image, target),
                ],
                1,
            )
        )
        if not self._gallery:
            n = min(self.gallery_size, keep)
            self._gallery = [target[:n], rendering.rgb[:n].clamp(0, 1)]

    def evaluate(self, batch: dict[str, Tensor], batch_idx: int, split: str) -> None:
        gt, scene, index = batch["pose"], batch["scene"], batch["index"]
        answer = self.teacher.estimate(batch["image"], scene)
        self.evaluation.update(split, "teacher", answer.raw_pose, gt, scene, index)
        self.evaluation.update(split, "mean_pose", self.mean_poses[scene], gt, scene, index)
        rgb = ImageTransform.unnormalize_batch(batch["image"])
        self._measure_quality(rgb, batch, split)
        intrinsics = self._intrinsics(split, index).to(rgb.device)
        query, intrinsics = compare_queries(rgb, intrinsics, self.query_width)
        self.eval_outputs.append(
            {
                "image": query,
                "intrinsics": intrinsics,
                "estimate": answer.pose,
                "scene_estimate": answer.scene,
                "pose": gt,
                "scene": scene,
                "index": index,
            }
        )

    def _log_quality(self, split: str) -> None:
        if not self._quality:
            return
        psnr, similarity, mean_psnr = torch.cat(self._quality).mean(0)
        prefix = f"{split}/scene_model"
        self.log_dict(
            {
                f"{prefix}/psnr_db": psnr,
                f"{prefix}/zncc": similarity,
                f"{prefix}/mean_image_psnr_db": mean_psnr,
            }
        )
        for logger in self.loggers:
            if isinstance(logger, TensorBoardLogger) and self._gallery:
                grid = torchvision.utils.make_grid(
                    torch.cat(self._gallery), nrow=len(self._gallery[0])
                )
                logger.experiment.add_image(f"{split}/scene_model/renders", grid, self.global_step)

    def on_validation_epoch_end(self) -> None:
        super().on_validation_epoch_end()
        self._log_quality("val")

    def on_test_epoch_end(self) -> None:
        super().on_test_epoch_end()
        self._log_quality("test")
