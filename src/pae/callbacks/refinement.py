"""Test-time position refinement (paper §3.3) as a Lightning callback for student runs."""

from __future__ import annotations

import time

import lightning as L
import numpy as np
import torch
from lightning.pytorch.loggers import TensorBoardLogger
from torch import Tensor

from pae.geometry import pose_errors
from pae.metrics import summarise_errors
from pae.models.base import Latents
from pae.refine import PoseIndex, PositionRefiner, perturb_positions
from pae.refine.affine import ORIENTATION_MODES, WEIGHT_MODELS


class TestTimeRefinement(L.Callback):
    """Refines every evaluated query of a StudentModule and logs `{split}/refined/...`.

    The store holds the data module's train poses. Runs at the end of every
    `every_n_val_epochs`-th validation and of every test. With `guess_sigma_m` set, also runs
    the random-guess check: the ground-truth position plus Gaussian noise (σ m), encoded by the
    PAE, is the query (`{split}/guess_initial/...` vs `{split}/guess_refined/...`).

    Diagnostics `{split}/diagnostics/{estimate,gt}_to_train_m`: median distance (m) from the
    teacher's estimates and from the true positions to the nearest train position of their
    scene. Retrieval can only pull an estimate back towards the train poses: when estimates
    already lie as close to them as the truth does, refinement has little to correct.
    """

    def __init__(
        self,
        k: int = 3,
        iterations: int = 3,
        lr: float = 1e-3,
        weight_model: str = "mlp",
        orientation: str = "teacher",
        distance: str = "normalized",
        rot_weight: float = 0.01,
        every_n_val_epochs: int = 1,
        guess_sigma_m: float | None = 0.5,
        seed: int = 0,
        trajectory_plot: bool = True,
    ) -> None:
        super().__init__()
        self.options = {
            "k": k,
            "iterations": iterations,
            "lr": lr,
            "weight_model": weight_model,
            "orientation": orientation,
        }
        self.distance = distance
        self.rot_weight = rot_weight
        self.every_n_val_epochs = max(1, every_n_val_epochs)
        self.guess_sigma_m = guess_sigma_m
        self.seed = seed
        self.trajectory_plot = trajectory_plot
        self.index: PoseIndex | None = None
        self.position_index: PoseIndex | None = None
        self._val_runs = 0
        if weight_model not in WEIGHT_MODELS:
            raise ValueError(
                f"unknown refine.weight_model {weight_model!r}; choose {WEIGHT_MODELS}"
            )
        if orientation not in ORIENTATION_MODES:
            raise ValueError(
                f"unknown refine.orientation {orientation!r}; choose {ORIENTATION_MODES}"
            )
        if distance not in ("normalized", "fixed"):
            raise ValueError(f"unknown refine.distance {distance!r}; choose normalized or fixed")

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        poses, scenes = trainer.datamodule.train_poses()
        self.index = PoseIndex(poses, scenes, distance=self.distance, rot_weight=self.rot_weight)
        self.position_index = PoseIndex(poses, scenes, distance="fixed", rot_weight=0.0)

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._val_runs += 1
        if (self._val_runs - 1) % self.every_n_val_epochs == 0:
            self.refine(trainer, pl_module, "val")

    def on_test_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.refine(trainer, pl_module, "test")

    def _refiner(self, pl_module: L.LightningModule) -> PositionRefiner:
        assert self.index is not None
        return PositionRefiner(self.index, pl_module.pae, seed=self.seed, **self.options)

    def refine(self, trainer: L.Trainer, pl_module: L.LightningModule, split: str) -> None:
        """Refine all queries of the finished evaluation epoch in one batched call."""
        if not pl_module.eval_outputs:
            return
        outputs = {
            key: torch.cat([batch[key] for batch in pl_module.eval_outputs])
            for key in pl_module.eval_outputs[0]
        }
        if trainer.world_size > 1:  # every rank refines all queries of the split
            outputs = {k: pl_module.all_gather(v).flatten(0, 1) for k, v in outputs.items()}
        names = pl_module.scene_names
        d = outputs["z"].shape[-1] // 2
        query = Latents(outputs["z"][:, :d], outputs["z"][:, d:])
        start = time.perf_counter()
        result = self._refiner(pl_module)(query, outputs["estimate"], outputs["scene_estimate"])
        elapsed = time.perf_counter() - start
        gt, scene = outputs["pose"], outputs["scene"]
        figures = self._figures(split, "refined", result.poses, gt, scene, names)
        figures |= self._store_distances(
            split, outputs["estimate"], outputs["scene_estimate"], gt, scene
        )
        if split == "test":
            figures["bench/refine/callback_ms_per_query"] = torch.tensor(1000 * elapsed / len(gt))
        if self.guess_sigma_m:
            generator = torch.Generator().manual_seed(self.seed)
            guess = perturb_positions(gt.cpu(), self.guess_sigma_m, generator).to(gt.device)
            with torch.no_grad():
                guess_latents = pl_module.pae(guess, scene)
            refined_guess = self._refiner(pl_module)(guess_latents, guess, scene)
            figures |= self._figures(split, "guess_initial", guess, gt, scene, names)
            figures |= self._figures(split, "guess_refined", refined_guess.poses, gt, scene, names)
        pl_module.log_dict(figures)
        if self.trajectory_plot:
            self._plot(trainer, split, gt, outputs["estimate"], result.poses, scene)

    def _store_distances(
        self, split: str, estimate: Tensor, estimate_scene: Tensor, gt: Tensor, scene: Tensor
    ) -> dict[str, Tensor]:
        assert self.position_index is not None
        _, to_estimate = self.position_index.query(estimate, estimate_scene, 1)
        _, to_gt = self.position_index.query(gt, scene, 1)
        return {
            f"{split}/diagnostics/estimate_to_train_m": to_estimate.median(),
            f"{split}/diagnostics/gt_to_train_m": to_gt.median(),
        }

    @staticmethod
    def _figures(
        split: str, method: str, pred: Tensor, gt: Tensor, scene: Tensor, names: list[str]
    ) -> dict[str, Tensor]:
        pos, rot = pose_errors(pred.float(), gt.float())
        summary = summarise_errors(pos, rot, scene, names)
        return {f"{split}/{method}/{key}": value for key, value in summary.items()}

    def _plot(
        self,
        trainer: L.Trainer,
        split: str,
        gt: Tensor,
        teacher: Tensor,
        refined: Tensor,
        scene: Tensor,
    ) -> None:
        loggers = [lg for lg in trainer.loggers if isinstance(lg, TensorBoardLogger)]
        if not loggers:
            return
        mask = scene == scene[0]
        image = trajectory_image(gt[mask], teacher[mask], refined[mask])
        for logger in loggers:
            logger.experiment.add_image(
                f"{split}/trajectory", image, trainer.global_step, dataformats="HWC"
            )


