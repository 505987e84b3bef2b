"""Label files: one row per image with its scene, split, sequence, path and camera pose.

The format is the one of the public MS-Transformer / PAE code::

    scene,split,seq,img_path,t1,t2,t3,q1,q2,q3,q4
    chess,test,seq-03,chess/seq-03/frame-000000.color.png,-0.0513658,...

``img_path`` is relative to a dataset root, ``t1..t3`` is the camera position in metres (world
frame) and ``q1..q4`` the camera-to-world orientation as a quaternion with the scalar part
first (``q1``). An optional ``focal`` column gives each image's focal length in px at the
resolution of the data's camera (``data.camera``; e.g. Cambridge's per-image focal
lengths). An optional ``orientation`` column records each row's convention,
``camera_to_world`` (what pae writes) or ``world_to_camera`` (conjugated on reading); a file
without it whose orientations look world-to-camera (``pae.data.orientation``: cameras far
more upright conjugated) is read as it is, with a warning naming the command that converts
it. Columns are found by name, so their order does not matter and other extra columns are
ignored.
"""

from __future__ import annotations

import csv
import os
import warnings
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

from pae.core.atomic import atomic_write
from pae.core.errors import LabelError, LabelWarning, OrientationWarning, RepeatedImageWarning
from pae.core.quaternion_sign import canonical_sign
from pae.data.orientation import conjugate, looks_world_to_camera

__all__ = [
    "LABEL_COLUMNS",
    "LabelError",
    "LabelTable",
    "LabelWarning",
    "focal_column_mismatch",
    "focal_problems",
    "read_labels",
    "read_labels_lenient",
    "write_labels",
]

LABEL_COLUMNS: tuple[str, ...] = (
    "scene",
    "split",
    "seq",
    "img_path",
    "t1",
    "t2",
    "t3",
    "q1",
    "q2",
    "q3",
    "q4",
)
TEXT_COLUMNS = LABEL_COLUMNS[:4]
POSE_COLUMNS = LABEL_COLUMNS[4:]
FOCAL_COLUMN = "focal"
ORIENTATION_COLUMN = "orientation"
CAMERA_TO_WORLD, WORLD_TO_CAMERA = "camera_to_world", "world_to_camera"
FOCAL_WIDTH_RANGE = (0.1, 10.0)
"""Plausible focal lengths, as multiples of the width (px) of the images they refer to."""
REQUIRED_TEXT_COLUMNS = ("scene", "split", "img_path")

ZERO_QUATERNION_NORM = 1e-8
"""Quaternions with a smaller norm carry no orientation and are rejected."""
NON_UNIT_TOLERANCE = 1e-3
"""Quaternions whose norm differs from 1 by more than this are reported when normalised."""
_RENORMALISE_TOLERANCE = 1e-12
"""Norms closer to 1 are left as read, so that read → write → read is exact."""


