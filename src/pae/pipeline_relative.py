"""pae-eval's evaluation of the relative regressors' checkpoints (`method_ckpts`), which read
the query image at test time: virtual RPR (references decoded from PAE encodings, `vrpr`),
the image RPR (real train images as references, `rpr_image`) and the iterative APR
(`iapr_{n}`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from pae.checkpoints import (
    checkpoint_kind,
    load_decoder,
    load_iapr,
    load_pae,
    load_rpr,
    load_teacher,
    read_checkpoint,
)
from pae.errors import CheckpointError
from pae.lit.methods import ImageMethodEvaluator
from pae.refine.index import PoseIndex
from pae.refine.relative import ImageRPR, IterativeAPRRefiner, TrainImages, VirtualRPR
from pae.runs import Metrics
from pae.runs.inputs import build_data, check_data
from pae.runs.trainer import build_trainer, validate_and_test


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
