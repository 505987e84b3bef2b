"""The rpr step: train the Siamese RPR on virtual references (images decoded from the PAE's
encodings of train poses near the query's), then test virtual RPR (`test/vrpr/...`)."""

from __future__ import annotations

from pathlib import Path

from hydra.utils import instantiate
from omegaconf import DictConfig

from pae.core.checkpoints import load_decoder, load_pae, load_teacher
from pae.lit.rpr import RPRModule
from pae.runs import Metrics
from pae.runs.inputs import build_data, check_data, required
from pae.runs.relative import relative_model, rpr_pairs, stored_model_config
from pae.runs.trainer import fit_and_test, optimisation


def fit_rpr(
    cfg: DictConfig,
    step_dir: Path,
    student_ckpt: str | Path | None,
    decoder_ckpt: str | Path | None,
) -> tuple[Metrics, Path]:
    """Train the Siamese RPR on virtual references, then test virtual RPR (`test/vrpr/...`)."""
    student_ckpt = required(student_ckpt, "student_ckpt", "rpr")
    decoder_ckpt = required(decoder_ckpt, "decoder_ckpt", "rpr")
    teacher, pae, decoder = (
        load_teacher(student_ckpt),
        load_pae(student_ckpt, "student_ckpt"),
        load_decoder(decoder_ckpt, "decoder_ckpt"),
    )
    data = build_data(cfg)
    for path, loaded in ((student_ckpt, pae), (decoder_ckpt, decoder)):
        check_data(cfg, path, loaded, data)
    module = RPRModule(
        relative_model(cfg, "rpr", teacher.model),
        teacher.model,
        pae.model,
        decoder.model,
        loss=instantiate(cfg.rpr.loss),
        **optimisation(cfg.rpr),
        scene_names=data.scene_names,
        configs={
            "teacher_config": teacher.config,
            "pae_config": pae.config,
            "decoder_config": decoder.config,
            "rpr_config": stored_model_config(cfg.rpr.model),
        },
        **rpr_pairs(cfg),
    )
    return fit_and_test(cfg, step_dir, "rpr", module, data, cfg.rpr.max_epochs)
