"""Readers for the raw layouts of Cambridge Landmarks and 7-Scenes, and their conversion to label
files.

Cambridge Landmarks (one folder per scene)::

    KingsCollege/dataset_train.txt      3 header lines, then
                                        seq1/frame00001.png X Y Z W P Q R   (W: scalar part)
    KingsCollege/dataset_test.txt
    KingsCollege/seq1/frame00001.png

7-Scenes (one folder per scene)::

    chess/TrainSplit.txt                sequence1, sequence2, ... (one per line)
    chess/TestSplit.txt
    chess/seq-01/frame-000000.color.png
    chess/seq-01/frame-000000.pose.txt  4×4 camera-to-world matrix (metres)

:func:`convert_raw` writes ``<scene>_{train,test}.csv`` and ``all_{train,test}.csv`` whose
``img_path`` is ``<scene>/<frame path>``, i.e. relative to the raw root: point ``data.root`` at
the raw root when training on the converted files.
"""

from __future__ import annotations

import os
import re
from collections.abc import Callable
from pathlib import Path
from typing import Literal

import numpy as np

from pae.core.errors import LabelError
from pae.core.quaternion_sign import canonical_sign
from pae.data.labels import ZERO_QUATERNION_NORM, LabelTable, write_labels
from pae.data.orientation import conjugate

__all__ = [
    "CAMBRIDGE_SPLIT_FILES",
    "SEVEN_SCENES_SPLIT_FILES",
    "convert_raw",
    "read_cambridge_scene",
    "read_seven_scenes_scene",
]

SPLITS = ("train", "test")
CAMBRIDGE_SPLIT_FILES = {"train": "dataset_train.txt", "test": "dataset_test.txt"}
SEVEN_SCENES_SPLIT_FILES = {"train": "TrainSplit.txt", "test": "TestSplit.txt"}
CAMBRIDGE_HEADER_LINES = 3
_SEQUENCE_NAME = re.compile(r"sequence\s*(\d+)", re.IGNORECASE)
RIGID_TOLERANCE = 0.01
"""How far a camera-to-world matrix may be from rigid: the largest entry of R^T R - I (R its
3×3 rotation part) and of its last row minus 0 0 0 1; printed digits, never a scale or shear."""


def rigid_problem(matrix: np.ndarray) -> str | None:
    """Why a 4×4 camera-to-world matrix is not a rigid transform (rotation part orthonormal
    with determinant +1, last row 0 0 0 1, within ``RIGID_TOLERANCE``), or None if it is."""
    last = matrix[3]
    if np.abs(last - np.array([0.0, 0.0, 0.0, 1.0])).max() > RIGID_TOLERANCE:
        shown = " ".join(f"{value:g}" for value in last)
        return f"not a rigid transform: its last row is {shown}, not 0 0 0 1"
    rotation = matrix[:3, :3]
    deviation = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    if deviation > RIGID_TOLERANCE:
        return (
            "not a rigid transform: its rotation part is not orthonormal (R^T R is off the "
            f"identity by up to {deviation:.3g}: a scale or shear)"
        )
    determinant = float(np.linalg.det(rotation))
    if determinant < 0:
        return f"not a rigid transform: its rotation part has determinant {determinant:.3g}"
    return None


def _split_file(scene_dir: Path, split: str, files: dict[str, str]) -> Path:
    """The file under ``scene_dir`` that lists the frames of ``split`` (named by ``files``)."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    return scene_dir / files[split]


def _read_lines(path: Path) -> list[str]:
    """Lines of a text file; :class:`LabelError` if it is missing."""
    if not path.is_file():
        raise LabelError(path, None, "file not found")
    return path.read_text(encoding="utf-8", errors="replace").splitlines()


def parse_numbers(tokens: list[str], path: Path, line: int) -> list[float]:
    """Finite floats of ``tokens``; :class:`LabelError` naming ``path:line`` otherwise."""
    numbers = []
    for token in tokens:
        try:
            value = float(token)
        except ValueError:
            raise LabelError(path, line, f"not a number: {token!r}") from None
        if not np.isfinite(value):
            raise LabelError(path, line, f"not a finite number: {token!r}")
        numbers.append(value)
    return numbers


def _scene_table(
    scene: str,
    split: str,
    seqs: list[str],
    img_paths: list[str],
    poses: np.ndarray,
    source: Path,
    lines: list[int] | None = None,
) -> LabelTable:
    """The rows read from one scene's split file (``lines``: their line numbers in it)."""
    return LabelTable(
        scene=[scene] * len(poses),
        split=[split] * len(poses),
        seq=seqs,
        img_path=img_paths,
        poses=poses,
        source=str(source),
        lines=None if lines is None else np.asarray(lines),
    )