@dataclass(frozen=True, eq=False)
class LabelTable:
    """Rows of a label file.

    ``poses`` is ``[N, 7]`` float64 (``x, y, z`` in metres, then ``qw, qx, qy, qz``).
    ``source`` names the file the rows came from and ``lines`` ``[N]`` holds each row's 1-based
    line number in it (the header is line 1; default: row ``i`` on line ``i + 2``); both serve
    error messages only. ``focal`` ``[N]`` (px), when the file has the column, else None.
    """

    scene: list[str]
    split: list[str]
    seq: list[str]
    img_path: list[str]
    poses: np.ndarray
    source: str = ""
    lines: np.ndarray | None = field(default=None, repr=False)
    focal: np.ndarray | None = field(default=None, repr=False)

    def __post_init__(self) -> None:
        poses = np.asarray(self.poses, dtype=np.float64).reshape(-1, 7)
        object.__setattr__(self, "poses", poses)
        for name in TEXT_COLUMNS:
            object.__setattr__(self, name, list(getattr(self, name)))
            if len(getattr(self, name)) != len(poses):
                raise ValueError(
                    f"LabelTable: column {name} has {len(getattr(self, name))} rows, "
                    f"poses have {len(poses)}"
                )
        if self.lines is None:
            lines = np.arange(len(poses), dtype=np.int64) + 2
        else:
            lines = np.asarray(self.lines, dtype=np.int64).reshape(-1)
            if len(lines) != len(poses):
                raise ValueError(f"LabelTable: {len(lines)} line numbers for {len(poses)} rows")
        object.__setattr__(self, "lines", lines)
        if self.focal is not None:
            focal = np.asarray(self.focal, dtype=np.float64).reshape(-1)
            if len(focal) != len(poses):
                raise ValueError(f"LabelTable: {len(focal)} focal lengths for {len(poses)} rows")
            object.__setattr__(self, "focal", focal)

    def __len__(self) -> int:
        return len(self.poses)

    def __repr__(self) -> str:
        return f"LabelTable({len(self)} rows, scenes={self.scene_names}, source={self.source!r})"

    @property
    def scene_names(self) -> list[str]:
        """Sorted unique scene names."""
        return sorted(set(self.scene))

    def scene_ids(self, scene_names: Sequence[str] | None = None) -> np.ndarray:
        """Index ``[N]`` (int64) of each row's scene in ``scene_names`` (default: sorted names)."""
        names = self.scene_names if scene_names is None else list(scene_names)
        index = {name: i for i, name in enumerate(names)}
        unknown = sorted(set(self.scene) - index.keys())
        if unknown:
            raise ValueError(f"scenes {unknown} are not among the given scene names {names}")
        return np.fromiter((index[s] for s in self.scene), dtype=np.int64, count=len(self))

    def file_line(self, i: int) -> int:
        """1-based line number of row ``i`` in ``source`` (header = line 1)."""
        return int(self.lines[i])

    def select(self, indices: np.ndarray | Sequence[int]) -> LabelTable:
        """Rows at ``indices`` (integer indices or a boolean mask ``[N]``), in that order."""
        idx = np.asarray(indices)
        idx = np.flatnonzero(idx) if idx.dtype == bool else idx.astype(np.int64).reshape(-1)
        return LabelTable(
            scene=[self.scene[i] for i in idx],
            split=[self.split[i] for i in idx],
            seq=[self.seq[i] for i in idx],
            img_path=[self.img_path[i] for i in idx],
            poses=self.poses[idx],
            source=self.source,
            lines=self.lines[idx],
            focal=None if self.focal is None else self.focal[idx],
        )

    @classmethod
    def concat(cls, tables: Iterable[LabelTable]) -> LabelTable:
        """Rows of all ``tables`` in order; ``source`` is kept only if they all share it."""
        tables = list(tables)
        sources = {t.source for t in tables}
        source = sources.pop() if len(sources) == 1 else ""
        lines = np.concatenate([t.lines for t in tables]) if tables and source else None
        with_focal = bool(tables) and all(t.focal is not None for t in tables)
        if not with_focal and any(t.focal is not None for t in tables):
            raise ValueError("LabelTable.concat: some tables have a focal column and some not")
        return cls(
            scene=[s for t in tables for s in t.scene],
            split=[s for t in tables for s in t.split],
            seq=[s for t in tables for s in t.seq],
            img_path=[s for t in tables for s in t.img_path],
            poses=np.concatenate([t.poses for t in tables]) if tables else np.zeros((0, 7)),
            source=source,
            lines=lines,
            focal=np.concatenate([t.focal for t in tables]) if with_focal else None,
        )


def read_labels(path: str | os.PathLike[str]) -> LabelTable:
    """Read a label file; raise :class:`LabelError` at the first bad row.

    Every returned quaternion is unit norm with ``qw >= 0``. Quaternions whose norm differs
    from 1 by more than ``NON_UNIT_TOLERANCE`` are normalised and counted in one
    :class:`LabelWarning` per file.
    """
    table, errors = read_labels_lenient(path)
    if errors:
        raise errors[0]
    return table


