"""One run per directory: an exclusive OS file lock (``flock``) on ``<run dir>/.pae-run.lock``,
held from the start checks to the end of the run. The operating system releases it when the
process ends, however it ends (a crash, a kill), so a stale lock cannot block a later run."""

from __future__ import annotations

import errno
import os
import socket
import time
from pathlib import Path
from typing import IO

from pae.core.errors import RunDirInUseError

try:
    import fcntl
except ImportError:  # not POSIX: runs are not locked
    fcntl = None

LOCK_FILE = ".pae-run.lock"
"""In the run (or sweep) directory; holds the pid and host of the run that last locked it."""
RANK_VARIABLES = ("RANK", "LOCAL_RANK", "SLURM_PROCID", "JSM_NAMESPACE_RANK")
"""Set by distributed launchers: a process of rank > 0 is part of the run that rank 0 locked."""
_HELD: dict[Path, IO[str]] = {}


def is_secondary_rank() -> bool:
    """Whether this process is a rank > 0 of a distributed run (its rank 0 holds the lock)."""
    return any(os.environ.get(name, "0") not in ("", "0") for name in RANK_VARIABLES)


def lock_run_dir(folder: Path, key: str, record: bool = True) -> None:
    """Hold the lock of `folder` (created with its lock file if needed) until the process
    ends or ``release_run_dir``; record=True writes this process's pid into the lock file
    (record=False changes no file, for a check before anything may be written). A folder
    locked by another process is a RunDirInUseError naming that process (`key`: the setting
    that chose the folder)."""
    if fcntl is None or is_secondary_rank():
        return
    folder = Path(os.path.abspath(folder))
    handle = _HELD.get(folder)
    if handle is None:
        folder.mkdir(parents=True, exist_ok=True)
        handle = open(folder / LOCK_FILE, "a+", encoding="utf-8")  # noqa: SIM115 (held open)
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as err:
            handle.seek(0)
            holder = handle.read().strip() or "a process that has not said its pid yet"
            handle.close()
            if err.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                return  # a filesystem without locks: the run goes on unlocked
            raise RunDirInUseError(
                f"{key}={folder} is in use by another run ({holder}): wait for it to end, "
                "or choose another directory"
            ) from None
        _HELD[folder] = handle
    if record:
        handle.seek(0)
        handle.truncate()
        started = time.strftime("%Y-%m-%d %H:%M:%S")
        handle.write(f"pid {os.getpid()} on {socket.gethostname()}, since {started}\n")
        handle.flush()


def lock_if_used(folder: Path, key: str) -> None:
    """Before the start checks: a folder that already has a lock file is locked now (or found
    in use), without writing anything; a new folder is locked after the checks."""
    if (folder / LOCK_FILE).is_file():
        lock_run_dir(folder, key, record=False)


def release_run_dir(folder: Path) -> None:
    """Let go of the lock of `folder`, if this process holds it."""
    handle = _HELD.pop(Path(os.path.abspath(folder)), None)
    if handle is not None:
        handle.close()
