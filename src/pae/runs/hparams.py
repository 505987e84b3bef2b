"""The record of a run's settings with its final figures: TensorBoard's HParams tab and a
TEXT table of every figure (other loggers: the flattened config)."""

from __future__ import annotations

from typing import Any

import lightning as L
from hydra.core.hydra_config import HydraConfig
from lightning.pytorch.loggers import TensorBoardLogger
from omegaconf import DictConfig, OmegaConf

from pae.reporting import best_refinement, format_results_table, headline_metrics
from pae.runs import Metrics


def flat_config(cfg: DictConfig, sep: str = "/") -> dict[str, Any]:
    """The resolved run config without its hydra section, flattened to `a{sep}b` keys; values
    are scalars, other leaves (lists, None) their string form."""
    flat: dict[str, Any] = {}

    def walk(node: Any, prefix: str) -> None:
        if isinstance(node, dict):
            for key, value in node.items():
                walk(value, f"{prefix}{key}{sep}")
        else:
            flat[prefix.removesuffix(sep)] = (
                node if isinstance(node, int | float | str | bool) else str(node)
            )

    run_config = OmegaConf.masked_copy(cfg, [key for key in cfg if key != "hydra"])
    walk(OmegaConf.to_container(run_config, resolve=True), "")
    return flat


HPARAMS_GROUPS = ("stage", "experiment", "data", "teacher", "backbone", "pae", "refine")
"""The config groups whose choice changes what a run trains or measures and that have several
options: the first columns of the HParams table (the others show up when overridden)."""


def hparams_columns(cfg: DictConfig) -> dict[str, Any]:
    """The settings the HParams table compares runs by: the choices of HPARAMS_GROUPS, the
    seed, and every key set on the command line or by a sweep (resolved), e.g.
    ``{"stage": "pipeline", ..., "seed": 0, "pae.L": 3}``; the whole flattened config when
    the run has no Hydra record of them. The full config stays in `.hydra/config.yaml`."""
    hydra_cfg = cfg.get("hydra")
    if hydra_cfg is None and HydraConfig.initialized():
        hydra_cfg = HydraConfig.get()
    choices = OmegaConf.select(hydra_cfg, "runtime.choices", default=None) if hydra_cfg else None
    if choices is None:
        return flat_config(cfg)
    flat = flat_config(cfg, sep=".")
    columns: dict[str, Any] = {g: str(choices[g]) for g in HPARAMS_GROUPS if g in choices}
    columns["seed"] = flat.get("seed")  # seed sweeps compare runs by it
    for override in OmegaConf.select(hydra_cfg, "overrides.task", default=None) or []:
        key, _, value = str(override).lstrip("+~").partition("=")
        if not key.startswith("hydra.") and key not in columns:
            columns[key] = flat.get(key, value)
    return columns


def log_hparams(trainer: L.Trainer, cfg: DictConfig, metrics: Metrics) -> None:
    """The settings with the final figures: TensorBoard's HParams tab (hparams_columns; the
    figures of headline_metrics, headline first, no per-scene keys, and the name of the best
    honest refinement) and a TEXT table ``results`` with every figure; other loggers get the
    flattened config."""
    for logger in trainer.loggers:
        if not isinstance(logger, TensorBoardLogger):
            logger.log_hyperparams(flat_config(cfg))
            continue
        columns = hparams_columns(cfg)
        best = best_refinement(metrics)
        if best is not None:
            columns["best_refinement"] = best
        figures = headline_metrics(metrics)
        logger.log_hyperparams(columns, metrics={f"hparams/{k}": v for k, v in figures.items()})
        table = format_results_table(metrics)
        code = "\n".join(f"    {line}" for line in table.splitlines())
        logger.experiment.add_text("results", code, trainer.global_step)
