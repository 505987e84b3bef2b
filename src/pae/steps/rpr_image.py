"""The rpr_image step: train the Siamese RPR (the `rpr` group's model and training settings)
on pairs of real train images, then test the image RPR and its audits
(`test/rpr_image/...`)."""

from __future__ import annotations

from pathlib import Path

from hydra.utils import instantiate
from omegaconf import DictConfig

from pae.core.checkpoints import load_teacher
from pae.lit.rpr_image import ImageRPRModule
from pae.runs import Metrics
from pae.runs.inputs import build_data, check_data, required
from pae.runs.relative import relative_model, rpr_pairs, stored_model_config
from pae.runs.trainer import fit_and_test, optimisation


def fit_rpr_image(
    cfg: DictConfig, step_dir: Path, teacher_ckpt: str | Path | None
) -> tuple[Metrics, Path]:
    """Train the Siamese RPR (the `rpr` group's model and training settings) on real
    train-image pairs, then test `rpr_image` and its audits (`test/rpr_image/...`)."""
    teacher_ckpt = required(teacher_ckpt, "teacher_ckpt", "rpr_image")
    teacher = load_teacher(teacher_ckpt, "teacher_ckpt")
    data = build_data(cfg)
    check_data(cfg, teacher_ckpt, teacher, data)
    module = ImageRPRModule(
        relative_model(cfg, "rpr", teacher.model),
        teacher.model,
        loss=instantiate(cfg.rpr.loss),
        **optimisation(cfg.rpr),
        scene_names=data.scene_names,
        configs={
            "teacher_config": teacher.config,
            "rpr_config": stored_model_config(cfg.rpr.model),
        },
        **rpr_pairs(cfg),
    )
    return fit_and_test(cfg, step_dir, "rpr_image", module, data, cfg.rpr.max_epochs)
