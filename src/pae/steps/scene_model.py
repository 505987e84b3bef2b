"""The scene_model step: fit a scene model from the train images, poses and intrinsics, then
test render-and-compare refinement of a frozen teacher (`test/render_compare/...`); and
pae-eval's test of a scene-model checkpoint."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from hydra.utils import get_class
from omegaconf import DictConfig, OmegaConf

from pae.callbacks.render_compare_gallery import RenderCompareGallery
from pae.callbacks.scene_quality import SceneModelQuality
from pae.checkpoints import LoadedModel, load_decoder, load_pae, load_scene_model, load_teacher
from pae.data.rays import RayLoader
from pae.errors import ConfigError
from pae.lit.scene_model import SceneModelModule
from pae.models.scene_model import SceneModel, SceneModelInputs
from pae.runs import Metrics
from pae.runs.hparams import log_hparams
from pae.runs.inputs import build_data, check_data, required
from pae.runs.trainer import (
    build_trainer,
    collect_metrics,
    fit_and_test,
    optimisation,
    render_compare_callback,
    validate_and_test,
)

LOADERS: dict[str, Callable[..., LoadedModel]] = {
    "teacher_ckpt": load_teacher,
    "student_ckpt": load_pae,
    "decoder_ckpt": load_decoder,
}
"""Checkpoint key -> what a scene model's ``build`` gets for it (the teacher, the student's
PAE, the decoder)."""


def build_scene_model(
    cfg: DictConfig, data: Any, checkpoints: dict[str, str | Path | None]
) -> tuple[SceneModel, dict[str, Any]]:
    """The scene model of ``scene_model.model`` (its ``_target_`` class's ``build``, given the
    data and the checkpoints it ``needs``) and what a checkpoint stores to rebuild it."""
    config = OmegaConf.to_container(cfg.scene_model.model, resolve=True)
    target = config.pop("_target_")
    cls = get_class(target)

    def load(key: str) -> LoadedModel:
        path = checkpoints.get(key)
        if path is None:
            raise ConfigError(f"scene_model.model._target_={target} needs {key}=PATH")
        loaded = LOADERS[key](path, key)
        check_data(cfg, path, loaded, data)
        return loaded

    inputs = SceneModelInputs(data, cfg.scene_model.appearance, load)
    model, stored = cls.build(config, inputs)
    return model, ({} if stored is None else {"scene_model_config": {"_target_": target, **stored}})


def fit_scene_model(
    cfg: DictConfig,
    step_dir: Path,
    teacher_ckpt: str | Path | None,
    student_ckpt: str | Path | None = None,
    decoder_ckpt: str | Path | None = None,
) -> tuple[Metrics, Path | None]:
    """Fit the configured scene model (one whose class ``trains``: its checkpoint is written
    with max_epochs=0 too; others are only built), then test render-and-compare from the
    teacher's estimates -> (metrics, the last checkpoint or None)."""
    checkpoints = {
        "teacher_ckpt": teacher_ckpt,
        "student_ckpt": student_ckpt,
        "decoder_ckpt": decoder_ckpt,
    }
    teacher_path = required(teacher_ckpt, "teacher_ckpt", "render_compare")
    teacher = load_teacher(teacher_path, "teacher_ckpt")
    images = build_data(cfg, augment=False)
    check_data(cfg, teacher_path, teacher, images)
    scene_model, configs = build_scene_model(cfg, images, checkpoints)
    settings = cfg.scene_model
    callback = render_compare_callback(cfg)
    images.train_batches = RayLoader(
        settings.rays_per_batch,
        settings.batches_per_epoch,
        settings.image_size,
        settings.appearance,
        cfg.seed,
    )
    module = SceneModelModule(
        scene_model,
        teacher.model,
        **optimisation(settings),
        scene_names=images.scene_names,
        configs={"teacher_config": teacher.config, **configs},
        tv_weight=settings.tv_weight,
        fit_trim=settings.fit_trim,
        fit_trim_from_epoch=settings.fit_trim_from_epoch,
        appearance_lr=settings.appearance_lr,
        query_width=callback.query_width,
    )
    quality = SceneModelQuality(settings.quality_size, settings.quality_images)
    callbacks = [callback, RenderCompareGallery(callback), quality]
    if scene_model.trains:  # max_epochs=0: saved untrained
        metrics, last = fit_and_test(
            cfg, step_dir, "scene_model", module, images, settings.max_epochs, callbacks
        )
        return metrics | collect_metrics(module.trainer, ("bench/render_compare",)), last
    trainer = build_trainer(cfg, step_dir, 0, callbacks, step="scene_model")
    metrics = validate_and_test(trainer, module, images)
    metrics |= collect_metrics(trainer, ("bench/",))
    log_hparams(trainer, cfg, metrics)
    return metrics, None


def evaluate_scene_model(
    cfg: DictConfig, run_dir: Path, path: str | Path, teacher: LoadedModel, data: Any
) -> Metrics:
    """Test render-and-compare (the `render_compare` group's settings) with the scene model
    of checkpoint ``path`` from ``teacher``'s estimates on ``data`` (pae-eval)."""
    loaded = load_scene_model(path, "scene_model_ckpt")
    check_data(cfg, path, loaded, data)
    callback = render_compare_callback(cfg)
    module = SceneModelModule(
        loaded.model,
        teacher.model,
        optimizer=torch.optim.Adam,
        scene_names=data.scene_names,
        configs={"teacher_config": teacher.config, "scene_model_config": loaded.config},
        query_width=callback.query_width,
    )
    callbacks = [callback, RenderCompareGallery(callback), SceneModelQuality()]
    trainer = build_trainer(cfg, run_dir / "render_compare", 0, callbacks)
    metrics = validate_and_test(trainer, module, data)
    metrics |= collect_metrics(trainer, ("bench/",))
    log_hparams(trainer, cfg, metrics)
    return metrics
