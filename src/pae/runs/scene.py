"""What the scene_fit and scene_model steps (and pae-eval) share: the scene model a config
names, built from the run's data and checkpoints; the module that fits it to the train
images' rays; the render-and-compare callback."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

from hydra.utils import get_class
from omegaconf import DictConfig, OmegaConf

from pae.core.checkpoints import LoadedModel, load_decoder, load_pae, load_teacher
from pae.core.errors import ConfigError
from pae.lit.scene_model import SceneModelModule
from pae.models.base import PoseRegressor
from pae.runs.inputs import check_data
from pae.runs.trainer import optimisation
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
        appearance_lr=settings.appearance_lr,
        query_width=query_width,
    )
