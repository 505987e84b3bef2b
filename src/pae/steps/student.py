"""The student step: distil a PAE from a frozen teacher checkpoint (on the teacher's latents,
cached or computed per batch), then test it with the configured refinement; with
``student.novel_views``, on the teacher's latents of the views a scene model renders around
the train cameras too (``teacher.novel_views``' sampling), and with
``student.store_novel_views`` kNN refinement retrieves among those views' poses as well."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from torch import Tensor

from pae.core.checkpoints import load_teacher
from pae.core.errors import ConfigError
from pae.data.datamodule import PoseDataModule
from pae.lit.student import StudentModule
from pae.models.latents import LatentCache, TeacherLatentDataModule
from pae.runs import Metrics
from pae.runs.inputs import load_frozen, novel_view_source
from pae.runs.trainer import fit_and_test, optimisation, refinement_callbacks
from pae.scene_model.novel_views import NovelViewPool


def novel_views(
    cfg: DictConfig, data: PoseDataModule, scene_model_ckpt: str | Path | None
) -> Callable[[], dict[str, Tensor]]:
    """The views of ``student.novel_views`` and ``student.store_novel_views``: the cameras
    ``teacher.novel_views`` samples (the pool of its first epoch), once ``data``'s train
    split is read, rendered by the scene model of ``scene_model_ckpt`` (checked to have been
    fitted to this data) only when the student learns from them (the store needs the poses
    alone): ``{"pose": [M, 7], "scene": [M]}`` and with ``student.novel_views`` ``"image"``."""
    model, settings = novel_view_source(
        cfg, data, scene_model_ckpt, "student with student.novel_views"
    )

    def views() -> dict[str, Tensor]:
        pool = NovelViewPool(data, model, settings, cfg.scene_model.appearance, cfg.seed)
        if cfg.student.novel_views:
            return pool.views(0)
        cameras = pool.cameras(0)
        return {"pose": cameras.poses, "scene": cameras.scenes}

    return views


def fit_student(
    cfg: DictConfig,
    step_dir: Path,
    teacher_ckpt: str | Path | None,
    scene_model_ckpt: str | Path | None = None,
) -> tuple[Metrics, Path]:
    """Distil a PAE from a frozen teacher checkpoint, then test it (with refinement)."""
    teacher_ckpt, teacher, data = load_frozen(
        cfg, teacher_ckpt, "teacher_ckpt", "student", load_teacher
    )
    pae_config = OmegaConf.to_container(cfg.pae, resolve=True)
    pae_config["n_scenes"] = data.n_scenes
    try:
        module = StudentModule(
            teacher.model,
            instantiate(pae_config),
            loss=instantiate(cfg.student.loss),
            **optimisation(cfg.student),
            scene_names=data.scene_names,
            teacher_config=teacher.config,
            pae_config=pae_config,
            latent_loss=cfg.student.latent_loss,
            pae_input=cfg.student.input,
        )
    except ValueError as err:  # latent sizes or options that do not fit: name the key
        raise ConfigError(str(err)) from None
    if not cfg.student.cache_latents:
        return fit_and_test(
            cfg,
            step_dir,
            "student",
            module,
            data,
            cfg.student.max_epochs,
            refinement_callbacks(cfg),
        )
    folder = cfg.student.get("latent_cache_dir")
    views = cfg.student.novel_views or cfg.student.store_novel_views
    train_data = TeacherLatentDataModule(
        data,
        teacher.model,
        cache=LatentCache(folder) if folder else None,
        teacher_ckpt=teacher_ckpt,
        views=novel_views(cfg, data, scene_model_ckpt) if views else None,
        store_views=cfg.student.store_novel_views,
        train_on_views=cfg.student.novel_views,
    )
    metrics, last = fit_and_test(
        cfg,
        step_dir,
        "student",
        module,
        train_data,
        cfg.student.max_epochs,
        refinement_callbacks(cfg),
    )
    if train_data.cache_hit is not None:
        metrics["bench/student/latent_cache_hit"] = float(train_data.cache_hit)
    if views:
        metrics["bench/student/novel_view_rows"] = float(train_data.view_rows)
    return metrics, last
