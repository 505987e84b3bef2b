"""The record of a run's settings with its final figures: TensorBoard's HParams tab and a
TEXT table of every figure (other loggers: the flattened config)."""

from __future__ import annotations

from typing import Any

import lightning as L
from hydra.core.hydra_config import HydraConfig
from lightning.pytorch.loggers import TensorBoardLogger
from omegaconf import DictConfig, OmegaConf

from pae.report.tables import (
    best_refinement,
    format_results_table,
    headline_metrics,
    honest_refinements,
)
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


CURVE_SPLIT = "val"
"""The split whose figures are logged over epochs: the HParams metrics and the Custom
Scalars charts read its curves (test figures are final: TEXT ``results`` and metrics.json)."""
OTHER_ROWS = r"(?!guess_|student_gt|diagnostics|decoder|scene_model)(?![^/]*_test_store/)"
"""A regular expression's lookahead that skips the rows that are no localisation method."""


def hparams_metric_tags(metrics: Metrics) -> list[str]:
    """The HParams metrics of a step: the scalar tags of its ``val/`` curves (their last
    value is what the HParams tab shows), headline first (teacher, student, the best honest
    refinement chosen on val, the test-store audit), then every method in table order, then
    the other overall figures (decoder PSNR, diagnostics); no per-scene tag, no mean."""
    best = best_refinement(metrics, CURVE_SPLIT)
    renamed = {"best_refinement": best} if best is not None else {}
    tags = []
    for key in headline_metrics(metrics, CURVE_SPLIT):
        split, _, rest = key.partition("/")
        method, _, figure = rest.partition("/")
        if split == CURVE_SPLIT:
            tags.append(f"{split}/{renamed.get(method, method)}/{figure}")
    return [tag for tag in dict.fromkeys(tags) if tag in metrics]


def custom_scalars_layout() -> dict[str, dict[str, list[Any]]]:
    """TensorBoard's Custom Scalars layout: the val split's methods side by side (median
    position and orientation errors over epochs; audits and checks apart), and training."""
    rows = rf"^{CURVE_SPLIT}/{OTHER_ROWS}[^/]+/"
    checks = rf"^{CURVE_SPLIT}/(guess_[^/]*|student_gt|[^/]*_test_store)/"
    return {
        f"methods side by side ({CURVE_SPLIT} split, held-out sequences)": {
            "median position error [m]": ["Multiline", [rows + "pos_median_m$"]],
            "median orientation error [deg]": ["Multiline", [rows + "rot_median_deg$"]],
            "within 10 cm, 10 deg [share]": ["Multiline", [rows + "within_10cm_10deg$"]],
        },
        f"audits and checks ({CURVE_SPLIT} split)": {
            "median position error [m]": ["Multiline", [checks + "pos_median_m$"]],
            "median orientation error [deg]": ["Multiline", [checks + "rot_median_deg$"]],
        },
        "training": {
            "loss": ["Multiline", ["^train/loss$", "^train/pos_loss$", "^train/rot_loss$"]],
            "learning rate": ["Multiline", ["^lr-"]],
        },
    }


def _hparams_value(value: Any) -> int | float | str | bool:
    return value if isinstance(value, int | float | str | bool) else str(value)


def log_hparams(trainer: L.Trainer, cfg: DictConfig, metrics: Metrics) -> None:
    """The settings with the final figures: TensorBoard's HParams tab (hparams_columns, and
    the name of the best honest refinement chosen on val; its metrics: the step's ``val/``
    curves of hparams_metric_tags, no copies of them), the Custom Scalars layout
    (custom_scalars_layout) and a TEXT table ``results`` with every figure; other loggers
    get the flattened config."""
    from lightning.pytorch.utilities import rank_zero_only
    from torch.utils.tensorboard.summary import hparams

    for logger in trainer.loggers:
        if not isinstance(logger, TensorBoardLogger):
            logger.log_hyperparams(flat_config(cfg))
            continue
        if rank_zero_only.rank != 0:  # the first process writes the event files
            continue
        columns = hparams_columns(cfg)
        if honest_refinements(metrics, CURVE_SPLIT):
            columns["best_refinement"] = best_refinement(metrics, CURVE_SPLIT) or "none"
        tags = hparams_metric_tags(metrics)
        params = {key: _hparams_value(value) for key, value in columns.items()}
        writer = logger.experiment._get_file_writer()
        for summary in hparams(params, dict.fromkeys(tags, 0.0)):
            writer.add_summary(summary, trainer.global_step)
        logger.experiment.add_custom_scalars(custom_scalars_layout())
        table = format_results_table(metrics)
        code = "\n".join(f"    {line}" for line in table.splitlines())
        logger.experiment.add_text("results", code, trainer.global_step)
