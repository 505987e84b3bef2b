"""The synthetic benchmark's pinhole camera and pose conventions (see ``pae.synthetic``):
camera-to-world poses, world-to-camera transforms, look-at rotations."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from pae.core.geometry import quaternion_to_matrix
from pae.synthetic.settings import SyntheticSettings

DEFAULT_SIZE = SyntheticSettings.size
"""Image width and height in pixels."""
DEFAULT_FOV_DEG = 65.0
"""Horizontal field of view in degrees."""
EPS_DIRECTION = 1e-9


@dataclass(frozen=True)
class PinholeCamera:
    """Square pinhole camera of ``size × size`` pixels with horizontal field of view ``fov_deg``."""

    size: int
    fov_deg: float = DEFAULT_FOV_DEG

    @property
    def focal_px(self) -> float:
        """Focal length ``fx = fy`` in pixels."""
        return (self.size / 2) / math.tan(math.radians(self.fov_deg) / 2)

    @property
    def principal_point(self) -> float:
        """``cx = cy`` in pixels (pixel centres at integer coordinates)."""
        return (self.size - 1) / 2

    def intrinsics(self) -> np.ndarray:
        """Calibration matrix ``K`` ``[3, 3]`` float64."""
        f, c = self.focal_px, self.principal_point
        return np.array([[f, 0.0, c], [0.0, f, c], [0.0, 0.0, 1.0]])

    def project(self, points_world: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """Pixel coordinates ``[N, 2]`` (u = column, v = row) of world points ``[N, 3]``.

        Points behind the camera get meaningless coordinates; check their depth with
        :func:`world_to_camera`.
        """
        points_camera = world_to_camera(points_world, pose)
        projected = points_camera @ self.intrinsics().T
        return projected[:, :2] / projected[:, 2:3]

    def ray_directions(self, supersample: int = 1) -> np.ndarray:
        """Camera-frame ray directions ``[S², H, W, 3]`` (``z = 1``) of ``S × S`` sub-pixel samples.

        Sample ``k = sy·S + sx`` of pixel ``(u, v)`` passes through
        ``(u + (sx + 0.5)/S − 0.5, v + (sy + 0.5)/S − 0.5)``.
        """
        offsets = (np.arange(supersample) + 0.5) / supersample - 0.5
        pixels = np.arange(self.size, dtype=np.float64)
        f, c = self.focal_px, self.principal_point
        directions = np.empty((supersample, supersample, self.size, self.size, 3))
        for sy, dy in enumerate(offsets):
            for sx, dx in enumerate(offsets):
                directions[sy, sx, :, :, 0] = ((pixels + dx - c) / f)[None, :]
                directions[sy, sx, :, :, 1] = ((pixels + dy - c) / f)[:, None]
                directions[sy, sx, :, :, 2] = 1.0
        return directions.reshape(supersample * supersample, self.size, self.size, 3)


def pose_rotation_translation(poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-to-world rotations ``[..., 3, 3]`` and positions ``[..., 3]`` of poses [..., 7]."""
    poses = np.asarray(poses, dtype=np.float64)
    rotations = quaternion_to_matrix(torch.from_numpy(poses[..., 3:])).numpy()
    return rotations, poses[..., :3]


def world_to_camera(points_world: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """World points ``[N, 3]`` in the camera frame of ``pose [7]``: ``[N, 3]``, z = depth (m)."""
    rotation, position = pose_rotation_translation(pose)
    return (np.asarray(points_world, dtype=np.float64) - position) @ rotation


def look_rotations(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """Camera-to-world rotations ``[N, 3, 3]`` from yaw about world ``z``, pitch and roll (rad).

    At zero angles the camera looks along world ``+x`` with its ``y`` (down) along world
    ``−z``; positive pitch looks up, roll turns about the optical axis.
    """
    level = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    cy, sy = np.cos(yaw), np.sin(yaw)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cr, sr = np.cos(roll), np.sin(roll)
    zero, one = np.zeros_like(yaw), np.ones_like(yaw)
    about_up = np.stack([cy, -sy, zero, sy, cy, zero, zero, zero, one], -1).reshape(-1, 3, 3)
    about_x = np.stack([one, zero, zero, zero, cp, -sp, zero, sp, cp], -1).reshape(-1, 3, 3)
    about_axis = np.stack([cr, -sr, zero, sr, cr, zero, zero, zero, one], -1).reshape(-1, 3, 3)
    return about_up @ level @ about_x @ about_axis
