"""The decoder step: train an image decoder on a frozen PAE (from a student checkpoint), then
test it; it renders virtual RPR's references and the pae_decoder scene model's images."""

from __future__ import annotations

from pathlib import Path

from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from pae.core.checkpoints import load_pae
from pae.lit.decoder import DecoderModule
from pae.runs import Metrics
from pae.runs.inputs import load_frozen
from pae.runs.trainer import fit_and_test, optimisation


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