def read_cambridge_scene(scene_dir: str | os.PathLike[str], split: str) -> LabelTable:
    """Rows of ``<scene_dir>/dataset_<split>.txt`` as camera-to-world poses.

    The file's positions are the camera centres in the world and are kept as they are; its
    quaternions are world-to-camera rotations (from the dataset's VisualSFM reconstruction),
    so each is conjugated into the camera-to-world rotation pae's label files hold
    (``pae.data.orientation``), and its sign flipped where the result has ``W < 0``;
    quaternions are not normalised (reading the written label file normalises them).
    """
    scene_dir = Path(scene_dir)
    scene = scene_dir.name
    path = _split_file(scene_dir, split, CAMBRIDGE_SPLIT_FILES)
    seqs: list[str] = []
    img_paths: list[str] = []
    poses: list[list[float]] = []
    lines: list[int] = []
    first_line: dict[str, int] = {}
    for line, text in enumerate(_read_lines(path), start=1):
        tokens = text.split()
        if line <= CAMBRIDGE_HEADER_LINES or not tokens:
            continue
        if len(tokens) != 8:
            raise LabelError(
                path, line, f"expected 'IMAGE X Y Z W P Q R' (8 fields), got {len(tokens)} fields"
            )
        frame = Path(tokens[0]).as_posix()
        if Path(frame).is_absolute() or ".." in Path(frame).parts:
            raise LabelError(path, line, f"image path must be relative to the scene: {frame!r}")
        pose = parse_numbers(tokens[1:], path, line)
        if np.linalg.norm(pose[3:]) < ZERO_QUATERNION_NORM:
            raise LabelError(path, line, "quaternion (W P Q R) has zero norm")
        if frame in first_line:
            raise LabelError(path, line, f"image {frame} repeats line {first_line[frame]}")
        first_line[frame] = line
        seqs.append(Path(frame).parts[0] if len(Path(frame).parts) > 1 else "")
        img_paths.append(f"{scene}/{frame}")
        poses.append(pose)
        lines.append(line)
    if not poses:
        raise LabelError(path, None, "no frames listed")
    pose_array = np.asarray(poses, dtype=np.float64)
    pose_array[:, 3:] = canonical_sign(conjugate(pose_array[:, 3:]))
    return _scene_table(scene, split, seqs, img_paths, pose_array, path, lines)


def _read_pose_matrix(path: Path) -> np.ndarray:
    """The 4×4 matrix of a 7-Scenes ``frame-*.pose.txt`` file."""
    rows = [(line, text.split()) for line, text in enumerate(_read_lines(path), start=1)]
    rows = [(line, tokens) for line, tokens in rows if tokens]
    if len(rows) != 4:
        raise LabelError(path, None, f"expected a 4×4 matrix (4 rows), got {len(rows)} rows")
    matrix = []
    for line, tokens in rows:
        if len(tokens) != 4:
            raise LabelError(path, line, f"expected 4 numbers, got {len(tokens)}")
        matrix.append(parse_numbers(tokens, path, line))
    problem = rigid_problem(np.asarray(matrix, dtype=np.float64))
    if problem is not None:
        raise LabelError(path, None, problem)
    return np.asarray(matrix, dtype=np.float64)


