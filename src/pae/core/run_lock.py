"""One run per directory: an exclusive OS file lock on ``<run dir>/.pae-run.lock`` (``filelock``:
``flock`` on POSIX, ``LockFileEx`` on Windows), held from the start checks to the end of the
run by whoever holds the :class:`RunDirLock`. The operating system releases it when the
process ends, however it ends (a crash, a kill), so a stale lock cannot block a later run."""

from __future__ import annotations

import os
import socket
import time
from pathlib import Path

from filelock import FileLock, Timeout

from pae.core.errors import RunDirInUseError

LOCK_FILE = ".pae-run.lock"
"""In the run (or sweep) directory; holds the pid and host of the run that last locked it."""
RANK_VARIABLES = ("RANK", "LOCAL_RANK", "SLURM_PROCID", "JSM_NAMESPACE_RANK")
"""Set by distributed launchers: a process of rank > 0 is part of the run that rank 0 locked."""


def is_secondary_rank() -> bool:
    """Whether this process is a rank > 0 of a distributed run (its rank 0 holds the lock)."""
    return any(os.environ.get(name, "0") not in ("", "0") for name in RANK_VARIABLES)


class RunDirLock:
    """The lock of run directory ``folder`` (``key``: the setting that chose it, for errors)."""

    def __init__(self, folder: Path, key: str) -> None:
        self.folder = Path(os.path.abspath(folder))
        self.key = key
        self._lock: FileLock | None = None

    @property
    def path(self) -> Path:
        return self.folder / LOCK_FILE

    def acquire(self, record: bool = True) -> None:
        """Hold the lock (the folder and its lock file created if needed) until the process
        ends or :meth:`release`; ``record`` writes this process's pid into the lock file
        (False changes no file, for a check before anything may be written). A folder
        locked by another process is a RunDirInUseError naming that process; a filesystem
        without locks leaves the run unlocked."""
        if is_secondary_rank():
            return
        if self._lock is None:
            self.folder.mkdir(parents=True, exist_ok=True)
            lock = FileLock(
                self.path, thread_local=False, fallback_to_soft=False, preserve_lock_file=True
            )
            try:
                lock.acquire(timeout=0)
            except Timeout:
                holder = self.path.read_text(encoding="utf-8").strip()
                raise RunDirInUseError(
                    f"{self.key}={self.folder} is in use by another run "
                    f"({holder or 'a process that has not said its pid yet'}): wait for it to "
                    "end, or choose another directory"
                ) from None
            except (OSError, NotImplementedError):
                return
            self._lock = lock
        if record:
            started = time.strftime("%Y-%m-%d %H:%M:%S")
            with self.path.open("w", encoding="utf-8") as handle:
                handle.write(f"pid {os.getpid()} on {socket.gethostname()}, since {started}\n")

    def acquire_if_used(self) -> None:
        """Before the start checks: a folder that already has a lock file is locked now (or
        found in use), without writing anything; a new folder is locked after the checks."""
        if self.path.is_file():
            self.acquire(record=False)

    def release(self) -> None:
        """Let go of the lock, if held."""
        if self._lock is not None:
            self._lock.release()
            self._lock = None
