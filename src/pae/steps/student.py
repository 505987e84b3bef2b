"""The student step: distil a PAE from a frozen teacher checkpoint (on the teacher's latents,
cached or computed per batch), then test it with the configured refinement."""

from __future__ import annotations

from pathlib import Path

from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from pae.checkpoints import load_teacher
from pae.data.latents import LatentCache, TeacherLatentDataModule
from pae.errors import ConfigError
from pae.lit.student import StudentModule
from pae.runs import Metrics
from pae.runs.inputs import load_frozen
from pae.runs.trainer import fit_and_test, optimisation, refinement_callbacks


def fit_student(
    cfg: DictConfig, step_dir: Path, teacher_ckpt: str | Path | None
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
    train_data = TeacherLatentDataModule(
        data,
        teacher.model,
        cache=LatentCache(folder) if folder else None,
        teacher_ckpt=teacher_ckpt,
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
    return metrics, last