def trajectory_image(gt: Tensor, teacher: Tensor, refined: Tensor, size: int = 480) -> np.ndarray:
    """Top-down plot (the two position axes of largest spread) of ground truth (green),
    teacher (red) and refined (blue) positions of one scene -> uint8 [size, size, 3] RGB."""
    points = torch.stack([gt[:, :3], teacher[:, :3], refined[:, :3]]).detach().cpu().double()
    axes = gt[:, :3].detach().cpu().double().var(0).argsort(descending=True)[:2]
    xy = points[..., axes].numpy()
    low, high = xy.reshape(-1, 2).min(0), xy.reshape(-1, 2).max(0)
    scale = (size - 40) / max(float((high - low).max()), 1e-9)
    pixels = ((xy - low) * scale + 20).astype(np.int64)  # [3, N, 2] (u, v)
    pixels[..., 1] = size - 1 - pixels[..., 1]
    image = np.full((size, size, 3), 255, np.uint8)
    offsets = np.stack(np.meshgrid(np.arange(-2, 3), np.arange(-2, 3)), -1).reshape(-1, 2)
    dots = (pixels[:, :, None, :] + offsets).clip(0, size - 1)  # [3, N, 25, 2]
    colours = np.array([(0, 160, 0), (220, 0, 0), (0, 0, 220)], np.uint8)
    for track, colour in zip(dots, colours, strict=True):  # three tracks, drawn in order
        image[track[..., 1], track[..., 0]] = colour
    return image
