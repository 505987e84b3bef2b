"""One scene's label files from another tool's layout (a COLMAP model, the ACE / DSAC* folders,
kapture folders): its frames, the one camera every row shares, and what the poses say about
scale and up.

The converters (:mod:`pae.data.colmap`, :mod:`pae.data.ace`, :mod:`pae.data.kapture`) read
their files into :class:`SceneFrames`; :func:`write_scene` writes ``<scene>_{train,test}.csv``
and ``all_{train,test}.csv`` with a ``focal`` column (each image's own focal length), and
:func:`camera_of` gives the ``data.camera`` those rows refer to: label files hold one focal
length per row and one principal point for the whole dataset.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np

from pae.core.camera import Intrinsics
from pae.data.labels import LabelTable, write_labels
from pae.data.orientation import camera_y_axes

__all__ = [
    "FOCAL_RATIO_TOLERANCE",
    "PRINCIPAL_POINT_TOLERANCE_PX",
    "SceneFrames",
    "camera_of",
    "camera_override",
    "scene_shape",
    "sequence_of",
    "unequal_focal_lengths",
    "write_scene",
]

SPLITS = ("train", "test")
FOCAL_RATIO_TOLERANCE = 1e-3
"""Largest relative difference of ``fx`` and ``fy`` written as one focal length (their mean)."""
PRINCIPAL_POINT_TOLERANCE_PX = 1.0
"""Largest distance (px) of an image's principal point from the scene's (the median)."""
NAMED_SEQUENCE = re.compile(r"(.+?)[-_]frame[-_]?\d+", re.IGNORECASE)
"""A frame name holding its sequence before ``frame`` (``seq-01-frame-000000``,
Cambridge's ``seq1_frame00001``): group 1 is the sequence."""
CORNER_CENTRE_PX = 0.5
"""Where COLMAP and the ACE layout put the centre of the top-left pixel (``(0.5, 0.5)``: a
pixel's corner at integer coordinates); pae puts it at ``(0, 0)`` (:mod:`pae.core.camera`),
so their principal point minus this is pae's (an image's centre ``W/2`` -> ``(W - 1)/2``)."""


@dataclass(frozen=True)
class SceneFrames:
    """The frames of one scene as read from another tool's files.

    ``img_path`` [N] relative to the image root, ``seq`` [N] sequence names, ``split`` [N]
    ``train`` or ``test``; ``poses`` [N, 7] camera-to-world (``x, y, z`` in the source's
    units, ``qw, qx, qy, qz``); ``focal`` [N] px and ``principal`` [N, 2] (``cx, cy`` px) of
    ``width × height`` images; ``origin`` [N] the file (and entry) each frame came from.
    """

    img_path: list[str]
    seq: list[str]
    split: list[str]
    poses: np.ndarray
    focal: np.ndarray
    principal: np.ndarray
    width: int
    height: int
    origin: list[str]

    def __len__(self) -> int:
        return len(self.img_path)


def recording_of(img_path: str) -> str:
    """The recording an image came from, by its path alone: its folder, and the sequence its
    name holds before ``frame`` where it holds one (the ACE layout's flat folders:
    ``test/rgb/seq-01-frame-000000.color.png`` -> ``test/rgb/seq-01``; 7-Scenes'
    ``chess/seq-03/frame-000000.color.png`` -> ``chess/seq-03``)."""
    path = PurePosixPath(img_path.replace("\\", "/"))
    named = NAMED_SEQUENCE.fullmatch(path.name.split(".")[0])
    return str(path.parent / named.group(1)) if named else str(path.parent)


def sequence_of(relative: str) -> str:
    """The sequence of an image from its folder relative to the split's root: the folders
    joined by ``-`` (``seq-01/frame.png`` -> ``seq-01``; a file at the top -> ``""``)."""
    return "-".join(PurePosixPath(relative).parent.parts)


def unequal_focal_lengths(fx: np.ndarray, fy: np.ndarray) -> np.ndarray:
    """Indices of the cameras whose ``fx`` and ``fy`` [N] (px) differ by more than
    ``FOCAL_RATIO_TOLERANCE`` of their mean: a label file holds one focal length per row."""
    mean = (fx + fy) / 2
    return np.flatnonzero(np.abs(fx - fy) > FOCAL_RATIO_TOLERANCE * mean)


def principal_point_outliers(principal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The scene's principal point [2] (the median of ``principal`` [N, 2], px) and the
    indices of those farther than ``PRINCIPAL_POINT_TOLERANCE_PX`` from it."""
    reference = np.median(principal, axis=0)
    distance = np.linalg.norm(principal - reference, axis=1)
    return reference, np.flatnonzero(distance > PRINCIPAL_POINT_TOLERANCE_PX)


def camera_of(frames: SceneFrames) -> Intrinsics:
    """The ``data.camera`` of the frames: their median focal length (each row's own in the
    focal column) and principal point, at ``width × height``. ValueError naming the first
    frame whose principal point lies farther than ``PRINCIPAL_POINT_TOLERANCE_PX`` away."""
    reference, outliers = principal_point_outliers(frames.principal)
    if outliers.size:
        i = int(outliers[0])
        cx, cy = frames.principal[i]
        raise ValueError(
            f"{frames.origin[i]}: principal point ({cx:g}, {cy:g}) px is more than "
            f"{PRINCIPAL_POINT_TOLERANCE_PX:g} px from the scene's ({reference[0]:g}, "
            f"{reference[1]:g}): pae's label files give every image one principal point"
        )
    focal = float(np.median(frames.focal))
    return Intrinsics(focal, focal, *map(float, reference), frames.width, frames.height)


def camera_override(camera: Intrinsics) -> str:
    """The ``data.camera=...`` override of ``camera`` for ``pae-train``."""
    return (
        f"data.camera={{fx: {camera.fx:.10g}, fy: {camera.fy:.10g}, cx: {camera.cx:.10g}, "
        f"cy: {camera.cy:.10g}, width: {camera.width}, height: {camera.height}}}"
    )


def scene_shape(poses: np.ndarray) -> list[str]:
    """Lines on the scale and up direction of camera-to-world ``poses`` [N, 7]: the extent of
    the camera positions, and the world direction opposite the cameras' mean image-down axis
    (``y``) with their spread about it."""
    positions = poses[:, :3]
    extent = positions.max(0) - positions.min(0)
    radius = np.linalg.norm(positions - positions.mean(0), axis=1)
    down = camera_y_axes(poses[:, 3:]).mean(0)
    up = -down / max(float(np.linalg.norm(down)), 1e-12)
    spread = np.degrees(np.median(np.arccos(np.clip(-camera_y_axes(poses[:, 3:]) @ up, -1, 1))))
    axis = int(np.argmax(np.abs(up)))
    nearest = f"{'+' if up[axis] > 0 else '-'}{'xyz'[axis]}"
    return [
        f"cameras span {extent[0]:.3g} x {extent[1]:.3g} x {extent[2]:.3g} (x y z) and lie a "
        f"median {np.median(radius):.3g} from their centroid, in the units written",
        f"up (opposite the cameras' mean image-down axis): ({up[0]:.3f}, {up[1]:.3f}, "
        f"{up[2]:.3f}), nearest world axis {nearest}; the cameras' up axes spread a median "
        f"{spread:.1f} deg about it",
    ]


def write_scene(out_dir: str | os.PathLike[str], scene: str, frames: SceneFrames) -> dict[str, int]:
    """Write ``out_dir/<scene>_{train,test}.csv`` and ``out_dir/all_{train,test}.csv`` (the
    same rows) with each frame's focal length -> rows per written file name. ValueError when
    a split has no frames."""
    split = np.asarray(frames.split)
    tables = {}
    for name in SPLITS:
        rows = np.flatnonzero(split == name)
        if not rows.size:
            raise ValueError(f"no {name} images: every split needs some (see the split options)")
        tables[name] = LabelTable(
            scene=[scene] * len(rows),
            split=[name] * len(rows),
            seq=[frames.seq[i] for i in rows],
            img_path=[frames.img_path[i] for i in rows],
            poses=frames.poses[rows],
            focal=frames.focal[rows],
        )
    written = {}
    for prefix in (scene, "all"):
        for name, table in tables.items():
            write_labels(Path(out_dir) / f"{prefix}_{name}.csv", table)
            written[f"{prefix}_{name}.csv"] = len(table)
    return written
