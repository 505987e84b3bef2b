"""The trainer of a step: built from the run's trainer, callbacks and logger settings, fitting
(resumed from the step's newest checkpoint with resume=true), validating and testing its
module, and the figures it logged, checked to be finite."""

from __future__ import annotations

import math
import re
import time
from pathlib import Path
from typing import Any

import lightning as L
import torch
from hydra.utils import instantiate
from lightning.pytorch.callbacks import LearningRateMonitor
from lightning.pytorch.loggers import Logger
from lightning.pytorch.utilities import rank_zero_info
from omegaconf import DictConfig, OmegaConf

from pae.callbacks.finite_loss import StopOnNonFiniteLoss
from pae.callbacks.seeded_batches import SeededBatches
from pae.core.checkpoints import (
    DATA_FINGERPRINT_KEY,
    AtomicCheckpointIO,
    CheckpointError,
    newest_readable_checkpoint,
    read_checkpoint,
)
from pae.core.console import say
from pae.core.error_reporting import first_line
from pae.core.errors import ConfigError, DivergenceError
from pae.lit.evaluation import EVAL_SPLITS
from pae.runs import Metrics
from pae.runs.hparams import log_hparams
from pae.runs.inputs import check_fingerprint
from pae.steps import STEPS


def _loggers(cfg: DictConfig, step_dir: Path) -> list[Logger]:
    return [instantiate(c, save_dir=str(step_dir)) for c in (cfg.get("logger") or {}).values()]


def build_trainer(
    cfg: DictConfig,
    step_dir: Path,
    max_epochs: int,
    callbacks: list[L.Callback],
    step: str = "eval",
) -> L.Trainer:
    """Trainer from cfg.trainer with the run's loggers, checkpointing into step_dir/checkpoints;
    the epoch progress lines name `step`."""
    configured = []
    loggers = _loggers(cfg, step_dir)
    for name, c in (cfg.get("callbacks") or {}).items():
        extra: dict[str, Any] = {}
        if name == "model_checkpoint":
            extra = {"dirpath": str(step_dir / "checkpoints")}
        elif name == "epoch_progress":
            extra = {"step": step}
        callback = instantiate(c, **extra)
        if loggers or not isinstance(callback, LearningRateMonitor):  # it needs a logger
            configured.append(callback)
    return instantiate(
        cfg.trainer,
        max_epochs=max_epochs,
        logger=loggers or False,
        callbacks=configured + callbacks,
        default_root_dir=str(step_dir),
        plugins=[AtomicCheckpointIO()],
    )


def _resume_path(cfg: DictConfig, step_dir: Path, data: L.LightningDataModule) -> str | None:
    """With resume=true: the newest readable checkpoint of the step (said in one line when a
    newer one is unreadable), checked against the data; None, said in one line, when the step
    has no complete checkpoint yet (it starts from epoch 0). The unfinished `*.tmp` files of a
    run killed while writing a checkpoint are removed first."""
    folder = step_dir / "checkpoints"
    if not cfg.get("resume"):
        return None
    unfinished = sorted(folder.glob("*.tmp"))
    for stale in unfinished:
        stale.unlink(missing_ok=True)
    path, skipped = newest_readable_checkpoint(folder)
    if path is None and skipped:
        raise CheckpointError(f"{folder}: no readable checkpoint to resume from ({skipped[0]})")
    if path is None:
        removed = f" (removed {len(unfinished)} unfinished .tmp file(s))" if unfinished else ""
        rank_zero_info(
            f"resume: no complete checkpoint in {folder}{removed}; the step starts from epoch 0"
        )
        return None
    trained = read_checkpoint(path).get(DATA_FINGERPRINT_KEY)
    if trained is not None:
        check_fingerprint(cfg, path, trained, data)
    if skipped:
        rank_zero_info(f"resume: {skipped[0]}; resuming from {path.name} instead")
    return str(path)


def collect_metrics(
    trainer: L.Trainer,
    prefixes: tuple[str, ...] = ("test/",),
    step: str = "evaluation",
    hint: str = "the checkpoints hold a diverged model (retrain it with a lower learning rate)",
) -> Metrics:
    """The figures the trainer logged under `prefixes`; a non-finite one is a DivergenceError
    (naming the run's `step` and, as `hint`, what to change): NaN is never a result."""
    metrics = {
        key: float(value)
        for key, value in trainer.callback_metrics.items()
        if key.startswith(prefixes)
    }
    bad = [key for key, value in metrics.items() if not math.isfinite(value)]
    if bad:
        more = f" and {len(bad) - 1} more" if len(bad) > 1 else ""
        raise DivergenceError(
            f"{step}: {bad[0]} is {metrics[bad[0]]}{more}: the model's outputs are not finite, "
            f"so nothing of it is reported as a result; {hint}"
        )
    return metrics


