"""The teacher step: train and test a teacher APR, the absolute pose regressor whose latents
the PAE learns; with ``teacher.novel_views.enabled``, on the train images mixed with views a
scene model renders around the train cameras (pae.scene_model.novel_views)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from pae.data.datamodule import PoseDataModule
from pae.lit.teacher import TeacherModule
from pae.runs import Metrics
from pae.runs.inputs import build_data, novel_view_source
from pae.runs.relative import stored_model_config
from pae.runs.trainer import fit_and_test, optimisation
from pae.scene_model.novel_views import NovelViewLoader


def _teacher_config(cfg: DictConfig, n_scenes: int) -> dict[str, Any]:
    """The teacher's architecture as stored in its checkpoint (weights come from the state dict)."""
    return {**stored_model_config(cfg.teacher.model), "n_scenes": n_scenes}


def novel_view_loader(
    cfg: DictConfig, data: PoseDataModule, scene_model_ckpt: str | Path | None
) -> NovelViewLoader:
    """The train batches of ``teacher.novel_views``: the scene model of ``scene_model_ckpt``
    (checked to have been fitted to this data) rendering around the train cameras."""
    model, settings = novel_view_source(
        cfg, data, scene_model_ckpt, "teacher with teacher.novel_views"
    )
    return NovelViewLoader(model, settings, cfg.scene_model.appearance, cfg.seed)


def fit_teacher(
    cfg: DictConfig, step_dir: Path, scene_model_ckpt: str | Path | None = None
) -> tuple[Metrics, Path]:
    """Train and test a teacher APR -> (metrics, path of its last checkpoint); with novel views
    the seconds spent rendering them are ``bench/teacher/novel_views_render_s``."""
    data = build_data(cfg)
    loader = None
    if OmegaConf.select(cfg, "teacher.novel_views.enabled"):
        loader = data.train_batches = novel_view_loader(cfg, data, scene_model_ckpt)
    teacher = instantiate(cfg.teacher.model, n_scenes=data.n_scenes)
    module = TeacherModule(
        teacher,
        loss=instantiate(cfg.teacher.loss),
        **optimisation(cfg.teacher),
        scene_names=data.scene_names,
        teacher_config=_teacher_config(cfg, data.n_scenes),
        scene_loss_weight=cfg.teacher.scene_loss_weight,
    )
    metrics, last = fit_and_test(cfg, step_dir, "teacher", module, data, cfg.teacher.max_epochs)
    if loader is not None and loader.pools:
        metrics["bench/teacher/novel_views_render_s"] = loader.pools[-1].render_s
    return metrics, last
