"""The steps of the relative regressors that read the query image at test time: the image
RPR (real train images as references, `rpr_image`) and the iterative APR (`iapr_{n}`)."""

from __future__ import annotations

from pathlib import Path

from hydra.utils import instantiate
from omegaconf import DictConfig

from pae.checkpoints import load_pae, load_teacher
from pae.lit.iapr import IAPRModule
from pae.lit.rpr_image import ImageRPRModule
from pae.pipeline import (
    Metrics,
    build_data,
    check_data,
    fit_and_test,
    optimisation,
    relative_model,
    required,
    rpr_pairs,
    stored_model_config,
)


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


def fit_iapr(
    cfg: DictConfig, step_dir: Path, student_ckpt: str | Path | None
) -> tuple[Metrics, Path]:
    """Train the iterative APR on a frozen PAE (and its teacher, from a student checkpoint),
    then test `iapr_1` .. `iapr_{iterations}` from the teacher's estimates."""
    student_ckpt = required(student_ckpt, "student_ckpt", "iapr")
    teacher, pae = load_teacher(student_ckpt), load_pae(student_ckpt, "student_ckpt")
    data = build_data(cfg)
    check_data(cfg, student_ckpt, pae, data)
    settings = cfg.iapr
    module = IAPRModule(
        relative_model(cfg, "iapr", teacher.model),
        teacher.model,
        pae.model,
        loss=instantiate(settings.loss),
        **optimisation(settings),
        scene_names=data.scene_names,
        configs={
            "teacher_config": teacher.config,
            "pae_config": pae.config,
            "iapr_config": stored_model_config(settings.model),
        },
        position_m=settings.start.position_m,
        orientation_deg=settings.start.orientation_deg,
        iterations=settings.iterations,
        refine_orientation=settings.refine_orientation,
    )
    return fit_and_test(cfg, step_dir, "iapr", module, data, settings.max_epochs)