def read_labels_lenient(path: str | os.PathLike[str]) -> tuple[LabelTable, list[LabelError]]:
    """Read a label file, skipping bad rows: the table of good rows and one error per bad row.

    Problems with the file as a whole (missing, empty, no data rows, missing column) raise
    :class:`LabelError`.
    """
    path_text = str(path)
    if not os.path.exists(path):
        raise LabelError(path_text, None, "file not found")
    if os.path.isdir(path):
        raise LabelError(path_text, None, "is a directory, not a label file")
    with open(path, newline="", encoding="utf-8-sig") as handle:
        try:
            reader = csv.reader(handle)
            header = next(reader, None)
            if header is None:
                raise LabelError(
                    path_text, None, f"empty file (expected the header {','.join(LABEL_COLUMNS)})"
                )
            names = [name.strip() for name in header]
            missing = [c for c in LABEL_COLUMNS if c not in names]
            if missing:
                raise LabelError(
                    path_text,
                    1,
                    f"missing column{'s' if len(missing) > 1 else ''} {', '.join(missing)} "
                    f"(header: {','.join(names)})",
                )
            text_at = [names.index(c) for c in TEXT_COLUMNS]
            pose_at = [names.index(c) for c in POSE_COLUMNS]
            if FOCAL_COLUMN in names:
                pose_at.append(names.index(FOCAL_COLUMN))
            orientation_at = (
                names.index(ORIENTATION_COLUMN) if ORIENTATION_COLUMN in names else None
            )
            inverse: list[bool] = []
            texts: list[list[str]] = []
            values: list[list[float]] = []
            lines: list[int] = []
            errors: list[LabelError] = []
            for row in reader:
                line = reader.line_num
                if not row or (len(row) == 1 and not row[0].strip()):
                    continue
                try:
                    text, pose = _parse_row(row, len(names), text_at, pose_at)
                    convention = CAMERA_TO_WORLD if orientation_at is None else row[orientation_at]
                    if convention.strip() not in (CAMERA_TO_WORLD, WORLD_TO_CAMERA):
                        raise ValueError(
                            f"column {ORIENTATION_COLUMN} must be {CAMERA_TO_WORLD} or "
                            f"{WORLD_TO_CAMERA}: {convention!r}"
                        )
                except ValueError as error:
                    errors.append(LabelError(path_text, line, str(error)))
                    continue
                inverse.append(convention.strip() == WORLD_TO_CAMERA)
                texts.append(text)
                values.append(pose)
                lines.append(line)
        except (csv.Error, UnicodeDecodeError) as error:
            raise LabelError(
                path_text, reader.line_num or None, f"not a CSV file: {error}"
            ) from None
    if not texts and not errors:
        raise LabelError(path_text, 1, "no data rows after the header")

    numbers = np.asarray(values, dtype=np.float64).reshape(len(values), len(pose_at))
    poses, focal = numbers[:, :7].copy().reshape(-1, 7), None
    if FOCAL_COLUMN in names:
        focal = numbers[:, 7] if len(values) else np.zeros(0)
    flip = np.asarray(inverse, dtype=bool)
    poses[flip, 3:] = conjugate(poses[flip, 3:])
    poses[:, 3:], non_unit = _unit_canonical_quaternions(poses[:, 3:])
    if ORIENTATION_COLUMN not in names and len(poses) >= 2:
        flipped, plain, conjugated = looks_world_to_camera(poses[:, 3:])
        if flipped:
            warnings.warn(
                f"{path_text}: its orientations look world-to-camera (camera y axes spread "
                f"{plain:.1f} deg, conjugated {conjugated:.1f} deg) and it has no "
                f"{ORIENTATION_COLUMN} column; pae reads camera-to-world: pae-data convert "
                f"authors-csv {path_text} OUT_DIR",
                OrientationWarning,
                stacklevel=3,
            )
    if non_unit:
        warnings.warn(
            f"{non_unit} quaternions in {path_text} were not unit norm and were normalised",
            LabelWarning,
            stacklevel=3,
        )
    _warn_repeated_images([text[3] for text in texts], lines, path_text)
    columns = list(zip(*texts, strict=True)) if texts else [(), (), (), ()]
    table = LabelTable(
        scene=list(columns[0]),
        split=list(columns[1]),
        seq=list(columns[2]),
        img_path=list(columns[3]),
        poses=poses,
        source=path_text,
        lines=np.asarray(lines, dtype=np.int64),
        focal=focal,
    )
    return table, errors


def _warn_repeated_images(img_paths: Sequence[str], lines: Sequence[int], source: str) -> None:
    """One LabelWarning naming the rows whose img_path an earlier row already has (an epoch
    would see those images more than once), with the line numbers of both."""
    first_line: dict[str, int] = {}
    repeats = []
    for img_path, line in zip(img_paths, lines, strict=True):
        if img_path in first_line:
            repeats.append(f"line {line} repeats line {first_line[img_path]}")
        else:
            first_line[img_path] = line
    if repeats:
        more = f" and {len(repeats) - 5} more" if len(repeats) > 5 else ""
        warnings.warn(
            f"{source}: {len(repeats)} rows repeat an earlier row's image "
            f"({', '.join(repeats[:5])}{more}): an epoch sees those images more than once",
            RepeatedImageWarning,
            stacklevel=4,
        )


