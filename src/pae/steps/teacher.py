"""The teacher step: train and test a teacher APR, the absolute pose regressor whose latents
the PAE learns."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from pae.lit.teacher import TeacherModule
from pae.runs import Metrics
from pae.runs.inputs import build_data
from pae.runs.trainer import fit_and_test, optimisation


def _teacher_config(cfg: DictConfig, n_scenes: int) -> dict[str, Any]:
    """The teacher's architecture as stored in its checkpoint (weights come from the state dict)."""
    config = OmegaConf.to_container(cfg.teacher.model, resolve=True)
    config["n_scenes"] = n_scenes
    config["backbone"]["pretrained"] = False
    config["backbone"]["weights_path"] = None
    return config


def fit_teacher(cfg: DictConfig, step_dir: Path) -> tuple[Metrics, Path]:
    """Train and test a teacher APR -> (metrics, path of its last checkpoint)."""
    data = build_data(cfg)
    teacher = instantiate(cfg.teacher.model, n_scenes=data.n_scenes)
    module = TeacherModule(
        teacher,
        loss=instantiate(cfg.teacher.loss),
        **optimisation(cfg.teacher),
        scene_names=data.scene_names,
        teacher_config=_teacher_config(cfg, data.n_scenes),
        scene_loss_weight=cfg.teacher.scene_loss_weight,
    )
    return fit_and_test(cfg, step_dir, "teacher", module, data, cfg.teacher.max_epochs)