def read_seven_scenes_scene(scene_dir: str | os.PathLike[str], split: str) -> LabelTable:
    """Rows of the sequences listed in ``<scene_dir>/{Train,Test}Split.txt``.

    Frames are the ``frame-*.pose.txt`` files of each sequence folder, in name order; the
    position is the last column of the matrix and the quaternion that of its rotation part
    (float64, canonicalised to ``qw >= 0``).
    """
    import torch

    from pae.core.geometry import matrix_to_quaternion

    scene_dir = Path(scene_dir)
    scene = scene_dir.name
    split_path = _split_file(scene_dir, split, SEVEN_SCENES_SPLIT_FILES)
    seqs: list[str] = []
    img_paths: list[str] = []
    matrices: list[np.ndarray] = []
    listed: dict[str, int] = {}
    for line, text in enumerate(_read_lines(split_path), start=1):
        name = text.strip()
        if not name:
            continue
        match = _SEQUENCE_NAME.fullmatch(name)
        if match is None:
            raise LabelError(split_path, line, f"expected 'sequenceN', got {name!r}")
        seq = f"seq-{int(match.group(1)):02d}"
        if seq in listed:
            raise LabelError(split_path, line, f"{name} repeats line {listed[seq]}")
        listed[seq] = line
        seq_dir = scene_dir / seq
        if not seq_dir.is_dir():
            raise LabelError(split_path, line, f"sequence folder not found: {seq_dir}")
        frames = sorted(seq_dir.glob("frame-*.pose.txt"))
        if not frames:
            raise LabelError(split_path, line, f"no frame-*.pose.txt files in {seq_dir}")
        for pose_file in frames:
            stem = pose_file.name.removesuffix(".pose.txt")
            seqs.append(seq)
            img_paths.append(f"{scene}/{seq}/{stem}.color.png")
            matrices.append(_read_pose_matrix(pose_file))
    if not matrices:
        raise LabelError(split_path, None, "no sequences listed")
    stacked = np.stack(matrices)
    quaternions = matrix_to_quaternion(torch.from_numpy(stacked[:, :3, :3])).numpy()
    poses = np.concatenate([stacked[:, :3, 3], quaternions], axis=1)
    return _scene_table(scene, split, seqs, img_paths, poses, split_path)


_READERS: dict[str, tuple[Callable[[Path, str], LabelTable], dict[str, str]]] = {
    "cambridge": (read_cambridge_scene, CAMBRIDGE_SPLIT_FILES),
    "7scenes": (read_seven_scenes_scene, SEVEN_SCENES_SPLIT_FILES),
}


def convert_raw(
    dataset: Literal["cambridge", "7scenes"],
    raw_root: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
) -> dict[str, int]:
    """Convert every scene folder directly under ``raw_root`` into label files in ``out_dir``.

    A scene folder is one holding a split file (``dataset_train.txt`` / ``TrainSplit.txt``,
    or the test one); both splits must be present. Everything is read before anything is
    written. Returns the number of rows per written file name, e.g. ``{"chess_train.csv": 4000,
    ..., "all_test.csv": 17000}``. Image paths are relative to ``raw_root``.
    """
    if dataset not in _READERS:
        raise ValueError(f"dataset must be one of {sorted(_READERS)}, got {dataset!r}")
    read_scene, split_files = _READERS[dataset]
    raw_root = Path(raw_root)
    if not raw_root.is_dir():
        raise ValueError(f"{raw_root}: raw dataset root is not a directory")
    scene_dirs = sorted(
        child
        for child in raw_root.iterdir()
        if child.is_dir() and any((child / name).is_file() for name in split_files.values())
    )
    if not scene_dirs:
        raise ValueError(
            f"{raw_root}: no {dataset} scene folders found "
            f"(sub-folders holding {' / '.join(split_files.values())})"
        )
    tables = {
        (scene_dir.name, split): read_scene(scene_dir, split)
        for scene_dir in scene_dirs
        for split in SPLITS
    }
    out_dir = Path(out_dir)
    written: dict[str, int] = {}
    for (scene, split), table in tables.items():
        write_labels(out_dir / f"{scene}_{split}.csv", table)
        written[f"{scene}_{split}.csv"] = len(table)
    for split in SPLITS:
        combined = LabelTable.concat(t for (_, s), t in tables.items() if s == split)
        write_labels(out_dir / f"all_{split}.csv", combined)
        written[f"all_{split}.csv"] = len(combined)
    return written


def raw_download(root: Path) -> tuple[str, str] | None:
    """The dataset whose raw layout ``root`` holds (a scene folder with its train split
    file, ``pae.data.raw``), if any: (its name, its ``pae-data convert`` argument)."""
    for name, argument, split_files in (
        ("7-Scenes", "7scenes", SEVEN_SCENES_SPLIT_FILES),
        ("Cambridge Landmarks", "cambridge", CAMBRIDGE_SPLIT_FILES),
    ):
        if next(root.glob(f"*/{split_files['train']}"), None) is not None:
            return name, argument
    return None
