"""The scene_fit step: fit a scene model to the train images, poses and intrinsics alone (no
teacher), and measure its renderings at the validation and test poses
(``{split}/scene_model/psnr_db``). Its checkpoint (``scene_model_ckpt``) serves a later
teacher's novel views and the scene_model step's render-and-compare."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from pae.callbacks.scene_quality import SceneModelQuality
from pae.runs import Metrics
from pae.runs.inputs import build_data
from pae.runs.scene import build_scene_model, fitting_module
from pae.runs.trainer import fit_and_test


def fit_scene(cfg: DictConfig, step_dir: Path) -> tuple[Metrics, Path]:
    """Fit the configured scene model (its class ``trains``: checked before the run) ->
    (metrics, its last checkpoint)."""
    images = build_data(cfg, augment=False)
    scene_model, configs = build_scene_model(cfg, images, {})
    module = fitting_module(cfg, images, scene_model, None, configs)
    settings = cfg.scene_model
    quality = SceneModelQuality(settings.quality_size, settings.quality_images)
    return fit_and_test(cfg, step_dir, "scene_fit", module, images, settings.max_epochs, [quality])
