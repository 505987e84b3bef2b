"""The steps a run executes: fit a decoder, evaluate checkpoints."""

from __future__ import annotations

from pathlib import Path

from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from pae.checkpoints import CheckpointError, architecture_differences, load_pae, load_teacher
from pae.lit.decoder import DecoderModule
from pae.lit.student import StudentEvaluator
from pae.runs import Metrics
from pae.runs.hparams import log_hparams
from pae.runs.inputs import build_data, check_data, load_frozen
from pae.runs.trainer import (
    build_trainer,
    fit_and_test,
    optimisation,
    refinement_callbacks,
    validate_and_test,
)


def fit_decoder(
    cfg: DictConfig, step_dir: Path, student_ckpt: str | Path | None
) -> tuple[Metrics, Path]:
    """Train an image decoder on a frozen PAE (from a student checkpoint), then test it."""
    _, pae, data = load_frozen(cfg, student_ckpt, "student_ckpt", "decoder", load_pae)
    decoder_config = OmegaConf.to_container(cfg.decoder.model, resolve=True)
    module = DecoderModule(
        pae.model,
        instantiate(decoder_config),
        **optimisation(cfg.decoder),
        scene_names=data.scene_names,
        pae_config=pae.config,
        decoder_config=decoder_config,
    )
    return fit_and_test(cfg, step_dir, "decoder", module, data, cfg.decoder.max_epochs)


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
        from pae.pipeline_scene import evaluate_scene_model

        metrics |= evaluate_scene_model(cfg, run_dir, cfg.scene_model_ckpt, teacher, data)
    return metrics
