"""The images pae-localize is given: label files, or image files and folders, as label-file
rows."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from pae.core.errors import ConfigError, ImageError
from pae.core.geometry import canonicalize_quaternion, normalize_pose, pose_errors
from pae.core.metrics import summarise_errors
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


def canonical(poses: Tensor) -> Tensor:
    """Poses [N, 7] as label files store them: unit quaternion with ``qw >= 0``."""
    poses = normalize_pose(poses.double())
    return torch.cat([poses[:, :3], canonicalize_quaternion(poses[:, 3:])], -1)


def summary_line(
    method: str,
    poses: Tensor,
    queries: Queries,
    scene_names: list[str],
    assigned: Tensor | None = None,
) -> str:
    """The median errors of ``poses`` [N, 7] against the label file's poses (per scene,
    averaged over scenes, as pae-eval's overall figures) and, for a multi-scene teacher
    whose scenes the label file names, the share of the scenes ``assigned`` [N] (ids into
    ``scene_names``) that are the label file's."""
    table = queries.table
    truth = torch.as_tensor(table.poses, dtype=torch.float32)
    known = [s for s in table.scene_names if s in scene_names]
    names = scene_names if known == table.scene_names else table.scene_names
    scene = torch.as_tensor(table.scene_ids(names))
    pos, rot = pose_errors(poses.float(), truth)
    summary = summarise_errors(pos, rot, scene, names)
    line = (
        f"{method}: median {float(summary['pos_median_m']):.3f} m / "
        f"{float(summary['rot_median_deg']):.2f}° against the label file's poses "
        f"({len(table)} images; within 10 cm, 10°: "
        f"{100 * float(summary['within_10cm_10deg']):.1f} %"
    )
    if assigned is not None and len(scene_names) > 1 and set(table.scene) <= set(scene_names):
        true = torch.as_tensor([scene_names.index(s) for s in table.scene])
        line += f"; scene accuracy {100 * float((assigned == true).float().mean()):.1f} %"
    return line + ")"


def output_table(queries: Queries, poses: Tensor, scene: Tensor, names: list[str]) -> LabelTable:
    """Label-file rows of the queries with ``poses`` [N, 7]: a label file's own columns, or
    for images the scene the teacher assigns (``scene`` [N], ids into ``names``) and the path
    as given."""
    table = queries.table
    scenes = table.scene if queries.labelled else [names[i] for i in scene.tolist()]
    return LabelTable(
        scene=scenes,
        split=table.split,
        seq=table.seq,
        img_path=queries.shown,
        poses=canonical(poses).numpy(),
        focal=table.focal,
    )
