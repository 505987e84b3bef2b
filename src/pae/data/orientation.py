"""Which way a label file's orientations point: camera-to-world (pae's convention) or
world-to-camera (Cambridge Landmarks' ``dataset_*.txt`` and the authors' label CSVs).

pae's camera frame is x right, y down, z forward (OpenCV's; 7-Scenes' and Cambridge's
VisualSFM cameras use the same axes), and its label files hold camera-to-world poses:
``X_world = R(q) @ X_camera + t``. Photographs are taken upright, so the cameras' y axes
(``R[:, 1]``) lie close to one direction in the world; read with the wrong convention they
spread widely. ``upright_spread_deg`` measures that spread, ``looks_world_to_camera`` compares
a file's orientations with their conjugates."""

from __future__ import annotations

import numpy as np

SPREAD_RATIO = 3.0
"""Orientations look world-to-camera when their cameras' y axes spread over more than this
many times the spread of the conjugated orientations' y axes ..."""
SPREAD_MIN_DEG = 15.0
"""... and over more than this many degrees (median)."""


def conjugate(quaternions: np.ndarray) -> np.ndarray:
    """Quaternions [N, 4] (qw, qx, qy, qz) -> their conjugates: the inverse rotations."""
    return quaternions * np.array([1.0, -1.0, -1.0, -1.0])


def camera_y_axes(quaternions: np.ndarray) -> np.ndarray:
    """Unit quaternions [N, 4] read as camera-to-world -> the cameras' y axes in the world
    [N, 3] (the second column of each rotation matrix)."""
    w, x, y, z = (quaternions / np.linalg.norm(quaternions, axis=1, keepdims=True)).T
    return np.stack([2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)], 1)


def upright_spread_deg(quaternions: np.ndarray) -> float:
    """The median angle (deg) between the cameras' y axes [N, 4] -> [N, 3] and their mean
    direction: small for photographs held upright, read in the right convention."""
    axes = camera_y_axes(quaternions)
    mean = axes.mean(0)
    mean /= max(float(np.linalg.norm(mean)), 1e-12)
    return float(np.degrees(np.median(np.arccos(np.clip(axes @ mean, -1.0, 1.0)))))


def looks_world_to_camera(quaternions: np.ndarray) -> tuple[bool, float, float]:
    """Whether orientations [N, 4] look world-to-camera, with the spreads (deg) of their
    cameras' y axes as given and conjugated."""
    plain = upright_spread_deg(quaternions)
    conjugated = upright_spread_deg(conjugate(quaternions))
    verdict = plain > SPREAD_MIN_DEG and plain > SPREAD_RATIO * conjugated
    return verdict, plain, conjugated
