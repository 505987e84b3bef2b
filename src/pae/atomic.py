"""Whole-or-nothing file writes: a temporary file beside the target, flushed to disk, then
one rename. Every file pae writes goes through ``atomic_write``: metrics, reports, error
lines, label files, checkpoints and cached latents (rendered datasets are built in a hidden
folder and renamed whole)."""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any


@contextmanager
def atomic_write(path: str | Path, mode: str = "w", **open_args: Any) -> Iterator[IO[Any]]:
    """Open a temporary file in `path`'s folder (same filesystem) for writing; on success it is
    flushed to disk and renamed over `path`, on failure removed. Readers see the old file or
    the whole new one, never a part (a full disk or a kill leaves `path` as it was)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    umask = os.umask(0)
    os.umask(umask)
    try:
        os.chmod(fd, 0o666 & ~umask)  # the permissions of an ordinary new file, not mkstemp's 0600
        with os.fdopen(fd, mode, **open_args) as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write ``text`` to ``path`` whole (see ``atomic_write``)."""
    with atomic_write(path) as handle:
        handle.write(text)


def write_json_atomic(path: str | Path, payload: Mapping[str, object]) -> None:
    """Write a JSON object to ``path`` whole (indented, sorted keys, final newline)."""
    write_text_atomic(path, json.dumps(dict(payload), indent=2, sort_keys=True) + "\n")
