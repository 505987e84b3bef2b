"""Whole-or-nothing file writes: a temporary file beside the target, flushed to disk, then
one rename. Every file pae writes goes through ``atomic_write``: metrics, reports, error
lines, label files, checkpoints and cached latents (rendered datasets are built in a hidden
folder and renamed whole). A write that fails for want of space raises DiskFullError, one line
naming the device and the file."""

from __future__ import annotations

import errno
import json
import os
import tempfile
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

from pae.core.errors import DiskFullError

_NO_SPACE = (errno.ENOSPC, errno.EDQUOT)


def no_space_error(err: BaseException) -> OSError | None:
    """The "no space left" (or quota) OSError behind ``err``: itself, or one it was raised
    from or while handling (torch.save reports a full disk as "unexpected pos" from it); the
    first that names its file, if any does (a failed write, then a failed clean-up)."""
    seen: set[int] = set()
    found: list[OSError] = []
    cause: BaseException | None = err
    while cause is not None and id(cause) not in seen:
        seen.add(id(cause))
        if isinstance(cause, OSError) and cause.errno in _NO_SPACE:
            found.append(cause)
        cause = cause.__cause__ or cause.__context__
    named = [error for error in found if error.filename is not None]
    return next(iter(named + found), None)


def device_of(path: str | Path) -> str:
    """The filesystem holding ``path``: "DEVICE (mounted at MOUNT POINT)" where the mount
    table names the device, else the mount point."""
    mount = Path(os.path.abspath(path))
    while not mount.exists() and mount != mount.parent:
        mount = mount.parent
    while not os.path.ismount(mount) and mount != mount.parent:
        mount = mount.parent
    device = None
    try:
        with open("/proc/self/mounts", encoding="utf-8") as table:
            for line in table:
                fields = line.split()
                if len(fields) > 1 and fields[1].replace("\\040", " ") == str(mount):
                    device = fields[0]
    except OSError:
        pass
    return f"{device} (mounted at {mount})" if device else str(mount)


def disk_full(path: str | Path) -> DiskFullError:
    """The one-line error of a write to ``path`` that found no space left."""
    error = DiskFullError(f"no space left on {device_of(path)} while writing {path}")
    error.errno = errno.ENOSPC
    return error


@contextmanager
def atomic_write(path: str | Path, mode: str = "w", **open_args: Any) -> Iterator[IO[Any]]:
    """Open a temporary file in `path`'s folder (same filesystem) for writing; on success it is
    flushed to disk and renamed over `path`, on failure removed. Readers see the old file or
    the whole new one, never a part (a full disk or a kill leaves `path` as it was)."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as err:
        if err.errno in _NO_SPACE:
            raise disk_full(path) from None
        raise
    umask = os.umask(0)
    os.umask(umask)
    try:
        os.chmod(fd, 0o666 & ~umask)  # the permissions of an ordinary new file, not mkstemp's 0600
        with os.fdopen(fd, mode, **open_args) as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException as err:
        Path(tmp).unlink(missing_ok=True)
        if isinstance(err, Exception) and no_space_error(err) is not None:
            raise disk_full(path) from None
        raise


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` whole (see ``atomic_write``)."""
    with atomic_write(path) as handle:
        handle.write(text)


def write_json_atomic(path: str | Path, payload: Mapping[str, object]) -> None:
    """Write a JSON object to ``path`` whole (indented, sorted keys, final newline); strict
    JSON: a NaN or infinite value is a ValueError, never written."""
    text = json.dumps(dict(payload), indent=2, sort_keys=True, allow_nan=False)
    write_text_atomic(path, text + "\n")


def _creatable_in(path: Path, name: str) -> None:
    """ConfigError (``name``: how to call ``path``) unless the nearest existing folder of
    ``path`` or above it is a writable directory."""
    from pae.core.errors import ConfigError

    existing = path
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise ConfigError(f"{name}: cannot be written ({existing} is a file, not a folder)")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ConfigError(f"{name}: cannot be written ({existing} is not writable)")


def check_writable_dir(path: str | Path, key: str) -> None:
    """``path`` exists as a writable folder or can be created; else ConfigError naming ``key``
    (checked before any work, so that a finished computation is never lost to its output)."""
    from pae.core.errors import ConfigError

    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ConfigError(f"{key}={path}: is a file, not a folder")
    _creatable_in(path, f"{key}={path}")


def check_writable_file(path: str | Path, key: str) -> None:
    """``path`` can be written as a file: not a folder, its folder writable or creatable;
    else ConfigError naming ``key``."""
    from pae.core.errors import ConfigError

    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"{key} {path}: is a folder, not a file")
    _creatable_in(path.parent, f"{key} {path}")
