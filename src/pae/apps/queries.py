"""The images pae-localize is given: label files, or image files and folders, as label-file
rows."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np

from pae.core.errors import ConfigError, ImageError
from pae.data.labels import LabelTable, read_labels

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
QUERY_SPLIT = "query"
"""The ``split`` column of the rows written for images given without a label file."""


class Queries(NamedTuple):
    """The images to localise as label-file rows (``img_path`` joined to ``root``), whether
    their poses are labels (a label file was given) or placeholders, and each image's path
    as the output names it."""

    table: LabelTable
    root: Path
    labelled: bool
    shown: list[str]


def image_files(inputs: Sequence[str | Path]) -> list[Path]:
    """Image files given directly, and those under given folders (recursively, sorted)."""
    files: list[Path] = []
    for item in map(Path, inputs):
        if item.is_dir():
            found = sorted(p for p in item.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES)
            if not found:
                raise ImageError(f"{item}: a folder without images ({', '.join(IMAGE_SUFFIXES)})")
            files += found
        elif item.exists():
            files.append(item)
        else:
            raise ImageError(f"{item}: no such image, folder or label file")
    return files


def gather_queries(inputs: Sequence[str | Path], root: str | Path | None) -> Queries:
    """Label files (``*.csv``: their rows, ``img_path`` under ``root``), or image files and
    folders (one row each, ``split`` ``query``, ``seq`` the image's folder name)."""
    labels = [Path(p) for p in inputs if Path(p).suffix.lower() == ".csv"]
    if labels and len(labels) < len(inputs):
        raise ConfigError("give label files or images and folders, not both")
    if labels:
        if root is None:
            raise ConfigError(f"{labels[0]}: a label file's img_path needs --root")
        table = LabelTable.concat(read_labels(p) for p in labels)
        return Queries(table, Path(root), True, table.img_path)
    files = image_files(inputs)
    table = LabelTable(
        scene=[""] * len(files),
        split=[QUERY_SPLIT] * len(files),
        seq=[p.resolve().parent.name for p in files],
        img_path=[str(p.resolve()) for p in files],
        poses=np.tile([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], (len(files), 1)),
    )
    return Queries(table, Path(Path.cwd().anchor), False, [str(p) for p in files])
