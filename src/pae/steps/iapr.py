"""The iapr step: train the iterative APR on a frozen PAE (and its teacher, from a student
checkpoint), then test `iapr_1` .. `iapr_{iterations}` from the teacher's estimates."""

from __future__ import annotations

from pathlib import Path

from hydra.utils import instantiate
from omegaconf import DictConfig

from pae.core.checkpoints import load_pae, load_teacher
from pae.lit.iapr import IAPRModule
from pae.runs import Metrics
from pae.runs.inputs import build_data, check_data, required
from pae.runs.relative import relative_model, stored_model_config
from pae.runs.trainer import fit_and_test, optimisation


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
