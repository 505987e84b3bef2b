"""The steps a run executes: fit a teacher, fit a student, evaluate checkpoints.

Each step writes into its own directory: checkpoints/, TensorBoard event files, and the
figures it measured; the entry points merge them into the run's metrics.json.
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import lightning as L
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from lightning.pytorch.loggers import Logger, TensorBoardLogger
from lightning.pytorch.utilities import rank_zero_info, rank_zero_only
from omegaconf import DictConfig, OmegaConf

from pae.callbacks.finite_loss import StopOnNonFiniteLoss
from pae.checkpoints import (
    DATA_FINGERPRINT_KEY,
    AtomicCheckpointIO,
    CheckpointError,
    LoadedModel,
    architecture_differences,
    load_pae,
    load_teacher,
    newest_readable_checkpoint,
    read_checkpoint,
)
from pae.console import say
from pae.data.datamodule import PoseDataModule
from pae.data.latents import LatentCache, TeacherLatentDataModule
from pae.errors import ConfigError, DivergenceError
from pae.lit.decoder import DecoderModule
from pae.lit.student import StudentEvaluator, StudentModule
from pae.lit.teacher import TeacherModule
from pae.provenance import dataset_line, flat_record, save_record
from pae.reporting import (
    best_refinement,
    first_line,
    format_results_table,
    headline_metrics,
)
from pae.steps import STEPS

Metrics = dict[str, float]


def build_data(cfg: DictConfig, **overrides: Any) -> PoseDataModule:
    """Instantiate and set up the configured data module (renders synthetic data if needed)."""
    data = instantiate(cfg.data, **overrides)
    data.setup()
    return data


def record_dataset(cfg: DictConfig, run_dir: Path) -> dict[str, str | int]:
    """Prepare the configured data (the default synthetic benchmark renders on first use),
    print which dataset the run reads and record it in `run_dir/.hydra/data.yaml` -> its
    `data/...` keys for metrics.json (pae.provenance)."""
    data = instantiate(cfg.data)
    data.prepare_data()
    record = data.describe()
    if rank_zero_only.rank == 0:
        say(dataset_line(record))
        save_record(record, run_dir)
    return flat_record(record)


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
    for name, c in (cfg.get("callbacks") or {}).items():
        extra: dict[str, Any] = {}
        if name == "model_checkpoint":
            extra = {"dirpath": str(step_dir / "checkpoints")}
        elif name == "epoch_progress":
            extra = {"step": step}
        configured.append(instantiate(c, **extra))
    loggers = _loggers(cfg, step_dir)
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
    newer one is unreadable), checked against the data; None when the step has none yet."""
    folder = step_dir / "checkpoints"
    if not cfg.get("resume"):
        return None
    path, skipped = newest_readable_checkpoint(folder)
    if path is None and skipped:
        raise CheckpointError(f"{folder}: no readable checkpoint to resume from ({skipped[0]})")
    if path is None:
        return None
    trained = read_checkpoint(path).get(DATA_FINGERPRINT_KEY)
    if trained is not None:
        _check_fingerprint(cfg, path, trained, data.fingerprint())
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


def _teacher_config(cfg: DictConfig, n_scenes: int) -> dict[str, Any]:
    """The teacher's architecture as stored in its checkpoint (weights come from the state dict)."""
    config = OmegaConf.to_container(cfg.teacher.model, resolve=True)
    config["n_scenes"] = n_scenes
    config["backbone"]["pretrained"] = False
    config["backbone"]["weights_path"] = None
    return config


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
    return metrics | collect_metrics(trainer, **checks)


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
    trainer = build_trainer(cfg, step_dir, epochs, [*(callbacks or []), finite], step=name)
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
    """A trained group's optimizer and scheduler factories (scheduler=null: a constant rate)."""
    scheduler = group.get("scheduler")
    return {
        "optimizer": instantiate(group.optimizer),
        "scheduler": instantiate(scheduler) if scheduler else None,
    }


