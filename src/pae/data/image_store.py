"""Decoded images kept on disk at the size a run reads them, so that each image file is
decoded and resized once, not once per epoch and once more per step.

One entry per (image file, shorter edge): a 16-byte header (the file's height and width in
px, the entry's height and width, little-endian uint32) and the RGB pixels, uint8 [h, w, 3].
An entry's name hashes the file's absolute path, size, modification time (ns) and the
shorter edge, so an image rewritten in place gets a new entry, and every row of a label
file its own even where two rows' files are hard links to one. Entries are written to a
temporary name and renamed (two loader workers writing one entry leave one whole entry);
one whose length disagrees with its header is decoded again and rewritten. Nothing is
evicted: the folder holds about ``3 h w`` bytes per image (262 kB at 256 × 341 px).

Where the data's root is read-only, the store's folder also holds the cache of each train
image file's BLAKE2b (:class:`pae.data.fingerprint.DigestCache`).
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from pae.core.atomic import disk_full, no_space_error
from pae.core.errors import ConfigError, ImageError
from pae.data.transforms import load_sized_image

HEADER = np.dtype("<u4")
"""The header's four numbers: the file's height and width, the entry's height and width."""


class ImageStore:
    """The decoded images under ``folder`` (created on first write)."""

    def __init__(self, folder: str | os.PathLike[str]) -> None:
        self.folder = Path(folder)

    def entry(self, path: str, shorter_edge: int) -> Path:
        """Where the image at ``path`` resized to ``shorter_edge`` px is kept, named by the
        file's absolute path, size, modification time and ``shorter_edge``
        (FileNotFoundError where the file is missing)."""
        stat = os.stat(path)
        name = f"{os.path.abspath(path)}\0{stat.st_size}\0{stat.st_mtime_ns}\0{shorter_edge}"
        digest = hashlib.sha1(name.encode(), usedforsecurity=False).hexdigest()
        return self.folder / digest[:2] / f"{digest}.rgb"

    def read(self, path: str, shorter_edge: int) -> tuple[np.ndarray, tuple[int, int]]:
        """The image at ``path`` resized so its shorter edge is ``shorter_edge`` px, as
        :func:`pae.data.transforms.load_sized_image` gives it (uint8 [H, W, 3] RGB, the
        (h, w) in px it has in the file): from its entry where one is whole, else decoded
        and kept. A missing or unreadable image is an ImageError naming it."""
        try:
            entry = self.entry(path, shorter_edge)
        except FileNotFoundError:
            return load_sized_image(path, shorter_edge)  # its ImageError names the path
        kept = _read_entry(entry)
        if kept is not None:
            return kept
        image, size = load_sized_image(path, shorter_edge)
        _write_image(entry, image, size)
        return image, size

    def fill(self, paths: Sequence[str], shorter_edge: int, threads: int) -> int:
        """Decode every image of ``paths`` that has no whole entry at ``shorter_edge`` px and
        keep it, on ``threads`` threads (OpenCV decodes without the GIL) -> how many were
        decoded. A missing or unreadable image is an ImageError naming it."""
        with ThreadPoolExecutor(max(1, threads)) as pool:
            return sum(pool.map(lambda path: self._fill_one(path, shorter_edge), paths))

    def _fill_one(self, path: str, shorter_edge: int) -> bool:
        try:
            entry = self.entry(path, shorter_edge)
        except FileNotFoundError:
            raise ImageError(f"{path}: missing or unreadable image") from None
        if _read_entry(entry) is not None:
            return False
        _write_image(entry, *load_sized_image(path, shorter_edge))
        return True


def _read_entry(entry: Path) -> tuple[np.ndarray, tuple[int, int]] | None:
    """An entry's image and file size; None where it is absent or not whole."""
    try:
        data = entry.read_bytes()
    except OSError:
        return None
    if len(data) < 4 * HEADER.itemsize:
        return None
    file_h, file_w, h, w = (int(v) for v in np.frombuffer(data, HEADER, 4))
    if len(data) != 4 * HEADER.itemsize + 3 * h * w:
        return None
    pixels = np.frombuffer(data, np.uint8, offset=4 * HEADER.itemsize).reshape(h, w, 3)
    return pixels.copy(), (file_h, file_w)


def _write_image(entry: Path, image: np.ndarray, size: tuple[int, int]) -> None:
    """Keep ``image`` [h, w, 3] (of a file of ``size`` (h, w)) at ``entry``."""
    header = np.array([*size, *image.shape[:2]], HEADER).tobytes()
    _write_entry(entry, header, np.ascontiguousarray(image).tobytes())


def _write_entry(entry: Path, header: bytes, body: bytes) -> None:
    """Keep ``header`` then ``body`` at ``entry``, atomically; a failed write is a one-line
    error naming the entry (DiskFullError on a full disk, else a ConfigError naming
    ``data.image_store``)."""
    temporary = None
    try:
        entry.parent.mkdir(parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(dir=entry.parent, suffix=".part")
        with os.fdopen(handle, "wb") as out:
            out.write(header)
            out.write(body)
        os.replace(temporary, entry)
    except BaseException as err:
        if temporary is not None:
            Path(temporary).unlink(missing_ok=True)
        if not isinstance(err, OSError):
            raise
        if no_space_error(err) is not None:
            raise disk_full(entry) from None
        reason = err.strerror or type(err).__name__
        raise ConfigError(f"data.image_store: cannot write {entry} ({reason})") from None
