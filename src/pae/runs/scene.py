"""What the scene_fit and scene_model steps (and pae-eval) share: the scene model a config
names, built from the run's data and checkpoints; the module that fits it to the train
images' rays; the render-and-compare callback; the test of a fitted scene model's checkpoint
(the scene_model step given one, pae-eval)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from hydra.utils import get_class
from omegaconf import DictConfig, OmegaConf

from pae.callbacks.render_compare_confusion import RenderCompareConfusion
from pae.callbacks.render_compare_gallery import RenderCompareGallery
from pae.callbacks.render_compare_init import RenderCompareFromFile
from pae.callbacks.scene_quality import SceneModelQuality
from pae.core.checkpoints import (
    LoadedModel,
    load_decoder,
    load_pae,
    load_scene_model,
    load_teacher,
)
from pae.core.errors import ConfigError
from pae.lit.scene_model import SceneModelModule
from pae.models.base import PoseRegressor
from pae.runs import Metrics
from pae.runs.hparams import log_hparams
from pae.runs.inputs import check_data
from pae.runs.trainer import (
    build_trainer,
    collect_metrics,
    optimisation,
    render_compare_callback,
    validate_and_test,
)
from pae.scene_model.base import SceneModel, SceneModelInputs
from pae.scene_model.rays import RayLoader

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


def fitting_module(
    cfg: DictConfig,
    data: Any,
    scene_model: SceneModel,
    teacher: PoseRegressor | None,
    configs: dict[str, Any],
    query_width: int | None = None,
) -> SceneModelModule:
    """The module fitting ``scene_model`` with the ``scene_model`` group's settings, with
    ``data``'s train batches set to the train images' rays (evaluated with ``teacher``, or
    its quality alone without one; ``configs``: what its checkpoint stores)."""
    settings = cfg.scene_model
    data.train_batches = RayLoader(
        settings.rays_per_batch,
        settings.batches_per_epoch,
        settings.image_size,
        settings.appearance,
        cfg.seed,
        settings.depth_rays,
    )
    return SceneModelModule(
        scene_model,
        teacher,
        **optimisation(settings),
        scene_names=data.scene_names,
        configs=configs,
        tv_weight=settings.tv_weight,
        fit_trim=settings.fit_trim,
        fit_trim_from_epoch=settings.fit_trim_from_epoch,
        depth_weight=settings.depth_weight,
        appearance_lr=settings.appearance_lr,
        query_width=query_width,
    )


def evaluate_scene_model(
    cfg: DictConfig,
    out_dir: Path,
    path: str | Path,
    teacher: LoadedModel,
    data: Any,
    quality: SceneModelQuality | None = None,
    step: str = "eval",
) -> Metrics:
    """Test render-and-compare (the `render_compare` group's settings) with the scene model
    of checkpoint ``path`` from ``teacher``'s estimates on ``data``, writing into ``out_dir``
    (the scene_model step, pae-eval); ``quality``: the scene model's quality callback
    (None: its defaults)."""
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
    callbacks = [
        callback,
        RenderCompareConfusion(callback),
        RenderCompareFromFile(callback),
        RenderCompareGallery(callback),
        quality or SceneModelQuality(),
    ]
    trainer = build_trainer(cfg, out_dir, 0, callbacks, step=step)
    metrics = validate_and_test(trainer, module, data)
    metrics |= collect_metrics(trainer, ("bench/",))
    log_hparams(trainer, cfg, metrics)
    return metrics