def validate_and_test(
    trainer: L.Trainer,
    module: L.LightningModule,
    data: L.LightningDataModule,
    **checks: str,
) -> Metrics:
    """The `val/` figures (the validation split: model selection reads these), then the
    `test/` figures (the final report) of the module as it is now; ``checks`` (step, hint)
    name a non-finite figure's step and remedy (see collect_metrics)."""
    trainer.validate(module, datamodule=data, verbose=False)
    metrics = collect_metrics(trainer, ("val/",), **checks)
    trainer.test(module, datamodule=data, verbose=False)
    metrics |= collect_metrics(trainer, **checks)
    return metrics | missing_scenes(data, checks.get("step", "evaluation"))


def missing_scenes(data: L.LightningDataModule, step: str) -> Metrics:
    """`{split}/missing_scenes`: the number of train scenes without rows in each evaluated
    split that lacks some, each split's said in a warning line naming them (its figures and
    their overall average cover the other scenes only)."""
    counts = {}
    for split in EVAL_SPLITS:
        missing = data.scenes_without_rows(split)
        if missing:
            say(
                f"{step}: warning: the {split} split has no rows of the train scenes "
                f"{', '.join(missing)}: its figures and their overall average cover the other "
                "scenes only"
            )
            counts[f"{split}/missing_scenes"] = float(len(missing))
    return counts


def fit_and_test(
    cfg: DictConfig,
    step_dir: Path,
    name: str,
    module: L.LightningModule,
    data: L.LightningDataModule,
    epochs: int,
    callbacks: list[L.Callback] | None = None,
) -> tuple[Metrics, Path]:
    """Fit (stopping at a non-finite loss), validate, test, record `bench/{name}/fit_s` ->
    (metrics, path of the last checkpoint). With `epochs` 0 the untrained model is
    evaluated, and its checkpoint written all the same."""
    group = STEPS[name].group if name in STEPS else name
    lr_setting = f"{group}.optimizer.lr={OmegaConf.select(cfg, f'{group}.optimizer.lr')}"
    finite = StopOnNonFiniteLoss(name, lr_setting)
    seeded = SeededBatches(cfg.seed, name)
    trainer = build_trainer(cfg, step_dir, epochs, [*(callbacks or []), finite, seeded], step=name)
    start = time.perf_counter()
    resume_from = _resume_path(cfg, step_dir, data)
    trainer.fit(module, datamodule=data, ckpt_path=resume_from, weights_only=True)
    fit_s = time.perf_counter() - start
    last = step_dir / "checkpoints" / "last.ckpt"
    if not last.is_file():  # no training epoch ran (max_epochs=0), or no checkpoint callback
        if epochs == 0:
            say(f"{name}: max_epochs=0: testing the untrained model, saved as {last}")
        trainer.save_checkpoint(last, weights_only=False)
    metrics = validate_and_test(
        trainer, module, data, step=name, hint=f"retrain with a lower {lr_setting}"
    )
    metrics[f"bench/{name}/fit_s"] = fit_s
    log_hparams(trainer, cfg, metrics)
    return metrics, last


def optimisation(group: DictConfig) -> dict[str, Any]:
    """A trained group's optimizer and scheduler factories (scheduler=null: a constant rate);
    both are built once on a stand-in parameter, so a bad setting of either is a one-line
    ConfigError naming its key before any data is read."""
    scheduler = group.get("scheduler")
    optimizer = instantiate(group.optimizer)
    group_key = group._get_full_key(None) or "the group"
    try:
        stand_in = optimizer(params=[torch.nn.Parameter(torch.zeros(1))])
    except (TypeError, ValueError) as err:
        raise ConfigError(f"{group_key}.optimizer: {err}") from err
    if not scheduler:
        return {"optimizer": optimizer, "scheduler": None}
    factory = instantiate(scheduler)
    try:
        factory(optimizer=stand_in, total_steps=1)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"{group_key}.scheduler: {err}") from err
    return {"optimizer": optimizer, "scheduler": factory}


def render_compare_callback(cfg: DictConfig) -> L.Callback:
    """The callback of the ``render_compare`` group (it builds its refiner once to check its
    settings); a bad value is a one-line ConfigError."""
    try:
        return instantiate(cfg.render_compare, _convert_="all")
    except Exception as err:  # a bad refiner option: the innermost message, one line
        key = re.search(r"full_key: (\S+)", str(err))
        raise ConfigError(
            f"{key.group(1) if key else 'render_compare'}: {first_line(err)}"
        ) from None


def refinement_callbacks(cfg: DictConfig) -> list[L.Callback]:
    """The callback the `refine` group instantiates (none for refine=none, an empty group)."""
    if not cfg.get("refine"):
        return []
    try:
        return [instantiate(cfg.refine)]
    except Exception as err:  # a bad target or option: name the key Hydra reports
        key = re.search(r"full_key: (\S+)", str(err))
        raise ConfigError(f"{key.group(1) if key else 'refine'}: {first_line(err)}") from None