def _parse_row(
    row: list[str], n_fields: int, text_at: list[int], pose_at: list[int]
) -> tuple[list[str], list[float]]:
    """Text fields and the 7 pose values of one row (then its focal length, when
    ``pose_at`` has the focal column's index); ``ValueError`` naming the bad column."""
    if len(row) != n_fields:
        raise ValueError(f"expected {n_fields} fields, got {len(row)}")
    text = [row[i].strip() for i in text_at]
    for name, value in zip(TEXT_COLUMNS, text, strict=True):
        if name in REQUIRED_TEXT_COLUMNS and not value:
            raise ValueError(f"column {name} is empty")
    pose = []
    columns = (*POSE_COLUMNS, FOCAL_COLUMN)[: len(pose_at)]
    for name, i in zip(columns, pose_at, strict=True):
        raw = row[i].strip()
        try:
            value = float(raw)
        except ValueError:
            raise ValueError(f"column {name} is not a number: {raw!r}") from None
        if not np.isfinite(value):
            raise ValueError(f"column {name} is not finite: {raw!r}")
        pose.append(value)
    if np.linalg.norm(pose[3:7]) < ZERO_QUATERNION_NORM:
        raise ValueError(f"quaternion (q1..q4) has zero norm: {pose[3:7]}")
    if len(pose) > 7 and pose[7] <= 0:
        raise ValueError(f"column {FOCAL_COLUMN} must be a focal length > 0 px: {pose[7]!r}")
    return text, pose


def _unit_canonical_quaternions(q: np.ndarray) -> tuple[np.ndarray, int]:
    """Quaternions ``[N, 4]`` normalised and sign-flipped to ``qw >= 0``; count of non-unit ones.

    Norms within ``_RENORMALISE_TOLERANCE`` of 1 are kept as they are, so normalising is
    idempotent and written files read back bit for bit.
    """
    norms = np.linalg.norm(q, axis=1, keepdims=True)
    off = np.abs(norms - 1.0)
    q = np.where(off > _RENORMALISE_TOLERANCE, q / norms, q)
    return canonical_sign(q), int(np.count_nonzero(off > NON_UNIT_TOLERANCE))


def write_labels(path: str | os.PathLike[str], table: LabelTable) -> None:
    """Write ``table`` to ``path`` atomically, creating parent folders.

    Numbers are written with Python's shortest round-trip representation, so reading the file
    gives back exactly ``table.poses``. Values are written as they are (no normalisation);
    every row records its convention (``orientation``: camera_to_world).
    """
    with atomic_write(path, newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle, lineterminator="\n")
        focal = None if table.focal is None else table.focal.tolist()
        focal_column = [FOCAL_COLUMN] if focal is not None else []
        writer.writerow([*LABEL_COLUMNS, *focal_column, ORIENTATION_COLUMN])
        poses = table.poses.tolist()
        for i in range(len(table)):
            writer.writerow(
                [
                    table.scene[i],
                    table.split[i],
                    table.seq[i],
                    table.img_path[i],
                    *(repr(v + 0.0) for v in poses[i]),
                    *([repr(focal[i] + 0.0)] if focal is not None else []),
                    CAMERA_TO_WORLD,
                ]
            )


def focal_problems(table: LabelTable, width: int) -> dict[int, str]:
    """Why each row's focal length (px) is implausible, by row index: outside
    ``FOCAL_WIDTH_RANGE`` times ``width``, the width (px) of the images it refers to. Empty
    for a table without a focal column."""
    if table.focal is None:
        return {}
    low, high = (factor * width for factor in FOCAL_WIDTH_RANGE)
    return {
        int(i): (
            f"focal length {table.focal[i]:g} px is implausible for images {width} px wide "
            f"(expected {low:g} to {high:g} px: {FOCAL_WIDTH_RANGE[0]:g} to "
            f"{FOCAL_WIDTH_RANGE[1]:g} times the width)"
        )
        for i in np.flatnonzero((table.focal < low) | (table.focal > high))
    }


def focal_column_mismatch(tables: Iterable[LabelTable]) -> LabelError | None:
    """The error when some label files (one per split) have a focal column and others do
    not: a split without one would use the nominal focal length. None when they agree."""
    tables = list(tables)
    with_focal = [t for t in tables if t.focal is not None]
    without = [t for t in tables if t.focal is None]
    if not with_focal or not without:
        return None
    return LabelError(
        without[0].source,
        None,
        f"no {FOCAL_COLUMN} column, unlike {with_focal[0].source}: the label files of all "
        "splits give per-image focal lengths, or none does",
    )
