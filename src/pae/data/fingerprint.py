"""The train images' part of a dataset's identity: a hash over every image's path, byte size
and every byte of its file, so that checkpoints notice other images at the same poses and any
edit of an image. Checkpoints written before recorded a sampled hash (4 KiB of each file), still
computed to check them.

Each file's BLAKE2b is kept in a :class:`DigestCache`, one JSON file beside the data
(``CACHE_NAME`` in its root), keyed by the file's path under the root, size and modification
time (ns): every later step and run reads back the digest of an unchanged file and hashes only
the files that changed or are new (an edit that keeps a file's size and modification time is
not seen)."""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import BinaryIO

from pae.core.atomic import write_text_atomic
from pae.core.errors import ImageError
from pae.data.labels import LabelTable

CHUNK_BYTES = 1 << 20
"""Bytes read at a time while hashing a whole file (the memory a file's hash needs)."""

SAMPLE_BYTES = 4096
"""Bytes read from the middle of each image file by the sampled hash (all of a smaller one)."""

CACHE_NAME = ".pae_fingerprint_cache.json"
"""The file in a dataset's root (in the image store, one per root, where the root is
read-only) that keeps each image file's BLAKE2b: ``{"blake2b": {path under the root: [size in bytes,
modification time in ns, digest hex]}}``."""


class DigestCache:
    """Each image file's BLAKE2b under ``root``, kept in the JSON file at ``path``
    (``CACHE_NAME``); read on creation (an absent or unreadable file: an empty cache),
    written by :meth:`save`."""

    def __init__(self, path: str | os.PathLike[str], root: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.root = Path(root)
        self.changed = False
        try:
            kept = json.loads(self.path.read_text(encoding="utf-8"))["blake2b"]
        except (OSError, ValueError, KeyError, TypeError):
            kept = {}
        self.files: dict[str, list] = kept if isinstance(kept, dict) else {}

    @classmethod
    def beside(cls, root: Path, spare: Path | None = None) -> DigestCache | None:
        """The cache of the images under ``root``: ``CACHE_NAME`` in ``root`` where it is a
        writable folder, else in ``spare`` (the image store's folder), named by ``root``'s
        absolute path, where one is given, else None (every file hashed each time)."""
        if os.access(root, os.W_OK | os.X_OK):
            return cls(root / CACHE_NAME, root)
        if spare is None:
            return None
        name = hashlib.sha1(os.path.abspath(root).encode(), usedforsecurity=False).hexdigest()
        return cls(spare / f"{Path(CACHE_NAME).stem}.{name[:16]}.json", root)

    def file_digest(
        self, path: Path, compute: Callable[[], tuple[int, bytes]]
    ) -> tuple[int, bytes]:
        """(size in bytes, BLAKE2b) of the file at ``path``: the kept one where the file's
        size and modification time are those it was hashed at, else ``compute()`` (which
        reads the file) and kept. OSError where the file cannot be read."""
        stat = os.stat(path)
        key = os.path.relpath(path, self.root)
        kept = self.files.get(key)
        if isinstance(kept, list) and kept[:2] == [stat.st_size, stat.st_mtime_ns]:
            try:
                return stat.st_size, bytes.fromhex(kept[2])
            except (IndexError, TypeError, ValueError):
                pass  # a damaged entry: hashed again
        size, digest = compute()
        self.files[key] = [stat.st_size, stat.st_mtime_ns, digest.hex()]
        self.changed = True
        return size, digest

    def save(self) -> None:
        """Write the cache whole where a digest was added since it was read; a failed write
        (a read-only folder, a full disk) leaves the old one, and later runs hash again."""
        if not self.changed:
            return
        try:
            text = json.dumps({"blake2b": self.files}, separators=(",", ":"), sort_keys=True)
            write_text_atomic(self.path, text + "\n")
        except OSError:
            return
        self.changed = False


def _each_image(
    table: LabelTable,
    root: Path,
    summary: Callable[[BinaryIO], tuple[int, bytes]],
    cache: DigestCache | None = None,
) -> Iterator[tuple[str, int, bytes]]:
    """(path as the label file gives it, size in bytes, ``summary``'s digest) per row, in row
    order (read from and kept in ``cache`` where one is given); an unreadable image is an
    ImageError naming it and its row."""
    for row, relative in enumerate(table.img_path):
        path = root / relative

        def compute(path: Path = path) -> tuple[int, bytes]:
            with path.open("rb") as handle:
                return summary(handle)

        try:
            size, digest = compute() if cache is None else cache.file_digest(path, compute)
        except OSError as err:
            where = f"{table.source or 'row'}:{table.file_line(row)}"
            raise ImageError(f"{path} ({where}): cannot be read ({err.strerror})") from None
        yield relative, size, digest


def _whole_file(handle: BinaryIO) -> tuple[int, bytes]:
    """(size in bytes, BLAKE2b of every byte), read in ``CHUNK_BYTES`` chunks."""
    digest = hashlib.blake2b()
    size = 0
    while chunk := handle.read(CHUNK_BYTES):
        digest.update(chunk)
        size += len(chunk)
    return size, digest.digest()


def _middle_sample(handle: BinaryIO) -> tuple[int, bytes]:
    """(size in bytes, SHA-256 of ``SAMPLE_BYTES`` from the middle of the file)."""
    size = handle.seek(0, 2)
    handle.seek(max(0, size // 2 - SAMPLE_BYTES // 2))
    return size, hashlib.sha256(handle.read(SAMPLE_BYTES)).digest()


def images_blake2b(table: LabelTable, root: Path, cache: DigestCache | None = None) -> str:
    """BLAKE2b (hex, 128 characters) over each row's ``img_path`` (as the label file gives it,
    so a copied dataset keeps its hash), its file's size in bytes and the BLAKE2b of every byte
    of the file, in row order: any edit of an image changes it. With a ``cache`` each file's
    BLAKE2b is read from it where the file's size and modification time are those it was
    hashed at, the others hashed and the cache saved (:class:`DigestCache`); the hash is the
    same. An unreadable image is an ImageError naming it and its row."""
    digest = hashlib.blake2b()
    try:
        for relative, size, file_digest in _each_image(table, root, _whole_file, cache):
            digest.update(f"{relative}\0{size}\0".encode())
            digest.update(file_digest)
    finally:
        if cache is not None:
            cache.save()
    return digest.hexdigest()


def sampled_images_sha256(table: LabelTable, root: Path) -> str:
    """The hash older checkpoints record: SHA-256 over each row's ``img_path``, its file's size
    and the SHA-256 of ``SAMPLE_BYTES`` from the middle of the file, in row order (an edit that
    keeps the size and misses the sample is not seen). An unreadable image is an ImageError
    naming it and its row."""
    digest = hashlib.sha256()
    for relative, size, sample_digest in _each_image(table, root, _middle_sample):
        digest.update(f"{relative}\0{size}\0".encode())
        digest.update(sample_digest)
    return digest.hexdigest()
