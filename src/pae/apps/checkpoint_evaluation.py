"""What pae-eval evaluates: a student checkpoint with the configured refinement (and
optionally another teacher of its teacher's architecture), a scene-model checkpoint with
render-and-compare, and the methods of the relative regressors' checkpoints
(`method_ckpts`), which read the query image at test time: virtual RPR (references decoded
from PAE encodings, `vrpr`), the image RPR (real train images as references, `rpr_image`)
and the iterative APR (`iapr_{n}`).

It imports the steps whose checkpoints it tests; no step imports it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from pae.core.checkpoints import (
    CheckpointError,
    architecture_differences,
    checkpoint_kind,
    load_decoder,
    load_iapr,
    load_pae,
    load_rpr,
    load_teacher,
    read_checkpoint,
)
from pae.lit.methods import ImageMethodEvaluator
from pae.lit.student import StudentEvaluator
from pae.refine.index import PoseIndex
from pae.relative.refiners import ImageRPR, IterativeAPRRefiner, TrainImages, VirtualRPR
from pae.runs import Metrics
from pae.runs.hparams import log_hparams
from pae.runs.inputs import build_data, check_data
from pae.runs.scene import evaluate_scene_model
from pae.runs.trainer import build_trainer, refinement_callbacks, validate_and_test


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
        metrics |= evaluate_scene_model(
            cfg, run_dir / "render_compare", cfg.scene_model_ckpt, teacher, data
        )
    return metrics


def method_evaluator(
    path: str | Path, data: Any, iapr_iterations: int, allow: DictConfig
) -> ImageMethodEvaluator:
    """The test-time method of a checkpoint of stage=rpr (``vrpr``), rpr_image or iapr
    (``iapr_{iapr_iterations}``), with the teacher (and PAE, decoder) it was trained with,
    checked against the data."""
    kind = checkpoint_kind(read_checkpoint(path))
    if kind not in ("rpr", "rpr_image", "iapr"):
        found = f"a stage={kind} checkpoint" if kind else "not a checkpoint of a pae stage"
        raise CheckpointError(
            f"method_ckpts: {path}: {found}, but method_ckpts takes checkpoints of stage=rpr, "
            "rpr_image or iapr"
        )
    teacher = load_teacher(path)
    check_data(allow, path, teacher, data)

    def store(datamodule: Any) -> PoseIndex:
        return PoseIndex(*datamodule.train_poses())

    if kind == "iapr":
        iapr, pae = load_iapr(path).model, load_pae(path).model
        method = IterativeAPRRefiner(iapr, pae, iapr_iterations)
        return ImageMethodEvaluator(
            teacher.model,
            f"iapr_{iapr_iterations}",
            lambda _: method,
            [iapr, pae],
            data.scene_names,
        )
    rpr = load_rpr(path).model
    if kind == "rpr_image":
        return ImageMethodEvaluator(
            teacher.model,
            kind,
            lambda datamodule: ImageRPR(rpr, store(datamodule), TrainImages(datamodule)),
            [rpr],
            data.scene_names,
        )
    pae, decoder = load_pae(path).model, load_decoder(path).model
    return ImageMethodEvaluator(
        teacher.model,
        "vrpr",
        lambda datamodule: VirtualRPR(rpr, pae, decoder, store(datamodule)),
        [rpr, pae, decoder],
        data.scene_names,
    )


def evaluate_methods(cfg: DictConfig, run_dir: Path) -> Metrics:
    """Test the method of every checkpoint in ``method_ckpts`` (stage=rpr, rpr_image, iapr)
    on the configured data -> ``test/{vrpr,rpr_image,iapr_n}/...``."""
    metrics: Metrics = {}
    paths = list(cfg.get("method_ckpts") or [])
    if not paths:
        return metrics
    data = build_data(cfg, augment=False)
    for path in paths:
        module = method_evaluator(path, data, cfg.iapr_iterations, cfg)
        trainer = build_trainer(cfg, run_dir, 0, [])
        metrics |= validate_and_test(trainer, module, data)
    return metrics
