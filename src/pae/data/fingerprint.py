"""The train images' part of a dataset's identity: a hash over every image's path, byte size
and every byte of its file, so that checkpoints notice other images at the same poses and any
edit of an image. Checkpoints written before recorded a sampled hash (4 KiB of each file), still
computed to check them."""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import BinaryIO

from pae.core.errors import ImageError
from pae.data.image_store import ImageStore
from pae.data.labels import LabelTable

CHUNK_BYTES = 1 << 20
"""Bytes read at a time while hashing a whole file (the memory a file's hash needs)."""

SAMPLE_BYTES = 4096
"""Bytes read from the middle of each image file by the sampled hash (all of a smaller one)."""


def _each_image(
    table: LabelTable,
    root: Path,
    summary: Callable[[BinaryIO], tuple[int, bytes]],
    store: ImageStore | None = None,
    name: str = "",
) -> Iterator[tuple[str, int, bytes]]:
    """(path as the label file gives it, size in bytes, ``summary``'s digest) per row, in row
    order (kept in ``store`` under ``name`` where a store is given); an unreadable image is an
    ImageError naming it and its row."""
    for row, relative in enumerate(table.img_path):
        path = root / relative

        def compute(path: Path = path) -> tuple[int, bytes]:
            with path.open("rb") as handle:
                return summary(handle)

        try:
            if store is None:
                size, digest = compute()
            else:
                size, digest = store.file_digest(str(path), compute, name)
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


def images_blake2b(table: LabelTable, root: Path, store: ImageStore | None = None) -> str:
    """BLAKE2b (hex, 128 characters) over each row's ``img_path`` (as the label file gives it,
    so a copied dataset keeps its hash), its file's size in bytes and the BLAKE2b of every byte
    of the file, in row order: any edit of an image changes it. With an image ``store`` each
    file's BLAKE2b is read from it where the file's size and modification time are those it
    was hashed at (:meth:`pae.data.image_store.ImageStore.file_digest`). An unreadable image
    is an ImageError naming it and its row."""
    digest = hashlib.blake2b()
    for relative, size, file_digest in _each_image(table, root, _whole_file, store, "blake2b"):
        digest.update(f"{relative}\0{size}\0".encode())
        digest.update(file_digest)
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
