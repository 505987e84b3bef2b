"""Pinhole camera intrinsics, kept consistent through every resize and crop of the images,
and the rays through their pixels.

Convention (OpenCV's, and the synthetic benchmark's): the centre of pixel ``(u, v)`` (column,
row) lies at integer coordinates ``(u, v)``; the camera frame has ``x`` right, ``y`` down and
looks along ``+z``. Resizing by ``s`` maps ``u -> (u + 0.5)·s - 0.5`` (what OpenCV's resize
and ``F.interpolate`` do), so ``fx -> fx·s`` and ``cx -> (cx + 0.5)·s - 0.5``; cropping at
``(left, top)`` moves the principal point by ``-(left, top)``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TypeVar

import numpy as np
import torch
from torch import Tensor

from pae.core.geometry import quaternion_to_matrix

Scalar = TypeVar("Scalar", float, Tensor)
"""A focal length or principal-point coordinate (px): one float, or a tensor of them."""


def resized_size(width: int, height: int, shorter_edge: int) -> tuple[int, int]:
    """(width, height) in px after scaling the shorter edge to ``shorter_edge`` px (the
    loaders' rounding)."""
    scale = shorter_edge / min(width, height)
    if scale == 1.0:
        return width, height
    return max(shorter_edge, round(width * scale)), max(shorter_edge, round(height * scale))


def centre_crop_origin(width: int, height: int, crop: int) -> tuple[int, int]:
    """(left, top) in px of the centre ``crop × crop`` window (the evaluation crop)."""
    return (width - crop) // 2, (height - crop) // 2


def _resized_axis(focal: Scalar, centre: Scalar, scale: float) -> tuple[Scalar, Scalar]:
    """Focal length and principal point (px) along one image axis resized by ``scale``."""
    return focal * scale, (centre + 0.5) * scale - 0.5


@dataclass(frozen=True)
class Intrinsics:
    """Focal lengths ``fx, fy`` and principal point ``cx, cy`` in px of ``width × height``
    images (``fx``, ``fy`` may be per image: then ``focal`` rows override them)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def resized(self, width: int, height: int) -> Intrinsics:
        """The same camera for images resized to ``width × height`` px."""
        fx, cx = _resized_axis(self.fx, self.cx, width / self.width)
        fy, cy = _resized_axis(self.fy, self.cy, height / self.height)
        return Intrinsics(fx, fy, cx, cy, width, height)

    def cropped(self, left: int, top: int, width: int, height: int) -> Intrinsics:
        """The same camera for the ``width × height`` window at ``(left, top)``."""
        return replace(self, cx=self.cx - left, cy=self.cy - top, width=width, height=height)

    def preprocessed(self, shorter_edge: int, crop: int) -> Intrinsics:
        """After the loaders' resize (shorter edge -> ``shorter_edge``) and the evaluation
        centre crop (``crop × crop``)."""
        width, height = resized_size(self.width, self.height, shorter_edge)
        resized = self.resized(width, height)
        left, top = centre_crop_origin(width, height, crop)
        return resized.cropped(left, top, crop, crop)

    def with_focal(self, focal_px: float) -> Intrinsics:
        """The same camera with ``fx = fy = focal_px``."""
        return replace(self, fx=float(focal_px), fy=float(focal_px))

    def vector(self) -> list[float]:
        """``[fx, fy, cx, cy]``."""
        return [self.fx, self.fy, self.cx, self.cy]

    def matrix(self) -> np.ndarray:
        """Calibration matrix ``K`` ``[3, 3]`` float64."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])


def scale_intrinsics(vectors: Tensor, scale_x: float, scale_y: float) -> Tensor:
    """Intrinsics ``[..., 4]`` (fx, fy, cx, cy) for images resized by ``scale_x, scale_y``."""
    fx, fy, cx, cy = vectors.unbind(-1)
    fx, cx = _resized_axis(fx, cx, scale_x)
    fy, cy = _resized_axis(fy, cy, scale_y)
    return torch.stack([fx, fy, cx, cy], -1)


def project(points_camera: Tensor, intrinsics: Tensor) -> Tensor:
    """Pixel coordinates ``[..., 2]`` (u, v) of camera-frame points ``[..., 3]``;
    ``intrinsics`` ``[..., 4]`` broadcasts against the points' leading dimensions."""
    fx, fy, cx, cy = intrinsics.unbind(-1)
    z = points_camera[..., 2].clamp_min(1e-6)
    u = fx * points_camera[..., 0] / z + cx
    v = fy * points_camera[..., 1] / z + cy
    return torch.stack([u, v], -1)


def directions_through(u: Tensor, v: Tensor, intrinsics: Tensor) -> Tensor:
    """Camera-frame ray directions ``[..., 3]`` (``z = 1``) through the pixel coordinates
    ``u, v`` ``[...]`` (px; column, row) of cameras with intrinsics ``[..., 4]`` (fx, fy, cx,
    cy), all broadcast against each other."""
    fx, fy, cx, cy = intrinsics.unbind(-1)
    x, y = torch.broadcast_tensors((u - cx) / fx, (v - cy) / fy)
    return torch.stack([x, y, torch.ones_like(x)], -1)


def pixel_directions(intrinsics: Tensor, width: int, height: int) -> Tensor:
    """Camera-frame ray directions ``[B, height, width, 3]`` (``z = 1``) through the pixel
    centres of ``B`` cameras with intrinsics ``[B, 4]``."""
    u = torch.arange(width, dtype=intrinsics.dtype, device=intrinsics.device)[None, None, :]
    v = torch.arange(height, dtype=intrinsics.dtype, device=intrinsics.device)[None, :, None]
    return directions_through(u, v, intrinsics[:, None, None])


def camera_rays(
    poses: Tensor, intrinsics: Tensor, width: int, height: int
) -> tuple[Tensor, Tensor]:
    """World-frame rays of every pixel of ``B`` cameras: origins [B, H·W, 3] and directions
    [B, H·W, 3] whose camera-frame ``z`` is 1 (a distance ``t`` along them is a depth).

    poses [B, 7] camera-to-world; intrinsics [B, 4] (fx, fy, cx, cy) of ``width × height``
    images.
    """
    local = pixel_directions(intrinsics, width, height).flatten(1, 2)  # [B, HW, 3]
    rotation = quaternion_to_matrix(poses[:, 3:])
    directions = torch.einsum("bij,bnj->bni", rotation, local)
    origins = poses[:, None, :3].expand_as(directions)
    return origins, directions
