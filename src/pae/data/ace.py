"""The ACE / DSAC* layout of one scene as frames (``pae-data convert ace ROOT OUT_DIR``)::

    ROOT/train/rgb/seq-01-frame-000000.color.png                  the image (png or jpg)
    ROOT/train/poses/seq-01-frame-000000.pose.txt                 4×4 camera-to-world, metres
    ROOT/train/calibration/seq-01-frame-000000.calibration.txt    focal length (px), or 3×3 K
    ROOT/test/rgb/ ...                                            the same for the test split

Other folders (``depth/``, ``eye/``, ``init/``) are not read. An image, its pose and its
calibration are one frame when their names agree once the suffixes are dropped (``.color.png``,
``.pose.txt``, ``.calibration.txt``; a plain ``.png`` / ``.jpg`` / ``.txt`` too); a file
without its two partners is an error naming it. ACE, like COLMAP, puts the centre of the
top-left pixel at ``(0.5, 0.5)`` (its pixel grid and its scaling ``c·s`` of the principal point
say so), pae at ``(0, 0)``: a calibration of one number has its principal point at the image
centre, ACE's ``(W/2, H/2)``, pae's ``((W - 1)/2, (H - 1)/2)``, and a 3×3 matrix's is moved
by ``-0.5`` px on both axes (``CORNER_CENTRE_PX``). The sequence of a frame is what
its name holds before ``frame`` (``seq-01-frame-000000`` -> ``seq-01``; Cambridge's
``seq1_frame00001`` -> ``seq1``).

ACE's set-up script writes 7-Scenes either with the dataset's own depth-SLAM (KinectFusion)
poses (moved to the colour camera by default) and a 525 px focal length (``7scenes_<scene>``)
or with the SfM pseudo ground truth and its per-frame focal lengths (``pgt_7scenes_<scene>``):
the labels hold whichever the converted folder holds.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from pae.core.errors import LabelError
from pae.data.converted import (
    CORNER_CENTRE_PX,
    NAMED_SEQUENCE,
    SceneFrames,
    unequal_focal_lengths,
)
from pae.data.holdout import natural_key
from pae.data.raw import parse_numbers, rigid_problem

__all__ = ["IMAGE_SUFFIXES", "read_ace_scene"]

SPLITS = ("train", "test")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def _frame_key(path: Path, inner: str) -> str:
    """The name a frame's files share: ``path``'s name without its suffix and ``inner``."""
    return path.stem.removesuffix(inner)


def _files(folder: Path, suffixes: tuple[str, ...], inner: str) -> dict[str, Path]:
    """The files of ``folder`` ending in ``suffixes`` by frame name; LabelError naming the
    folder if it is missing."""
    if not folder.is_dir():
        raise LabelError(
            folder, None, "folder not found (the ACE layout: rgb/, poses/, calibration/)"
        )
    found = (p for p in folder.iterdir() if p.suffix.lower() in suffixes and p.is_file())
    return {_frame_key(path, inner): path for path in found}


def _numbers(path: Path) -> np.ndarray:
    """The whitespace-separated numbers of a text file [K] float64; LabelError naming the
    file and line at a token that is not a finite number."""
    values: list[float] = []
    for line, text in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
        values += parse_numbers(text.split(), path, line)
    return np.asarray(values, dtype=np.float64)


def _pose(path: Path) -> np.ndarray:
    """The 4×4 camera-to-world matrix of a pose file; LabelError naming it if it is not rigid."""
    values = _numbers(path)
    if values.size != 16:
        raise LabelError(path, None, f"expected a 4×4 matrix (16 numbers), got {values.size}")
    matrix = values.reshape(4, 4)
    problem = rigid_problem(matrix)
    if problem is not None:
        raise LabelError(path, None, problem)
    return matrix


def _calibration(path: Path, width: int, height: int) -> tuple[float, float, float, float]:
    """``fx, fy, cx, cy`` (px; ``cx, cy`` in pae's pixel convention) of a calibration file:
    one focal length (principal point at the centre of ``width × height`` images) or a 3×3
    matrix in ACE's convention."""
    values = _numbers(path)
    if values.size == 1:
        fx = fy = float(values[0])
        cx, cy = width / 2 - CORNER_CENTRE_PX, height / 2 - CORNER_CENTRE_PX
    elif values.size == 9:
        fx, fy, cx, cy = (float(values[i]) for i in (0, 4, 2, 5))
        cx, cy = cx - CORNER_CENTRE_PX, cy - CORNER_CENTRE_PX
    else:
        raise LabelError(
            path, None, f"expected a focal length or a 3×3 matrix, got {values.size} numbers"
        )
    if fx <= 0 or fy <= 0:
        raise LabelError(path, None, f"focal length must be > 0 px, got {fx:g}, {fy:g}")
    return fx, fy, cx, cy


def _split_frames(root: Path, split: str) -> list[tuple[str, Path, Path, Path]]:
    """(name, image, pose file, calibration file) of each frame of ``root/split``, in name
    order; LabelError naming a file that lacks a partner."""
    folder = root / split
    images = _files(folder / "rgb", IMAGE_SUFFIXES, ".color")
    poses = _files(folder / "poses", (".txt",), ".pose")
    calibrations = _files(folder / "calibration", (".txt",), ".calibration")
    if not images:
        raise LabelError(folder / "rgb", None, f"no images ({', '.join(IMAGE_SUFFIXES)})")
    for mine, theirs, lacks in (
        (images, poses, "pose file in poses/"),
        (images, calibrations, "calibration file in calibration/"),
        (poses, images, "image in rgb/"),
        (calibrations, images, "image in rgb/"),
    ):
        missing = sorted(set(mine) - set(theirs), key=natural_key)
        if missing:
            raise LabelError(mine[missing[0]], None, f"no {lacks} for this frame")
    names = sorted(images, key=natural_key)
    return [(name, images[name], poses[name], calibrations[name]) for name in names]


def _one_image_size(images: list[Path]) -> tuple[int, int]:
    """(h, w) in px that ``images`` (one per split, the first in name order) share;
    LabelError naming the first of another size than the first image (the loaders check
    every other image against the label file's first)."""
    from pae.data.transforms import image_size

    height, width = image_size(str(images[0]))
    for image in images[1:]:
        h, w = image_size(str(image))
        if (h, w) != (height, width):
            raise LabelError(
                image,
                None,
                f"{w}x{h} px, but {images[0]} is {width}x{height} px: pae reads one image size "
                "per scene (resize the images, and their calibrations, to one size)",
            )
    return height, width


def read_ace_scene(root: str | os.PathLike[str]) -> SceneFrames:
    """The train and test frames of an ACE-layout scene folder, ``img_path`` relative to
    ``root`` (``train/rgb/...``), each with its own focal length. LabelError (one line naming
    the file) for a missing folder, a file without its partners, a pose that is not a rigid
    4×4 matrix or holds NaN, a calibration that is not one number or a 3×3 matrix,
    ``fx != fy``, and a split whose first image differs in size from the train split's."""
    from pae.core.geometry import matrix_to_quaternion

    root = Path(root)
    if not root.is_dir():
        raise ValueError(f"{root}: ROOT is not a directory")
    frames = {split: _split_frames(root, split) for split in SPLITS}
    height, width = _one_image_size([rows[0][1] for rows in frames.values()])
    img_path, seq, split_of, matrices, intrinsics, origin = [], [], [], [], [], []
    for split, rows in frames.items():
        for name, image, pose_file, calibration_file in rows:
            img_path.append(image.relative_to(root).as_posix())
            match = NAMED_SEQUENCE.fullmatch(name)
            seq.append(match.group(1) if match else "")
            split_of.append(split)
            matrices.append(_pose(pose_file))
            intrinsics.append(_calibration(calibration_file, width, height))
            origin.append(str(calibration_file))
    table = np.asarray(intrinsics, dtype=np.float64)
    unequal = unequal_focal_lengths(table[:, 0], table[:, 1])
    if unequal.size:
        fx, fy = table[unequal[0], :2]
        raise LabelError(
            origin[unequal[0]],
            None,
            f"fx {fx:g} != fy {fy:g} px: pae's label files hold one focal length per image",
        )
    import torch

    stacked = np.stack(matrices)
    quaternions = matrix_to_quaternion(torch.from_numpy(stacked[:, :3, :3])).numpy()
    return SceneFrames(
        img_path=img_path,
        seq=seq,
        split=split_of,
        poses=np.concatenate([stacked[:, :3, 3], quaternions], axis=1),
        focal=table[:, :2].mean(1),
        principal=table[:, 2:],
        width=width,
        height=height,
        origin=origin,
    )