def _frozen(
    cfg: DictConfig,
    path: str | Path | None,
    key: str,
    stage: str,
    load: Callable[[str | Path, str], LoadedModel],
) -> tuple[str | Path, LoadedModel, PoseDataModule]:
    """The checkpoint a step needs (`key`), its model and the step's data (no augmentation),
    checked to belong together."""
    path = required(path, key, stage)
    loaded = load(path, key)
    data = build_data(cfg, augment=False)
    check_data(cfg, path, loaded, data)
    return path, loaded, data


def fit_teacher(cfg: DictConfig, step_dir: Path) -> tuple[Metrics, Path]:
    """Train and test a teacher APR -> (metrics, path of its last checkpoint)."""
    data = build_data(cfg)
    teacher = instantiate(cfg.teacher.model, n_scenes=data.n_scenes)
    module = TeacherModule(
        teacher,
        loss=instantiate(cfg.teacher.loss),
        **optimisation(cfg.teacher),
        scene_names=data.scene_names,
        teacher_config=_teacher_config(cfg, data.n_scenes),
        scene_loss_weight=cfg.teacher.scene_loss_weight,
    )
    return fit_and_test(cfg, step_dir, "teacher", module, data, cfg.teacher.max_epochs)


def _check_fingerprint(
    cfg: DictConfig, path: str | Path, trained: dict[str, Any], data: dict[str, Any]
) -> None:
    """A checkpoint trained on other data (scene names, or train poses when it records them)
    is an error unless allow_other_data=true."""
    if cfg.get("allow_other_data"):
        return
    if trained["scenes"] != data["scenes"]:
        raise CheckpointError(
            f"{path}: trained on scenes {trained['scenes']}, but the data has scenes "
            f"{data['scenes']} (allow_other_data=true uses it anyway)"
        )
    if trained.get("train_poses_sha256", data["train_poses_sha256"]) != data["train_poses_sha256"]:
        raise CheckpointError(
            f"{path}: trained on other train poses than those of {data['scenes']} in this "
            "data's train labels (allow_other_data=true uses it anyway)"
        )


def check_data(
    cfg: DictConfig, path: str | Path, loaded: LoadedModel, data: PoseDataModule
) -> None:
    """The checkpoint was trained on this data, and its models fit this data's scene count."""
    if len(loaded.scene_names) != data.n_scenes:
        raise CheckpointError(
            f"{path}: trained on scenes {loaded.scene_names}, but the data has scenes "
            f"{data.scene_names}"
        )
    trained = loaded.data_fingerprint or {"scenes": loaded.scene_names}
    _check_fingerprint(cfg, path, trained, data.fingerprint())


def refinement_callbacks(cfg: DictConfig) -> list[L.Callback]:
    """The callback the `refine` group instantiates (none for refine=none, an empty group)."""
    if not cfg.get("refine"):
        return []
    try:
        return [instantiate(cfg.refine)]
    except Exception as err:  # a bad target or option: name the key Hydra reports
        key = re.search(r"full_key: (\S+)", str(err))
        raise ConfigError(f"{key.group(1) if key else 'refine'}: {first_line(err)}") from None


def fit_student(
    cfg: DictConfig, step_dir: Path, teacher_ckpt: str | Path | None
) -> tuple[Metrics, Path]:
    """Distil a PAE from a frozen teacher checkpoint, then test it (with refinement)."""
    teacher_ckpt, teacher, data = _frozen(
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


def required(path: str | Path | None, key: str, stage: str) -> str | Path:
    if path is None:
        raise ConfigError(f"stage={stage} needs {key}=PATH")
    return path


def fit_decoder(
    cfg: DictConfig, step_dir: Path, student_ckpt: str | Path | None
) -> tuple[Metrics, Path]:
    """Train an image decoder on a frozen PAE (from a student checkpoint), then test it."""
    _, pae, data = _frozen(cfg, student_ckpt, "student_ckpt", "decoder", load_pae)
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
