"""Checks that run before Hydra creates or writes anything in a run directory: the settings,
the run directory itself (free of other runs: pae.core.run_lock), and whether a resumed run can
continue with the given settings. Only the resume checks load torch: a sweep's launching
process runs the others without it."""

from __future__ import annotations

import os
import traceback
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from pae.config.optuna_study import keeps_a_study
from pae.config.validation import apply_renamed_keys, validate_eval_config, validate_train_config
from pae.core.atomic import check_writable_dir
from pae.core.error_reporting import reporting_errors
from pae.core.errors import ConfigError
from pae.core.run_lock import RunDirLock
from pae.steps import RESUMABLE_CHANGES


def _check_latent_cache(config: DictConfig) -> None:
    """The teacher-latent cache folder, when one is set, can be written."""
    folder = OmegaConf.select(config, "student.latent_cache_dir", default=None)
    if folder:
        check_writable_dir(Path(folder), "student.latent_cache_dir")


def _checkpoint_folders(run_dir: Path) -> list[Path]:
    return sorted({p.parent for p in run_dir.glob("**/checkpoints/*.ckpt")})


def _changed_settings(old: DictConfig, new: DictConfig) -> list[str]:
    """Keys whose value differs between two run configs, except RESUMABLE_CHANGES."""
    from pae.runs.hparams import flat_config

    before, after = flat_config(old, sep="."), flat_config(new, sep=".")
    changed = []
    for key in sorted(before.keys() | after.keys()):
        if before.get(key) != after.get(key) and not key.startswith(RESUMABLE_CHANGES):
            changed.append(f"{key}: {before.get(key, '(unset)')} -> {after.get(key, '(unset)')}")
    return changed


def check_resume(cfg: DictConfig, run_dir: Path) -> None:
    """resume=true continues `run_dir` only if it is an earlier run with the same settings
    (RESUMABLE_CHANGES aside) and every step folder with checkpoints has a readable one."""
    from pae.core.checkpoints import newest_readable_checkpoint

    saved = run_dir / ".hydra" / "config.yaml"
    if not saved.is_file():
        raise ConfigError(
            f"resume=true: {run_dir} is not an earlier run (no .hydra/config.yaml); "
            "pass hydra.run.dir=<the run directory to continue>"
        )
    earlier = OmegaConf.load(saved)
    apply_renamed_keys(earlier)  # a run made before a key was renamed
    changed = _changed_settings(earlier, cfg)
    if changed:
        more = f" and {len(changed) - 3} more" if len(changed) > 3 else ""
        raise ConfigError(
            f"resume=true: {run_dir} was trained with other settings ({'; '.join(changed[:3])}"
            f"{more}); resume with its settings, or start a new run"
        )
    for folder in _checkpoint_folders(run_dir):
        path, skipped = newest_readable_checkpoint(folder)
        if path is None:
            raise ConfigError(f"resume=true: no readable checkpoint in {folder} ({skipped[0]})")


def check_fresh(run_dir: Path, key: str, program: str = "pae-train") -> None:
    """A new run must not overwrite an earlier one with checkpoints in `run_dir`; the error
    says what `program` can do instead (pae-eval takes no resume=true)."""
    folders = _checkpoint_folders(run_dir) if run_dir.is_dir() else []
    if not folders:
        return
    if program == "pae-eval":
        remedy = (
            "pae-eval would write its metrics.json and .hydra/ over that run's; choose another "
            "directory (the checkpoints are read from student_ckpt, scene_model_ckpt, ...)"
        )
    else:
        remedy = "resume=true continues it; choose another directory to start a new run"
    raise ConfigError(
        f"{key}={run_dir} already holds the checkpoints of a run ({folders[0]}): {remedy}"
    )


class Preflight(Callback):
    """Hydra callback (conf/train.yaml, conf/eval.yaml: hydra.callbacks): every check that can
    fail runs here, before Hydra creates the run directory or rewrites its .hydra/ files, and
    ends in one line. Sweep jobs check their settings again when they start."""

    def __init__(self, program: str) -> None:
        self.program = program
        self.locks: dict[Path, RunDirLock] = {}
        """Run (or sweep) directory -> its lock, held from the checks to the run's end."""

    def __getstate__(self) -> dict[str, Any]:
        """What a launcher that pickles the callbacks (joblib, submitit) sends to the sweep's
        job processes: the program, without the locks, which the launching process holds."""
        return {"program": self.program, "locks": {}}

    def _validate(self, config: DictConfig) -> None:
        if self.program == "pae-train":
            validate_train_config(config)
        else:
            validate_eval_config(config)

    def on_run_start(self, config: DictConfig, **kwargs: Any) -> None:
        self._check(config, Path(config.hydra.run.dir), "hydra.run.dir", sweep=False)

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        self._check(config, Path(config.hydra.sweep.dir), "hydra.sweep.dir", sweep=True)

    def on_run_end(self, config: DictConfig, **kwargs: Any) -> None:
        self._release(Path(config.hydra.run.dir))

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        self._release(Path(config.hydra.sweep.dir))

    def _release(self, folder: Path) -> None:
        lock = self.locks.pop(Path(os.path.abspath(folder)), None)
        if lock is not None:
            lock.release()

    def _check(self, config: DictConfig, folder: Path, key: str, sweep: bool) -> None:
        """The run (or sweep) directory `folder` can be written, is not in use by another run
        and holds no other run's checkpoints, or, with resume=true, an earlier run of these
        settings (single runs) or the trials of an earlier run of its Optuna study (sweeps
        of ``hparams_search``); every setting; the latent cache folder. Then `folder` is
        locked for the run. A failing check ends the process: one line for a user error, the
        traceback for anything else (Hydra would only warn and run)."""
        try:
            with reporting_errors(self.program):
                apply_renamed_keys(config, self.program)
                check_writable_dir(folder, key)
                lock = self.locks.setdefault(Path(os.path.abspath(folder)), RunDirLock(folder, key))
                lock.acquire_if_used()
                if not config.get("resume") and not (sweep and keeps_a_study(config)):
                    check_fresh(folder, key, self.program)
                if not sweep:  # sweep jobs check their own settings when they start
                    self._validate(config)  # first: it may correct data settings (validation)
                if config.get("resume") and not sweep:
                    check_resume(config, folder)
                _check_latent_cache(config)
                lock.acquire()
        except Exception:
            traceback.print_exc()
            raise SystemExit(1) from None
