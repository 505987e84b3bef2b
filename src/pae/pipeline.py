"""pae-eval's evaluation of a student checkpoint and of a scene-model checkpoint."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from pae.checkpoints import CheckpointError, architecture_differences, load_pae, load_teacher
from pae.lit.student import StudentEvaluator
from pae.runs import Metrics
from pae.runs.hparams import log_hparams
from pae.runs.inputs import build_data, check_data
from pae.runs.trainer import (
    build_trainer,
    refinement_callbacks,
    validate_and_test,
)


def evaluate_checkpoints(cfg: DictConfig, run_dir: Path) -> Metrics:
    """Test a student checkpoint (and optionally another teacher of its teacher's
    architecture) with the configured refinement, and/or a scene-model checkpoint with
    render-and-compare refinement."""
    metrics: Metrics = {}
    teacher_path = cfg.teacher_ckpt or cfg.student_ckpt or cfg.get("scene_model_ckpt")
    teacher = load_teacher(teacher_path, "teacher_ckpt" if cfg.teacher_ckpt else None)
    data = build_data(cfg, augment=False)
    check_data(cfg, teacher_path, teacher, data)
    if cfg.student_ckpt:
        pae = load_pae(cfg.student_ckpt, "student_ckpt")
        if cfg.teacher_ckpt:
            changed = architecture_differences(pae.hparams["teacher_config"], teacher.config)
            if changed:
                raise CheckpointError(
                    f"teacher_ckpt={teacher_path}: another architecture than the teacher the "
                    f"PAE of {cfg.student_ckpt} was trained on ({'; '.join(changed[:3])}): "
                    "its latents mean nothing to that PAE"
                )
        check_data(cfg, cfg.student_ckpt, pae, data)
        if pae.model.latent_dim != teacher.model.latent_dim:
            raise CheckpointError(
                f"{cfg.student_ckpt}: PAE latent size {pae.model.latent_dim} does not match "
                f"the teacher's {teacher.model.latent_dim} ({teacher_path})"
            )
        module = StudentEvaluator(teacher.model, pae.model, data.scene_names)
        trainer = build_trainer(cfg, run_dir, 0, refinement_callbacks(cfg))
        metrics |= validate_and_test(trainer, module, data)
        log_hparams(trainer, cfg, metrics)
    if cfg.get("scene_model_ckpt"):
        from pae.steps.scene_model import evaluate_scene_model

        metrics |= evaluate_scene_model(cfg, run_dir, cfg.scene_model_ckpt, teacher, data)
    return metrics
