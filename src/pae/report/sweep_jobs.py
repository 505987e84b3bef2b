"""The jobs a Hydra sweep was started with, read back from its ``multirun.yaml``: what
``pae-report`` checks the finished run directories against (a job that never started has
no directory to find)."""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple

from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import OmegaConf

MULTIRUN_FILE = "multirun.yaml"
"""What Hydra writes at the top of a sweep directory before it launches the jobs."""
_BASIC_SWEEPER = "hydra._internal.core_plugins.basic_sweeper.BasicSweeper"
_JOB_NUMBER_SUBDIR = "${hydra.job.num}"


class SweepJob(NamedTuple):
    """One job of a sweep: its number, its overrides and, where the sweep names job folders
    by number (pae's configs do), its run directory (else None)."""

    number: int
    overrides: list[str]
    run_dir: Path | None


def _parse(arguments: list[str]) -> list[list[str]]:
    """Each job's overrides, as Hydra's basic sweeper expands the sweep's arguments."""
    try:
        overrides = OverridesParser.create().parse_overrides(arguments)
    except Exception:  # glob(...) choices need the config groups: parse with pae's
        from hydra._internal.config_loader_impl import ConfigLoaderImpl
        from hydra._internal.utils import create_config_search_path

        from pae import CONFIG_DIR

        loader = ConfigLoaderImpl(config_search_path=create_config_search_path(CONFIG_DIR))
        overrides = OverridesParser.create(config_loader=loader).parse_overrides(arguments)
    return [job for batch in BasicSweeper.split_arguments(overrides, None) for job in batch]


def sweep_jobs(sweep_dir: Path) -> list[SweepJob] | None:
    """The jobs of the sweep in `sweep_dir` (numbered as Hydra numbers them), or None where
    they cannot be known: no or an unreadable multirun.yaml, or a sweeper other than
    Hydra's basic one (an optimiser chooses its jobs as it goes)."""
    try:
        config = OmegaConf.load(sweep_dir / MULTIRUN_FILE)
        raw = OmegaConf.to_container(config.hydra, resolve=False)
        if raw["sweeper"].get("_target_") != _BASIC_SWEEPER:
            return None
        params = raw["sweeper"].get("params") or {}
        arguments = [f"{key}={value}" for key, value in params.items()]
        jobs = _parse([*arguments, *raw["overrides"]["task"]])
    except Exception:  # a damaged or foreign file: the report lists what it finds
        return None
    numbered = raw["sweep"].get("subdir") == _JOB_NUMBER_SUBDIR
    return [
        SweepJob(number, overrides, sweep_dir / str(number) if numbered else None)
        for number, overrides in enumerate(jobs)
    ]
