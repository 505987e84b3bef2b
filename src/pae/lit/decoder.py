"""LightningModule that trains an image decoder on the encodings of a frozen PAE."""

from __future__ import annotations

from typing import Any

import torch
import torchvision
from lightning.pytorch.loggers import TensorBoardLogger
from torch import Tensor, nn

from pae.data.transforms import ImageTransform
from pae.lit.base import OptimizerFactory, PaeModule, SchedulerFactory
from pae.models.decoder import ImageDecoder
from pae.models.pae import PoseAutoEncoder


def image_targets(images: Tensor, size: int) -> Tensor:
    """Network-input images [B, 3, h, w] -> RGB in [0, 1] resized to [B, 3, size, size]."""
    rgb = ImageTransform.unnormalize_batch(images)
    return nn.functional.interpolate(rgb, size=(size, size), mode="area")


def psnr_db(images: Tensor, targets: Tensor) -> Tensor:
    """Peak signal-to-noise ratio [B] (dB) of images against targets [B, 3, s, s] in [0, 1]:
    10·log10(1 / MSE) per image (MSE clamped at 1e-10, i.e. at most 100 dB)."""
    mse = (images - targets).square().flatten(1).mean(1)
    return -10.0 * torch.log10(mse.clamp_min(1e-10))


def mean_train_image(datamodule: Any, size: int, chunk: int = 256) -> Tensor:
    """The mean of the train split's images [3, size, size] in [0, 1], each pre-processed as
    the decoder's targets are (evaluation crop, `image_targets`); read `chunk` rows at a
    time through the train dataset. The baseline a decoder must beat: it knows no pose."""
    dataset = datamodule.datasets["train"]
    total = torch.zeros(3, size, size, dtype=torch.float64)
    for start in range(0, len(dataset), chunk):
        rows = list(range(start, min(start + chunk, len(dataset))))
        images = datamodule.preprocess(dataset.__getitems__(rows)["image"], train=False)
        total += image_targets(images, size).double().sum(0)
    return (total / max(len(dataset), 1)).float()


class DecoderModule(PaeModule):
    """L1 between the image and the decoding of the PAE encoding of its ground-truth pose.

    The PAE is frozen. Logs `{split}/decoder/l1`, `{split}/decoder/psnr_db` (mean per-image
    PSNR of the decodings) beside `{split}/decoder/psnr_mean_image_db` (the same for the mean
    train image, a decoder that ignores the pose), and a gallery (top: images, bottom:
    reconstructions) to TensorBoard.
    """

    def __init__(
        self,
        pae: PoseAutoEncoder,
        decoder: ImageDecoder,
        optimizer: OptimizerFactory,
        scene_names: list[str],
        pae_config: dict[str, Any],
        decoder_config: dict[str, Any],
        scheduler: SchedulerFactory | None = None,
        gallery_size: int = 8,
    ) -> None:
        super().__init__(optimizer, scheduler)
        if pae.latent_dim != decoder.latent_dim:
            raise ValueError(
                f"decoder latent_dim={decoder.latent_dim} does not match the PAE's {pae.latent_dim}"
            )
        self.save_hyperparameters(
            {
                "pae_config": pae_config,
                "decoder_config": decoder_config,
                "scene_names": list(scene_names),
            }
        )
        self.pae = pae.eval().requires_grad_(False)
        self.decoder = decoder
        self.gallery_size = gallery_size
        self.register_buffer("mean_image", torch.zeros(3, decoder.size, decoder.size), False)

    def _fill_mean_image(self) -> None:
        datamodule = getattr(self.trainer, "datamodule", None)
        if datamodule is not None and hasattr(datamodule, "datasets"):
            self.mean_image.copy_(mean_train_image(datamodule, self.decoder.size))

    def on_fit_start(self) -> None:
        super().on_fit_start()
        self._fill_mean_image()

    def on_test_start(self) -> None:
        super().on_test_start()
        self._fill_mean_image()

    def train(self, mode: bool = True) -> DecoderModule:
        super().train(mode)
        self.pae.eval()
        return self

    def reconstruct(self, poses: Tensor, scenes: Tensor) -> Tensor:
        """poses [B, 7], scenes [B] -> decoded images [B, 3, s, s] in [0, 1]."""
        with torch.no_grad():
            encoding = self.pae(poses, scenes).joint()
        return self.decoder(encoding)

    def _l1(self, batch: dict[str, Tensor]) -> tuple[Tensor, Tensor, Tensor]:
        target = image_targets(batch["image"], self.decoder.size)
        recon = self.reconstruct(batch["pose"], batch["scene"])
        return nn.functional.l1_loss(recon, target), target, recon

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        loss, _, _ = self._l1(batch)
        self.log_train({"train/decoder_l1": loss})
        return loss

    def trainable_parameters(self) -> list[nn.Parameter]:
        return list(self.decoder.parameters())

    def evaluate(self, batch: dict[str, Tensor], batch_idx: int, split: str) -> None:
        loss, target, recon = self._l1(batch)
        baseline = psnr_db(self.mean_image.expand_as(target), target)
        self.log_dict(
            {
                f"{split}/decoder/l1": loss,
                f"{split}/decoder/psnr_db": psnr_db(recon, target).mean(),
                f"{split}/decoder/psnr_mean_image_db": baseline.mean(),
            },
            batch_size=len(target),
        )
        if batch_idx == 0:
            self._gallery(f"{split}/reconstructions", target, recon)

    def _gallery(self, tag: str, target: Tensor, recon: Tensor) -> None:
        n = min(self.gallery_size, len(target))
        grid = torchvision.utils.make_grid(torch.cat([target[:n], recon[:n]]), nrow=n)
        for logger in self.loggers:
            if isinstance(logger, TensorBoardLogger):
                logger.experiment.add_image(tag, grid, self.global_step)
