"""A scene model's quality at an evaluated split's poses, and its render gallery."""

from __future__ import annotations

from typing import Any

import lightning as L
import torch
import torchvision
from lightning.pytorch.loggers import TensorBoardLogger
from torch import Tensor, nn

from pae.core.camera import scale_intrinsics
from pae.data.transforms import ImageTransform
from pae.render_compare.images import grey, zncc

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


def mean_train_image(data: Any, size: int) -> Tensor:
    """The mean [3, size, size] of at most ``MEAN_IMAGE_ROWS`` evenly spaced train images of
    ``data`` (a PoseDataModule) at ``size`` px, read 256 rows at a time."""
    dataset = data.datasets["train"]
    count = min(len(dataset), MEAN_IMAGE_ROWS)
    picked = torch.linspace(0, len(dataset) - 1, count).round().long().tolist()
    total = torch.zeros(3, size, size, dtype=torch.float64)
    for start in range(0, count, 256):
        rows = picked[start : start + 256]
        images = data.preprocess(dataset.__getitems__(rows)["image"], train=False)
        rgb = ImageTransform.unnormalize_batch(images)
        total += nn.functional.interpolate(rgb, size=(size, size), mode="area").double().sum(0)
    return (total / max(count, 1)).float()


class SceneModelQuality(L.Callback):
    """The scene model of a SceneModelModule rendered at the true poses of the first
    ``images`` queries of each validation and test run, at ``size`` px: logs
    ``{split}/scene_model/psnr_db`` (after a per-image gain and bias fit), ``.../zncc`` (grey
    images) and ``.../mean_image_psnr_db`` (the mean train image: a model that ignores the
    pose), and a gallery of ``gallery_size`` queries above their renderings to TensorBoard
    (``{split}/scene_model/renders``). The figures read the split's poses and images: they
    measure the scene model, they steer nothing."""

    def __init__(self, size: int = 24, images: int = 128, gallery_size: int = 8) -> None:
        self.size = size
        self.images = images
        self.gallery_size = gallery_size
        self.mean_image: Tensor | None = None
        self._figures: list[Tensor] = []
        self._gallery: list[Tensor] = []
        self._intrinsics: Tensor | None = None

    def _start(self, trainer: L.Trainer, split: str) -> None:
        self._figures, self._gallery = [], []
        data = trainer.datamodule
        self._intrinsics = data.intrinsics(split)
        if self.mean_image is None:
            self.mean_image = mean_train_image(data, self.size)

    def on_validation_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._start(trainer, "val")

    def on_test_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._start(trainer, "test")

    @torch.no_grad()
    def _measure(self, pl_module: L.LightningModule, batch: dict[str, Tensor]) -> None:
        """Render the batch's first queries (up to ``images`` in all) and compare."""
        keep = min(len(batch["pose"]), self.images - sum(len(f) for f in self._figures))
        if keep <= 0:
            return
        rgb = ImageTransform.unnormalize_batch(batch["image"][:keep])
        target = nn.functional.interpolate(rgb, size=(self.size, self.size), mode="area")
        h, w = rgb.shape[-2:]
        intrinsics = self._intrinsics[batch["index"][:keep].cpu()].to(rgb.device)
        rendering = pl_module.scene_model.render(
            batch["pose"][:keep],
            batch["scene"][:keep],
            scale_intrinsics(intrinsics, self.size / w, self.size / h),
            self.size,
            self.size,
        )
        mean_image = self.mean_image.to(target.device).expand_as(target)
        figures = [
            fitted_psnr_db(rendering.rgb, target),
            grey_zncc(rendering.rgb, target),
            fitted_psnr_db(mean_image, target),
        ]
        self._figures.append(torch.stack(figures, 1))
        if not self._gallery:
            n = min(self.gallery_size, keep)
            self._gallery = [target[:n], rendering.rgb[:n].clamp(0, 1)]

    def on_validation_batch_end(
        self,
        trainer: L.Trainer,
        pl_module: L.LightningModule,
        outputs: Any,
        batch: dict[str, Tensor],
        batch_idx: int,
        dataloader_idx: int = 0,
    ) -> None:
        self._measure(pl_module, batch)

    on_test_batch_end = on_validation_batch_end

    def _log(self, trainer: L.Trainer, pl_module: L.LightningModule, split: str) -> None:
        if not self._figures:
            return
        psnr, similarity, mean_psnr = torch.cat(self._figures).mean(0)
        prefix = f"{split}/scene_model"
        pl_module.log_dict(
            {
                f"{prefix}/psnr_db": psnr,
                f"{prefix}/zncc": similarity,
                f"{prefix}/mean_image_psnr_db": mean_psnr,
            }
        )
        for logger in trainer.loggers:
            if isinstance(logger, TensorBoardLogger) and self._gallery:
                grid = torchvision.utils.make_grid(
                    torch.cat(self._gallery), nrow=len(self._gallery[0])
                )
                logger.experiment.add_image(f"{prefix}/renders", grid, trainer.global_step)

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._log(trainer, pl_module, "val")

    def on_test_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._log(trainer, pl_module, "test")
