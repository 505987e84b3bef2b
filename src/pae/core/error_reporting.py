"""User errors in one line: what the ``pae-*`` programs report of a failed run
(:func:`reporting_errors`), and the one-line record a failed Hydra job leaves in its run
directory (``ERROR_FILE``, which ``pae-report`` lists)."""

from __future__ import annotations

import os
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from hydra.errors import CompactHydraException, HydraException, InstantiationException
from hydra.types import RunMode
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from pae.core.atomic import disk_full, no_space_error, write_text_atomic
from pae.core.errors import (
    BackboneError,
    CheckpointError,
    ConfigError,
    DiskFullError,
    DivergenceError,
    ExportError,
    ImageError,
    LabelError,
    RunDirInUseError,
)

ERROR_FILE = "error.txt"
"""A failed run's one-line error, written into its run directory (pae-report lists it)."""


class SweepJobFailed(CompactHydraException):
    """A sweep job stopped on a user error: Hydra goes on with the other jobs, then ends the
    sweep with this one line and exit status 1."""


USER_ERRORS = (
    ConfigError,
    LabelError,
    ImageError,
    CheckpointError,
    BackboneError,
    DivergenceError,
    DiskFullError,
    ExportError,
    RunDirInUseError,
    OmegaConfBaseException,
    HydraException,
)
"""Reported in one line (``pae.core.errors``, and Hydra's and OmegaConf's own config errors)."""


def first_line(err: BaseException) -> str:
    """The user-facing line of an error: the root of a Hydra instantiation error, and the
    original message (not the worker traceback) of an error raised in a DataLoader worker."""
    cause = err
    while isinstance(cause, InstantiationException) and cause.__cause__ is not None:
        cause = cause.__cause__
    lines = [line.strip() for line in str(cause).strip().splitlines() if line.strip()]
    if lines and lines[0].startswith("Caught ") and "Traceback" in str(cause):
        lines = [lines[-1].split(": ", 1)[-1]]
    return " ".join(" ".join(lines).split()) or type(cause).__name__


def config_error_line(err: HydraException | OmegaConfBaseException) -> str:
    """The line of a config that Hydra could not compose (an override of a key no schema
    has, a value of the wrong type): the key and what is wrong with it."""
    cause = err.__cause__ if isinstance(err.__cause__, OmegaConfBaseException) else err
    key = getattr(cause, "full_key", None)
    if key and isinstance(cause, OmegaConfBaseException):
        return f"{key}: {str(cause).strip().splitlines()[0]}"
    return first_line(err).split(" Config search path:")[0]


def in_one_line(program: str, hydra_main: Callable[[], object]) -> Callable[[], None]:
    """The console entry point of ``hydra_main`` (a ``hydra.main`` function): what Hydra
    reports itself before or after the run (a config it cannot compose, a failed sweep) is
    said in one line ``<program>: error: ...`` with exit status 1. ``HYDRA_FULL_ERROR=1``
    keeps Hydra's own report with its traceback."""

    def entry() -> None:
        if os.environ.get("HYDRA_FULL_ERROR") == "1":
            hydra_main()
            return
        os.environ["HYDRA_FULL_ERROR"] = "1"  # Hydra raises instead of printing
        try:
            hydra_main()
        except (HydraException, OmegaConfBaseException) as err:
            line = config_error_line(err)
            prefix = f"{program}: error: "
            print(line if line.startswith(prefix) else prefix + line, file=sys.stderr)
            raise SystemExit(1) from None
        finally:
            del os.environ["HYDRA_FULL_ERROR"]

    return entry


def _hydra_job() -> tuple[Path, bool] | None:
    """(output directory, whether it is a sweep job) of the running Hydra job, if any."""
    if not HydraConfig.initialized():
        return None
    hydra_cfg = HydraConfig.get()
    output_dir = OmegaConf.select(hydra_cfg, "runtime.output_dir", throw_on_missing=False)
    if output_dir is None or not Path(output_dir).is_dir():
        return None
    return Path(output_dir), hydra_cfg.mode == RunMode.MULTIRUN


def _writer_file(thread: threading.Thread | None) -> str | None:
    """The event file of a TensorBoard writer thread (its record writer's file); None for any
    other thread."""
    record_writer = getattr(thread, "_record_writer", None)
    name = getattr(getattr(record_writer, "_writer", None), "filename", None)
    return os.fsdecode(name) if isinstance(name, str | bytes) else None


def _name_full_disks_in_writer_threads() -> None:
    """Install (once per process) a thread exception hook for TensorBoard's event writer
    threads: a full disk there is not printed as the thread's traceback; the error gets the
    event file's name, and the thread hands it to the next write of the run, which
    reporting_errors reports in one line naming the file. Other errors in threads go to the
    hook installed before."""
    previous = threading.excepthook
    if getattr(previous, "names_full_disks", False):
        return

    def hook(args: threading.ExceptHookArgs) -> None:
        name = _writer_file(args.thread)
        full = no_space_error(args.exc_value) if args.exc_value is not None else None
        if name is None or full is None:
            previous(args)
        elif full.filename is None:
            full.filename = name

    hook.names_full_disks = True  # type: ignore[attr-defined]
    threading.excepthook = hook


@contextmanager
def reporting_errors(program: str) -> Iterator[None]:
    """Turn user errors (bad labels, images, checkpoints, config) into one line on stderr.

    Outside Hydra and in single runs the process exits with status 1. Inside a Hydra job the
    error is also written to `<run dir>/error.txt` (any error, tracebacks too; a finished job
    removes an old one); a sweep job raises SweepJobFailed instead of exiting, so that the
    other jobs of the sweep still run. A full disk met by a TensorBoard writer thread is
    reported the same way, naming the event file (_name_full_disks_in_writer_threads).
    """
    _name_full_disks_in_writer_threads()
    job = _hydra_job()
    try:
        try:
            yield
        except Exception as err:
            full = no_space_error(err)
            if full is None or isinstance(err, DiskFullError):
                raise
            if full.filename is None:
                raise DiskFullError(f"no space left on a device ({full})") from None
            raise disk_full(full.filename) from None
    except USER_ERRORS as err:
        line = f"{program}: error: {first_line(err)}"
        print(line, file=sys.stderr)
        if job is None:
            raise SystemExit(1) from None
        run_dir, sweep = job
        record_failure(run_dir, line)
        if not sweep:
            raise SystemExit(1) from None
        raise SweepJobFailed(
            f"{program}: error: a sweep job failed ({run_dir}: {first_line(err)}); "
            f"pae-report {run_dir.parent} lists every failed job"
        ) from None
    except Exception as err:
        if job is not None:
            record_failure(job[0], f"{type(err).__name__}: {first_line(err)}")
        raise
    if job is not None:
        (job[0] / ERROR_FILE).unlink(missing_ok=True)


def record_failure(run_dir: Path, line: str) -> None:
    """Write a run's one-line error to `<run_dir>/error.txt`, atomically; where that cannot
    be written (the disk is full) the line on stderr is the record."""
    with suppress(OSError):
        write_text_atomic(run_dir / ERROR_FILE, line + "\n")
