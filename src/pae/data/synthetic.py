"""Embedded synthetic localisation benchmark: textured rooms seen by moving pinhole cameras.

Each scene is a room (an axis-aligned box seen from inside, a few metres wide like the
7-Scenes rooms) holding a few axis-aligned boxes and thin panels. Every face carries its own
procedural texture: large coloured gradients and shapes (so a 64 px view tells where the
camera is and where it looks) plus finer detail. Images are ray cast exactly in numpy,
with a point light and 2×2 supersampling, then pass through a per-sequence camera response
(gain, bias, tint, gamma, sensor noise). The pose can only be learnt from what the camera sees.

Conventions:

- World frame: metres, ``z`` up, floor at ``z = 0``, room centred on ``x = y = 0``.
- Poses ``[7]`` = ``x, y, z, qw, qx, qy, qz``, camera-to-world, ``qw >= 0``.
- Camera frame (OpenCV): ``x`` right, ``y`` down, looking along ``+z``.
- Pixels: the centre of pixel ``(u, v)`` (column, row) lies at integer coordinates ``(u, v)``;
  the principal point is the image centre ``((W - 1) / 2, (H - 1) / 2)`` and
  ``fx = fy = (W / 2) / tan(fov / 2)`` for the horizontal field of view ``fov``.
- Textures: texel ``(row i, column j)`` of a face covers face coordinates
  ``a ∈ [j·s, (j+1)·s)``, ``b ∈ [i·s, (i+1)·s)`` (texel size ``s`` metres); its centre is at
  ``((j + 0.5)·s, (i + 0.5)·s)``. Textures are sampled bilinearly between texel centres.

Layout written by :func:`write_synthetic_dataset` (label format of :mod:`pae.data.labels`)::

    OUT/labels/scene00_train.csv  OUT/labels/scene00_test.csv  ...  OUT/labels/all_{train,test}.csv
    OUT/scene00/seq-01/frame-000000.png  ...
"""

from __future__ import annotations

import colorsys
import dataclasses
import functools
import math
import shutil
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from pae.data.labels import LabelTable, write_labels
from pae.geometry import matrix_to_quaternion, quaternion_to_matrix

__all__ = [
    "DEFAULT_FOV_DEG",
    "DEFAULT_SCENES",
    "DEFAULT_SIZE",
    "DEFAULT_TEST_FRAMES",
    "DEFAULT_TEST_OFFSET_M",
    "DEFAULT_TRAIN_FRAMES",
    "Appearance",
    "Box",
    "CameraRoute",
    "CameraSequence",
    "FaceTexture",
    "PinholeCamera",
    "RenderProgress",
    "SyntheticScene",
    "SyntheticSummary",
    "furnish",
    "make_scene",
    "make_sequences",
    "measure_render_speed",
    "pose_rotation_translation",
    "render",
    "render_batch",
    "render_frames",
    "room_textures",
    "scene_name",
    "shade_rays",
    "world_to_camera",
    "write_label_files",
    "write_synthetic_dataset",
    "write_whole",
]

DEFAULT_SCENES = 2
DEFAULT_TRAIN_FRAMES = 1600
"""Training frames per scene."""
DEFAULT_TEST_FRAMES = 250
"""Test frames per scene."""
DEFAULT_SIZE = 64
"""Image width and height in pixels."""
DEFAULT_FOV_DEG = 65.0
"""Horizontal field of view in degrees."""
DEFAULT_TEST_OFFSET_M = 0.0
"""Lateral offset (m) of the test sequences from the route, alternately left and right."""
DEFAULT_TRAIN_LANE_M = 0.5
"""Lateral offset (m) of the train sequences from the route, alternately left and right.
With the defaults the test sequences walk between the train lanes, as test walks do between
train walks in Cambridge Landmarks: the median test camera lies 0.21 m from the nearest train
camera, about half the CPU teacher's error (the real datasets: 0.37-1.07 of MS-Transformer's)."""
DEFAULT_STRAY_M = 0.1
"""How far (m) a sequence's camera strays horizontally from its lane, at most."""
DEFAULT_YAW_STRAY_RAD = 0.15
"""How far (rad) a sequence's yaw strays from the route's heading, at most."""

TRAIN_SEQUENCES = 6
TEST_SEQUENCES = 2
TEXEL_SIZE_M = 0.02
SUPERSAMPLE = 2
"""Rays per pixel along each image axis (``SUPERSAMPLE²`` rays are averaged per pixel)."""
FRAMES_PER_WRITE = 64
"""Frames rendered before they are written, bounding memory for large images."""
RAYS_PER_CHUNK = 1 << 17
"""Rays cast at once: bounds memory (about 100 bytes per ray) and keeps arrays cache-friendly."""
_EPS_DIRECTION = 1e-9


# --------------------------------------------------------------------------------- camera


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


def _look_rotations(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
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


# --------------------------------------------------------------------------------- scenes


@dataclass(frozen=True, eq=False)
class FaceTexture:
    """Texture of one face: ``image`` ``[rows, cols, 3]`` float32 linear RGB in ``[0, 1]``.

    Row index grows with face coordinate ``b``, column index with ``a`` (see module doc).
    """

    image: np.ndarray
    texel_size: float = TEXEL_SIZE_M


@dataclass(frozen=True, eq=False)
class Box:
    """Axis-aligned box from corner ``lo`` ``[3]`` to ``hi`` ``[3]`` (m) with 6 face textures.

    Face ``f`` lies on axis ``f // 2`` at ``lo`` (``f`` even) or ``hi`` (``f`` odd). Its face
    coordinates ``(a, b)`` run from ``lo`` along the two other axes in increasing order
    (x-faces: ``(y, z)``, y-faces: ``(x, z)``, z-faces: ``(x, y)``).
    """

    lo: np.ndarray
    hi: np.ndarray
    textures: tuple[FaceTexture, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "lo", np.asarray(self.lo, dtype=np.float64))
        object.__setattr__(self, "hi", np.asarray(self.hi, dtype=np.float64))
        if len(self.textures) != 6:
            raise ValueError(f"a box needs 6 face textures, got {len(self.textures)}")

    @staticmethod
    def face_axes(face: int) -> tuple[int, int, int]:
        """``(normal axis, a axis, b axis)`` of ``face``."""
        axis = face // 2
        a_axis, b_axis = (k for k in range(3) if k != axis)
        return axis, a_axis, b_axis

    def face_extent(self, face: int) -> tuple[float, float]:
        """Size ``(along a, along b)`` of ``face`` in metres."""
        _, a_axis, b_axis = self.face_axes(face)
        size = self.hi - self.lo
        return float(size[a_axis]), float(size[b_axis])

    def face_point(self, face: int, ab: np.ndarray) -> np.ndarray:
        """World points ``[N, 3]`` at face coordinates ``ab`` ``[N, 2]`` (m) on ``face``."""
        axis, a_axis, b_axis = self.face_axes(face)
        ab = np.asarray(ab, dtype=np.float64).reshape(-1, 2)
        points = np.empty((len(ab), 3))
        points[:, axis] = self.hi[axis] if face % 2 else self.lo[axis]
        points[:, a_axis] = self.lo[a_axis] + ab[:, 0]
        points[:, b_axis] = self.lo[b_axis] + ab[:, 1]
        return points


@dataclass(frozen=True, eq=False)
class CameraRoute:
    """Closed walk through a scene that all its sequences follow, each with its own deviations.

    At route time ``tau`` (period 1) the position is ``centre + half · w(tau)`` per axis, with
    ``w`` a sum of two sines of integer ``cycles`` ``[3, 2]``, ``weights`` ``[2]`` (summing to
    1) and ``phases`` ``[3, 2]``; the yaw turns ``yaw_turns`` times around per period from
    ``yaw_start`` with a wobble of ``yaw_wobble`` rad and ``wobble_cycles`` per period.
    """

    centre: np.ndarray
    half: np.ndarray
    cycles: np.ndarray
    weights: np.ndarray
    phases: np.ndarray
    yaw_start: float
    yaw_turns: int
    yaw_wobble: float
    wobble_cycles: int
    wobble_phase: float

    @classmethod
    def random(cls, rng: np.random.Generator, centre: np.ndarray, half: np.ndarray) -> CameraRoute:
        """A route filling the box ``centre ± half`` (m): Lissajous-like over ``x, y``."""
        first = rng.permutation([2, 3])
        cycles = np.array(
            [
                [first[0], rng.integers(4, 6)],
                [first[1], rng.integers(4, 6)],
                [rng.integers(1, 4), rng.integers(4, 7)],
            ]
        )
        return cls(
            centre=np.asarray(centre, dtype=np.float64),
            half=np.asarray(half, dtype=np.float64),
            cycles=cycles,
            weights=np.array([0.8, 0.2]),
            phases=rng.uniform(0, 2 * np.pi, (3, 2)),
            yaw_start=float(rng.uniform(0, 2 * np.pi)),
            yaw_turns=int(rng.choice([-1, 1])),
            yaw_wobble=float(rng.uniform(0.3, 0.7)),
            wobble_cycles=int(rng.integers(1, 3)),
            wobble_phase=float(rng.uniform(0, 2 * np.pi)),
        )

    def at(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Positions ``[n, 3]`` (m) and yaw angles ``[n]`` (rad) at route times ``tau`` ``[n]``."""
        angles = 2 * np.pi * self.cycles[None] * np.asarray(tau)[:, None, None] + self.phases
        position = self.centre + self.half * (np.sin(angles) @ self.weights)
        yaw = (
            self.yaw_start
            + 2 * np.pi * self.yaw_turns * tau
            + self.yaw_wobble * np.sin(2 * np.pi * self.wobble_cycles * tau + self.wobble_phase)
        )
        return position, yaw


@dataclass(frozen=True, eq=False)
class SyntheticScene:
    """A room seen from inside, boxes inside it seen from outside, a point light ``[3]`` (m)
    and the route the cameras walk: within ``route.centre ± route.half``, which the boxes keep
    0.6 m (plus the test sequences' lateral offset) away from; sequences stray from the route
    by at most 0.35 m. ``route`` is None for a world built around given poses.
    ``scale`` is the world's size relative to a room (m per room metre): the point light's
    fall-off distance grows with it."""

    name: str
    room: Box
    boxes: tuple[Box, ...]
    light_position: np.ndarray
    route: CameraRoute | None
    scale: float = 1.0

    @functools.cached_property
    def _tables(self) -> _FaceTables:
        return _FaceTables.build(self)


@dataclass(frozen=True, eq=False)
class _FaceTables:
    """All face textures flattened into one ``[T, 3]`` array, with per-face lookup arrays
    ``[F]``. Face ``6·k + f`` is face ``f`` of box ``k`` (box 0 is the room); its normal, facing
    the free space, lies along axis ``f // 2`` with sign ``normal_sign``."""

    texels: np.ndarray
    offset: np.ndarray
    cols: np.ndarray
    rows: np.ndarray
    inv_texel: np.ndarray
    origin_a: np.ndarray
    origin_b: np.ndarray
    normal_sign: np.ndarray

    @classmethod
    def build(cls, scene: SyntheticScene) -> _FaceTables:
        images, offset, cols, rows, inv_texel = [], [], [], [], []
        origin_a, origin_b, normal_sign = [], [], []
        start = 0
        for index, box in enumerate((scene.room, *scene.boxes)):
            for face, texture in enumerate(box.textures):
                _, a_axis, b_axis = Box.face_axes(face)
                image = np.asarray(texture.image, dtype=np.float32)
                images.append(image.reshape(-1, 3))
                offset.append(start)
                start += image.shape[0] * image.shape[1]
                rows.append(image.shape[0])
                cols.append(image.shape[1])
                inv_texel.append(1.0 / texture.texel_size)
                origin_a.append(box.lo[a_axis])
                origin_b.append(box.lo[b_axis])
                outward = 1.0 if face % 2 else -1.0
                normal_sign.append(-outward if index == 0 else outward)
        return cls(
            texels=np.concatenate(images),
            offset=np.asarray(offset, dtype=np.int64),
            cols=np.asarray(cols, dtype=np.int64),
            rows=np.asarray(rows, dtype=np.int64),
            inv_texel=np.asarray(inv_texel, dtype=np.float32),
            origin_a=np.asarray(origin_a, dtype=np.float32),
            origin_b=np.asarray(origin_b, dtype=np.float32),
            normal_sign=np.asarray(normal_sign, dtype=np.float32),
        )


def scene_name(index: int) -> str:
    """Name of scene ``index``: ``scene00``, ``scene01``, …"""
    return f"scene{index:02d}"


def _rgb(hue: float, saturation: float, value: float) -> tuple[float, float, float]:
    return colorsys.hsv_to_rgb(hue % 1.0, float(np.clip(saturation, 0, 1)), float(value))


def _texel_shape(width_m: float, height_m: float) -> tuple[int, int]:
    """``(rows, cols)`` of a texture covering ``width_m × height_m``."""
    return max(2, math.ceil(height_m / TEXEL_SIZE_M)), max(2, math.ceil(width_m / TEXEL_SIZE_M))


def _smooth_field(
    shape: tuple[int, int], cells: tuple[int, int], colours: np.ndarray
) -> np.ndarray:
    """Image ``[rows, cols, 3]`` interpolating a ``cells`` grid of ``colours`` ``[cy, cx, 3]``."""
    rows, cols = shape
    grid = np.asarray(colours, dtype=np.float32).reshape(cells[0], cells[1], 3)
    return cv2.resize(grid, (cols, rows), interpolation=cv2.INTER_CUBIC)


def _value_noise(rng: np.random.Generator, shape: tuple[int, int], scale: int) -> np.ndarray:
    """Zero-mean smooth noise ``[rows, cols, 1]`` with features of about ``scale`` texels."""
    rows, cols = shape
    coarse = rng.random((max(2, rows // scale + 2), max(2, cols // scale + 2)), dtype=np.float32)
    noise = cv2.resize(coarse - 0.5, (cols, rows), interpolation=cv2.INTER_CUBIC)
    return noise[:, :, None]


def _draw_shapes(
    rng: np.random.Generator, image: np.ndarray, count: int, size_m: tuple[float, float]
) -> None:
    """Draw ``count`` random filled shapes (circles, rectangles, triangles, rings, striped and
    checkered patches) of ``size_m`` (min, max) metres and random colours into ``image``."""
    rows, cols = image.shape[:2]
    shift = 4
    scale = (1 << shift) / TEXEL_SIZE_M
    for _ in range(count):
        kind = rng.integers(6)
        colour = _rgb(rng.random(), rng.uniform(0.5, 1.0), rng.uniform(0.3, 1.0))
        size = rng.uniform(*size_m)
        centre_m = np.array([rng.uniform(0, cols), rng.uniform(0, rows)]) * TEXEL_SIZE_M
        centre = tuple(int(v) for v in centre_m * scale)
        half = int(size / 2 * scale)
        if kind == 0:
            cv2.circle(image, centre, half, colour, -1, cv2.LINE_AA, shift)
        elif kind == 1:
            ring_width = max(2, round(0.12 * size / TEXEL_SIZE_M))
            cv2.circle(image, centre, half, colour, ring_width, cv2.LINE_AA, shift)
        elif kind == 2:
            angles = rng.uniform(0, 2 * np.pi) + np.array([0, 2.1, 4.2]) + rng.normal(0, 0.2, 3)
            corners = np.stack([np.cos(angles), np.sin(angles)], -1) * half + centre
            cv2.fillPoly(image, [corners.astype(np.int32)], colour, cv2.LINE_AA, shift)
        else:
            aspect = rng.uniform(0.4, 1.0)
            half_w, half_h = (
                (half, int(half * aspect)) if rng.random() < 0.5 else (int(half * aspect), half)
            )
            top_left = (centre[0] - half_w, centre[1] - half_h)
            bottom_right = (centre[0] + half_w, centre[1] + half_h)
            cv2.rectangle(image, top_left, bottom_right, colour, -1, cv2.LINE_AA, shift)
            if kind >= 4:
                _pattern_patch(rng, image, centre_m, half_w / scale, half_h / scale, kind == 4)


def _pattern_patch(
    rng: np.random.Generator,
    image: np.ndarray,
    centre_m: np.ndarray,
    half_w_m: float,
    half_h_m: float,
    stripes: bool,
) -> None:
    """Overlay stripes or a checkerboard (second colour) on a rectangle of the texture."""
    rows, cols = image.shape[:2]
    half = np.array([half_w_m, half_h_m])
    c0, r0 = (centre_m - half) / TEXEL_SIZE_M
    c1, r1 = (centre_m + half) / TEXEL_SIZE_M
    c0, r0 = max(0, int(c0)), max(0, int(r0))
    c1, r1 = min(cols, int(c1)), min(rows, int(r1))
    if c1 <= c0 or r1 <= r0:
        return
    period = rng.uniform(0.08, 0.25) / TEXEL_SIZE_M
    jj, ii = np.meshgrid(np.arange(c0, c1), np.arange(r0, r1))
    if stripes:
        angle = rng.choice([0.0, np.pi / 2, np.pi / 4, -np.pi / 4])
        phase = (np.cos(angle) * jj + np.sin(angle) * ii) / period
        mask = (np.sin(2 * np.pi * phase) > 0).astype(np.float32)
    else:
        mask = ((jj // (period / 2) + ii // (period / 2)) % 2).astype(np.float32)
    colour = np.array(
        _rgb(rng.random(), rng.uniform(0.3, 1.0), rng.uniform(0.2, 1.0)), dtype=np.float32
    )
    patch = image[r0:r1, c0:c1]
    patch += mask[:, :, None] * (colour - patch)


def _finish(rng: np.random.Generator, image: np.ndarray) -> FaceTexture:
    """Add fine detail, band-limit to a few centimetres, clip to ``[0, 1]``."""
    shape = image.shape[:2]
    image = image * (1.0 + 0.25 * _value_noise(rng, shape, 3))
    image = image + 0.08 * _value_noise(rng, shape, 12)
    image = cv2.GaussianBlur(image, (0, 0), 1.0)
    return FaceTexture(np.clip(image, 0.0, 1.0).astype(np.float32))


def _wall_texture(
    rng: np.random.Generator, width_m: float, height_m: float, hue: float
) -> FaceTexture:
    """Wall with a dominant ``hue``: colour gradients, a dado band, big shapes and detail."""
    shape = _texel_shape(width_m, height_m)
    cells = (2, max(2, round(width_m / 1.5)))
    colours = [
        _rgb(hue + rng.normal(0, 0.05), rng.uniform(0.3, 0.8), rng.uniform(0.35, 0.9))
        for _ in range(cells[0] * cells[1])
    ]
    image = _smooth_field(shape, cells, np.array(colours))
    band_lo, band_hi = sorted(rng.uniform(0.3, 1.2, 2))
    band = slice(int(band_lo / TEXEL_SIZE_M), int(band_hi / TEXEL_SIZE_M) + 2)
    image[band] = 0.5 * image[band] + 0.5 * np.float32(_rgb(hue + 0.5, 0.6, rng.uniform(0.2, 0.8)))
    _draw_shapes(rng, image, 3 + int(width_m * height_m / 1.5), (0.3, 1.1))
    _draw_shapes(rng, image, int(width_m * height_m), (0.08, 0.3))
    return _finish(rng, image)


def _floor_texture(rng: np.random.Generator, width_m: float, depth_m: float) -> FaceTexture:
    """Tiled floor shaded by a gradient, with a few rugs."""
    rows, cols = _texel_shape(width_m, depth_m)
    hue = rng.random()
    colours = [
        _rgb(hue + rng.normal(0, 0.08), rng.uniform(0.2, 0.6), rng.uniform(0.4, 0.9))
        for _ in range(9)
    ]
    image = _smooth_field((rows, cols), (3, 3), np.array(colours))
    tile = int(rng.uniform(0.4, 0.7) / TEXEL_SIZE_M)
    jj, ii = np.meshgrid(np.arange(cols), np.arange(rows))
    checker = ((jj // tile + ii // tile) % 2).astype(np.float32)[:, :, None]
    image *= 1.0 - 0.3 * checker
    _draw_shapes(rng, image, 3 + int(width_m * depth_m / 8), (0.8, 2.0))
    return _finish(rng, image)


def _ceiling_texture(rng: np.random.Generator, width_m: float, depth_m: float) -> FaceTexture:
    """Pale ceiling with a grid of light panels and a few shapes."""
    rows, cols = _texel_shape(width_m, depth_m)
    hue = rng.random()
    colours = [
        _rgb(hue + rng.normal(0, 0.1), rng.uniform(0.05, 0.4), rng.uniform(0.6, 0.95))
        for _ in range(4)
    ]
    image = _smooth_field((rows, cols), (2, 2), np.array(colours))
    spacing = rng.uniform(1.2, 2.0) / TEXEL_SIZE_M
    panel = int(0.25 / TEXEL_SIZE_M)
    for r in np.arange(spacing / 2, rows, spacing):
        for c in np.arange(spacing / 2, cols, spacing):
            image[
                max(0, int(r) - panel) : int(r) + panel,
                max(0, int(c) - 2 * panel) : int(c) + 2 * panel,
            ] = 1.0
    _draw_shapes(rng, image, 2 + int(width_m * depth_m / 10), (0.3, 1.0))
    return _finish(rng, image)


def _box_textures(
    rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray
) -> tuple[FaceTexture, ...]:
    """Six textures of a box: one base colour, a pattern and a shape or two per face."""
    hue = rng.random()
    textures = []
    for face in range(6):
        _, a_axis, b_axis = Box.face_axes(face)
        width_m, height_m = hi[a_axis] - lo[a_axis], hi[b_axis] - lo[b_axis]
        shape = _texel_shape(width_m, height_m)
        base = _rgb(hue + rng.normal(0, 0.04), rng.uniform(0.4, 0.9), rng.uniform(0.3, 0.9))
        image = np.empty((*shape, 3), dtype=np.float32)
        image[:] = base
        centre = np.array([width_m, height_m]) / 2
        _pattern_patch(rng, image, centre, width_m / 2, height_m / 2, bool(rng.random() < 0.5))
        image = 0.6 * image + 0.4 * np.float32(base)
        _draw_shapes(rng, image, 1 + int(width_m * height_m), (0.15, 0.5))
        textures.append(_finish(rng, image))
    return tuple(textures)


def _overlaps(
    lo: np.ndarray, hi: np.ndarray, other_lo: np.ndarray, other_hi: np.ndarray, margin: float
) -> bool:
    """Whether two boxes' ``xy`` footprints come closer than ``margin``."""
    return bool(np.all(lo[:2] < other_hi[:2] + margin) and np.all(other_lo[:2] < hi[:2] + margin))


def room_textures(rng: np.random.Generator, size: np.ndarray) -> tuple[FaceTexture, ...]:
    """The six face textures of a room of ``size`` ``[3]`` (m): four walls of hues a quarter
    turn apart, a floor and a ceiling."""
    hue0 = rng.random()
    wall_hues = hue0 + np.array([0.0, 0.25, 0.5, 0.75]) + rng.normal(0, 0.03, 4)
    return (
        _wall_texture(rng, size[1], size[2], wall_hues[0]),
        _wall_texture(rng, size[1], size[2], wall_hues[1]),
        _wall_texture(rng, size[0], size[2], wall_hues[2]),
        _wall_texture(rng, size[0], size[2], wall_hues[3]),
        _floor_texture(rng, size[0], size[1]),
        _ceiling_texture(rng, size[0], size[1]),
    )


def furnish(
    rng: np.random.Generator,
    room: Box,
    region_lo: np.ndarray,
    region_hi: np.ndarray,
    keep_out: float,
    count: int = 5,
) -> tuple[Box, ...]:
    """Up to ``count`` boxes and thin panels standing on the floor of ``room``, their
    footprints ``keep_out`` (m) clear of the camera region ``region_lo..region_hi`` ``[3]``
    and 0.1 m clear of each other (200 random placements are tried)."""
    boxes: list[Box] = []
    for _attempt in range(200):
        if len(boxes) >= count:
            break
        panel = rng.random() < 0.3
        footprint = rng.uniform(0.4, 1.2, 2)
        if panel:
            footprint[rng.integers(2)] = 0.06
        height = rng.uniform(1.8, 2.3) if panel else rng.uniform(0.5, 2.2)
        lo = np.array(
            [*rng.uniform(room.lo[:2] + 0.05, room.hi[:2] - footprint - 0.05), room.lo[2]]
        )
        hi = lo + np.array([*footprint, height])
        if _overlaps(lo, hi, region_lo, region_hi, keep_out) or any(
            _overlaps(lo, hi, b.lo, b.hi, 0.1) for b in boxes
        ):
            continue
        boxes.append(Box(lo, hi, _box_textures(rng, lo, hi)))
    return tuple(boxes)


def make_scene(
    index: int,
    seed: int = 0,
    test_offset_m: float = DEFAULT_TEST_OFFSET_M,
    train_lane_m: float = DEFAULT_TRAIN_LANE_M,
) -> SyntheticScene:
    """Scene ``index`` of the benchmark with ``seed``: room, furniture, textures, camera route.

    ``test_offset_m`` and ``train_lane_m`` are the lateral offsets of the test and train
    sequences from the route (see :func:`make_sequences`); the furniture keeps the larger of
    them further away from the route.
    """
    rng = np.random.default_rng([seed, index, 0])
    size = np.array([rng.uniform(6.0, 8.0), rng.uniform(5.5, 7.0), rng.uniform(2.6, 3.2)])
    room_lo = np.array([-size[0] / 2, -size[1] / 2, 0.0])
    room = Box(room_lo, room_lo + size, room_textures(rng, size))

    centre = np.array([*rng.uniform(-0.3, 0.3, 2), 1.4])
    half = np.array([rng.uniform(1.2, 1.6), rng.uniform(1.0, 1.4), 0.3])
    route = CameraRoute.random(rng, centre, half)
    boxes = furnish(rng, room, centre - half, centre + half, 0.6 + max(test_offset_m, train_lane_m))
    light = np.array([*rng.uniform(-1.0, 1.0, 2), size[2] - 0.5])
    return SyntheticScene(scene_name(index), room, boxes, light, route)


# ----------------------------------------------------------------------------- appearance


@dataclass(frozen=True)
class Appearance:
    """Lighting and camera response of one sequence.

    The shaded linear colour ``c`` becomes ``clip(c·tint·gain + bias)^gamma + noise``;
    ``ambient`` is the share of light not coming from the scene's point light.
    """

    gain: float = 1.0
    bias: float = 0.0
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)
    gamma: float = 1.0
    noise_std: float = 0.0
    ambient: float = 0.45

    @classmethod
    def random(cls, rng: np.random.Generator) -> Appearance:
        """A random appearance: gain 0.7–1.3, bias ±0.06, tint ±15 %, gamma 0.75–1.35,
        noise 0.005–0.025 (std of values in ``[0, 1]``), ambient 0.3–0.6."""
        return cls(
            gain=float(rng.uniform(0.7, 1.3)),
            bias=float(rng.uniform(-0.06, 0.06)),
            tint=tuple(float(v) for v in rng.uniform(0.85, 1.15, 3)),
            gamma=float(rng.uniform(0.75, 1.35)),
            noise_std=float(rng.uniform(0.005, 0.025)),
            ambient=float(rng.uniform(0.3, 0.6)),
        )


# ------------------------------------------------------------------------------ rendering


def _cast(
    scene: SyntheticScene, origins: np.ndarray, directions: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hits of rays with origins ``[3, B, 1]`` inside the room and directions
    ``[3, B, R]`` (axis first): face index ``[B, R]`` (see :class:`_FaceTables`) and the
    distance ``[B, R]`` along each direction, in units of its length."""
    directions = np.where(np.abs(directions) < _EPS_DIRECTION, _EPS_DIRECTION, directions)
    inverse = 1.0 / directions
    positive = directions > 0
    lo, hi = scene.room.lo.astype(np.float32), scene.room.hi.astype(np.float32)
    t_exit = [(np.where(positive[k], hi[k], lo[k]) - origins[k]) * inverse[k] for k in range(3)]
    t_best = np.minimum(np.minimum(t_exit[0], t_exit[1]), t_exit[2])
    face = np.where(
        t_exit[0] == t_best,
        positive[0].astype(np.int64),
        np.where(t_exit[1] == t_best, 2 + positive[1], 4 + positive[2]),
    )
    for index, box in enumerate(scene.boxes, start=1):
        lo, hi = box.lo.astype(np.float32), box.hi.astype(np.float32)
        near, far = [], []
        for k in range(3):
            t_lo = (lo[k] - origins[k]) * inverse[k]
            t_hi = (hi[k] - origins[k]) * inverse[k]
            near.append(np.minimum(t_lo, t_hi))
            far.append(np.maximum(t_lo, t_hi))
        t_near = np.maximum(np.maximum(near[0], near[1]), near[2])
        t_far = np.minimum(np.minimum(far[0], far[1]), far[2])
        hit = (t_near <= t_far) & (t_near > 0) & (t_near < t_best)
        if not hit.any():
            continue
        t_hit = t_near[hit]
        axis = np.where(near[0][hit] == t_hit, 0, np.where(near[1][hit] == t_hit, 1, 2))
        entered_hi = ~positive[:, hit][axis, np.arange(len(axis))]
        t_best[hit] = t_hit
        face[hit] = 6 * index + 2 * axis + entered_hi
    return face, t_best


def _shade(
    scene: SyntheticScene, origins: np.ndarray, directions: np.ndarray, ambient: float
) -> tuple[np.ndarray, np.ndarray]:
    """Linear colours ``[B, R, 3]`` float32 of rays (origins ``[3, B, 1]``, directions
    ``[3, B, R]``): bilinearly sampled texture × (ambient + point light), and the distance
    ``[B, R]`` to the hit along each direction (in units of its length)."""
    tables = scene._tables
    face, t = _cast(scene, origins, directions)
    x, y, z = (origins[k] + t * directions[k] for k in range(3))
    normal_axis = (face % 6) // 2
    a = np.where(normal_axis == 0, y, x) - tables.origin_a[face]
    b = np.where(normal_axis == 2, y, z) - tables.origin_b[face]
    col = a * tables.inv_texel[face] - 0.5
    row = b * tables.inv_texel[face] - 0.5
    col0, row0 = np.floor(col), np.floor(row)
    frac_c, frac_r = (col - col0)[..., None], (row - row0)[..., None]
    cols, rows, offset = tables.cols[face], tables.rows[face], tables.offset[face]
    col0, row0 = col0.astype(np.int64), row0.astype(np.int64)
    c0, c1 = np.clip(col0, 0, cols - 1), np.clip(col0 + 1, 0, cols - 1)
    r0 = np.clip(row0, 0, rows - 1) * cols + offset
    r1 = np.clip(row0 + 1, 0, rows - 1) * cols + offset
    texels = tables.texels
    top = texels[r0 + c0] * (1 - frac_c) + texels[r0 + c1] * frac_c
    bottom = texels[r1 + c0] * (1 - frac_c) + texels[r1 + c1] * frac_c
    colour = top * (1 - frac_r) + bottom * frac_r

    light = scene.light_position.astype(np.float32)
    to_light = (light[0] - x, light[1] - y, light[2] - z)
    distance_sq = to_light[0] ** 2 + to_light[1] ** 2 + to_light[2] ** 2
    along_normal = np.where(
        normal_axis == 0, to_light[0], np.where(normal_axis == 1, to_light[1], to_light[2])
    )
    cosine = along_normal * tables.normal_sign[face] / np.sqrt(distance_sq)
    direct = np.maximum(cosine, 0.0) * 2.2 / (1.0 + distance_sq / (6.0 * scene.scale**2))
    return colour * (ambient + (1.0 - ambient) * direct)[..., None], t


def shade_rays(
    scene: SyntheticScene, origins: np.ndarray, directions: np.ndarray, ambient: float = 0.45
) -> tuple[np.ndarray, np.ndarray]:
    """Exact colours and hit distances of rays from origins ``[N, 3]`` (inside the room)
    along directions ``[N, 3]``: linear RGB ``[N, 3]`` float32 (no camera response) and the
    distance ``[N]`` to the first hit in units of each direction's length."""
    origins = np.asarray(origins, dtype=np.float32).T[:, :, None]
    directions = np.asarray(directions, dtype=np.float32).T[:, :, None]
    colour, t = _shade(scene, origins, directions, ambient)
    return colour[:, 0], t[:, 0]


def render_batch(
    scene: SyntheticScene,
    poses: np.ndarray,
    camera: PinholeCamera,
    appearance: Appearance | None = None,
    rng: np.random.Generator | None = None,
    supersample: int = SUPERSAMPLE,
) -> np.ndarray:
    """Images ``[B, H, W, 3]`` uint8 RGB of ``scene`` from camera-to-world ``poses`` ``[B, 7]``.

    ``rng`` draws the sensor noise (``appearance.noise_std``); ``None`` renders without noise.
    """
    appearance = appearance or Appearance()
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 7)
    rotations, positions = pose_rotation_translation(poses)
    local = camera.ray_directions(supersample).reshape(-1, 3)
    size = camera.size
    frames_per_chunk = max(1, RAYS_PER_CHUNK // len(local))
    images = np.empty((len(poses), size, size, 3), dtype=np.uint8)
    tint = np.asarray(appearance.tint, dtype=np.float32) * np.float32(appearance.gain)
    for start in range(0, len(poses), frames_per_chunk):
        stop = min(start + frames_per_chunk, len(poses))
        directions = np.einsum("bij,nj->ibn", rotations[start:stop], local).astype(np.float32)
        origins = positions[start:stop].T[:, :, None].astype(np.float32)
        colour, _ = _shade(scene, origins, directions, appearance.ambient)
        colour = colour.reshape(stop - start, supersample * supersample, size, size, 3).mean(1)
        colour = np.clip(colour * tint + np.float32(appearance.bias), 0.0, 1.0)
        colour **= np.float32(appearance.gamma)
        if rng is not None and appearance.noise_std > 0:
            colour += np.float32(appearance.noise_std) * rng.standard_normal(
                colour.shape, dtype=np.float32
            )
        images[start:stop] = np.clip(np.rint(colour * 255.0), 0, 255).astype(np.uint8)
    return images


def render(
    scene: SyntheticScene,
    pose: np.ndarray,
    camera: PinholeCamera,
    appearance: Appearance | None = None,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Image ``[H, W, 3]`` uint8 RGB of ``scene`` from camera-to-world ``pose`` ``[7]``."""
    return render_batch(scene, np.asarray(pose)[None], camera, appearance, rng)[0]


# ---------------------------------------------------------------------------- trajectories


@dataclass(frozen=True, eq=False)
class CameraSequence:
    """One recorded sequence: ``name`` (``seq-01``…), ``split``, poses ``[n, 7]`` and its
    appearance; ``noise_seed`` seeds its sensor noise."""

    name: str
    split: str
    poses: np.ndarray
    appearance: Appearance
    noise_seed: tuple[int, ...]


def _split_counts(total: int, parts: int) -> list[int]:
    """``total`` frames over ``min(parts, total)`` sequences, as evenly as possible."""
    parts = min(parts, total)
    return [total // parts + (1 if i < total % parts else 0) for i in range(parts)]


def _smooth_wave(
    rng: np.random.Generator,
    t: np.ndarray,
    cycles: tuple[float, float],
    weights: tuple[float, float],
) -> np.ndarray:
    """Sum of two sines of ``t`` ``[n]`` with random phases and frequencies: ``cycles`` bounds
    the first one's cycles per unit of ``t``, the second is 2–3 times faster."""
    f1 = rng.uniform(*cycles)
    f2 = rng.uniform(2 * cycles[1], 3 * cycles[1])
    p1, p2 = rng.uniform(0, 2 * np.pi, 2)
    return weights[0] * np.sin(2 * np.pi * f1 * t + p1) + weights[1] * np.sin(
        2 * np.pi * f2 * t + p2
    )


def _route_normals(route: CameraRoute, tau: np.ndarray) -> np.ndarray:
    """Unit horizontal normals ``[n, 3]`` to the left of the route's direction at ``tau``."""
    here, _ = route.at(tau)
    ahead, _ = route.at(tau + 1e-4)
    direction = ahead[:, :2] - here[:, :2]
    direction /= np.linalg.norm(direction, axis=1, keepdims=True).clip(min=1e-12)
    return np.stack([-direction[:, 1], direction[:, 0], np.zeros(len(tau))], axis=1)


def _trajectory(
    scene: SyntheticScene,
    frames: int,
    start: float,
    rng: np.random.Generator,
    offset_m: float = 0.0,
    yaw_stray_rad: float = DEFAULT_YAW_STRAY_RAD,
    stray_m: float = DEFAULT_STRAY_M,
) -> np.ndarray:
    """Smooth camera path of ``frames`` poses ``[frames, 7]`` along the scene's route.

    The sequence walks 55–75 % of the route from route time ``start``, ``offset_m`` to the
    left of it (negative: to the right), straying from that path by up to ``stray_m`` and
    ``yaw_stray_rad`` of yaw; pitch stays within about −14…+8° and roll within ±5°.
    """
    if scene.route is None:
        raise ValueError(f"scene {scene.name} has no camera route")
    t = np.arange(frames) / max(frames, 1)
    tau = start + rng.uniform(0.55, 0.75) * t
    route_position, route_yaw = scene.route.at(tau)
    if offset_m:
        route_position = route_position + offset_m * _route_normals(scene.route, tau)
    position = route_position + np.stack(
        [
            stray_m * _smooth_wave(rng, t, (0.5, 1.5), (0.7, 0.3)),
            stray_m * _smooth_wave(rng, t, (0.5, 1.5), (0.7, 0.3)),
            0.1 * _smooth_wave(rng, t, (0.5, 1.5), (0.7, 0.3)),
        ],
        axis=1,
    )
    yaw = route_yaw + yaw_stray_rad * _smooth_wave(rng, t, (0.5, 1.5), (0.7, 0.3))
    pitch = np.radians(-3.0) + np.radians(11.0) * _smooth_wave(rng, t, (0.5, 1.5), (0.8, 0.2))
    roll = np.radians(5.0) * _smooth_wave(rng, t, (0.5, 1.5), (0.7, 0.3))
    rotations = _look_rotations(yaw, pitch, roll)
    quaternions = matrix_to_quaternion(torch.from_numpy(rotations)).numpy()
    return np.concatenate([position, quaternions], axis=1)


def make_sequences(
    scene_index: int,
    scene: SyntheticScene,
    train_frames: int,
    test_frames: int,
    seed: int = 0,
    test_offset_m: float = DEFAULT_TEST_OFFSET_M,
    train_lane_m: float = DEFAULT_TRAIN_LANE_M,
    yaw_stray_rad: float = DEFAULT_YAW_STRAY_RAD,
    stray_m: float = DEFAULT_STRAY_M,
) -> list[CameraSequence]:
    """Train sequences ``seq-01…`` then test sequences (numbered on) of scene ``scene_index``.

    Up to 6 train and 2 test sequences share the frames of each split. Each walks most of the
    scene's route with its own deviations and :class:`Appearance`; the sequences of a split
    start at staggered route times, so that together they cover the whole route. Test
    sequences walk ``test_offset_m`` beside the route, alternately to its left and right (0:
    on the route, like the train sequences).
    """
    train_counts = _split_counts(train_frames, TRAIN_SEQUENCES)
    test_counts = _split_counts(test_frames, TEST_SEQUENCES)
    splits = [("train", i, len(train_counts), n) for i, n in enumerate(train_counts)]
    splits += [("test", i, len(test_counts), n) for i, n in enumerate(test_counts)]
    sequences = []
    for number, (split, index_in_split, count, frames) in enumerate(splits, start=1):
        rng = np.random.default_rng([seed, scene_index, 1, number])
        start = (index_in_split + rng.uniform(0, 0.3)) / count
        lane = train_lane_m if split == "train" else test_offset_m
        offset = lane * (-1) ** index_in_split
        poses = _trajectory(scene, frames, start, rng, offset, yaw_stray_rad, stray_m)
        appearance = Appearance.random(rng)
        sequences.append(
            CameraSequence(
                f"seq-{number:02d}", split, poses, appearance, (seed, scene_index, 2, number)
            )
        )
    return sequences


# -------------------------------------------------------------------------------- writing


@dataclass(frozen=True)
class SyntheticSummary:
    """What :func:`write_synthetic_dataset` wrote and how fast."""

    root: str
    scenes: list[str]
    train_frames: int
    """Training frames over all scenes."""
    test_frames: int
    """Test frames over all scenes."""
    size: int
    seconds: float
    frames_per_second: float

    def summary(self) -> str:
        """Short human-readable multi-line summary."""
        return "\n".join(
            [
                f"synthetic dataset at {self.root}",
                f"  scenes: {len(self.scenes)} ({', '.join(self.scenes)})",
                f"  frames: {self.train_frames} train, {self.test_frames} test "
                f"({self.size}x{self.size} px)",
                f"  time:   {self.seconds:.1f} s ({self.frames_per_second:.1f} frames/s)",
            ]
        )


def _write_png(path: Path, image_rgb: np.ndarray) -> None:
    """Write an RGB image as PNG (into the rendering folder, renamed into place when whole)."""
    ok, encoded = cv2.imencode(".png", cv2.cvtColor(image_rgb, cv2.COLOR_RGB2BGR))
    if not ok:
        raise OSError(f"could not encode {path}")
    path.write_bytes(encoded.tobytes())


def _prepare_output(out: Path, overwrite: bool) -> None:
    """Refuse a used folder unless `overwrite`, and even then one that holds no dataset."""
    if not out.exists():
        return
    if not out.is_dir():
        raise FileExistsError(f"{out}: exists and is not a folder")
    if not any(out.iterdir()):
        return
    if not overwrite:
        raise FileExistsError(f"{out}: folder is not empty; --overwrite replaces the dataset in it")
    if not (out / "labels").is_dir():
        raise FileExistsError(
            f"{out}: folder is not empty and holds no dataset (no labels/); not replacing it"
        )


def _replace_folder(new: Path, out: Path) -> None:
    """Put the folder `new` in place of `out` (moved aside, then deleted if it existed)."""
    old = out.with_name(f".{out.name}.old-{uuid.uuid4().hex}")
    if out.exists():
        out.rename(old)
    new.rename(out)
    shutil.rmtree(old, ignore_errors=True)


RenderProgress = Callable[[int, int], None]
"""``progress(done, total)``: frames rendered so far, of all the dataset's frames."""


def render_frames(
    out: Path,
    paths: list[str],
    scene: SyntheticScene,
    poses: np.ndarray,
    camera: PinholeCamera,
    appearance: Appearance,
    noise: np.random.Generator,
) -> None:
    """Render ``poses`` ``[n, 7]`` of one sequence and write them as PNGs at ``out / paths[i]``,
    ``FRAMES_PER_WRITE`` frames at a time."""
    for folder in sorted({(out / path).parent for path in paths}):
        folder.mkdir(parents=True, exist_ok=True)
    for start in range(0, len(poses), FRAMES_PER_WRITE):
        images = render_batch(
            scene, poses[start : start + FRAMES_PER_WRITE], camera, appearance, noise
        )
        for path, image in zip(paths[start : start + FRAMES_PER_WRITE], images, strict=True):
            _write_png(out / path, image)


def write_label_files(folder: Path, tables: dict[tuple[str, str], LabelTable]) -> None:
    """``folder/<scene>_<split>.csv`` for each ``(scene, split)`` table, then
    ``folder/all_<split>.csv`` for each split (the data modules read those last)."""
    for (name, split), table in tables.items():
        write_labels(folder / f"{name}_{split}.csv", table)
    for split in dict.fromkeys(split for _, split in tables):
        write_labels(
            folder / f"all_{split}.csv",
            LabelTable.concat(t for (_, s), t in tables.items() if s == split),
        )


def write_whole(
    out: Path | str, overwrite: bool, render: Callable[[Path], SyntheticSummary]
) -> SyntheticSummary:
    """Run ``render(folder)`` into a hidden folder beside ``out``, then put it in place of
    ``out``: ``out`` ends as exactly the new dataset, or unchanged when rendering fails.

    A non-empty ``out`` is refused (FileExistsError) unless ``overwrite``, which replaces a
    folder holding a dataset (``labels/``) as a whole, stale files included. The summary's
    ``root`` names ``out``.
    """
    final = Path(out)
    _prepare_output(final, overwrite)
    final.parent.mkdir(parents=True, exist_ok=True)
    folder = final.with_name(f".{final.name}.rendering-{uuid.uuid4().hex}")
    try:
        summary = render(folder)
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    _replace_folder(folder, final)
    return dataclasses.replace(summary, root=str(final))


def write_synthetic_dataset(
    out: Path | str,
    scenes: int = DEFAULT_SCENES,
    train_frames: int = DEFAULT_TRAIN_FRAMES,
    test_frames: int = DEFAULT_TEST_FRAMES,
    size: int = DEFAULT_SIZE,
    seed: int = 0,
    test_offset_m: float = DEFAULT_TEST_OFFSET_M,
    overwrite: bool = False,
    train_lane_m: float = DEFAULT_TRAIN_LANE_M,
    yaw_stray_rad: float = DEFAULT_YAW_STRAY_RAD,
    stray_m: float = DEFAULT_STRAY_M,
    progress: RenderProgress | None = None,
) -> SyntheticSummary:
    """Render the benchmark into ``out`` (see :func:`write_whole`): images first, label files
    last.

    ``train_frames`` and ``test_frames`` are per scene; ``test_offset_m`` is the test
    sequences' lateral offset from the train route (see :func:`make_sequences`). The same
    arguments give byte-identical files. ``progress(done, total)`` is called after each
    sequence with the frames rendered so far.
    """
    for name, value, low in (
        ("scenes", scenes, 1),
        ("train_frames", train_frames, 1),
        ("test_frames", test_frames, 1),
        ("size", size, 8),
        ("seed", seed, 0),
    ):
        if int(value) != value or value < low:
            raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
    for name, value in (
        ("test_offset_m", test_offset_m),
        ("train_lane_m", train_lane_m),
        ("stray_m", stray_m),
    ):
        if not (math.isfinite(value) and 0 <= value <= 1.0):
            raise ValueError(f"{name} must lie in [0, 1] m, got {value!r}")
    if not (math.isfinite(yaw_stray_rad) and 0 <= yaw_stray_rad <= math.pi / 2):
        raise ValueError(f"yaw_stray_rad must lie in [0, pi/2], got {yaw_stray_rad!r}")

    def render(folder: Path) -> SyntheticSummary:
        started = time.perf_counter()
        _render(
            folder,
            scenes,
            train_frames,
            test_frames,
            size,
            seed,
            (test_offset_m, train_lane_m, yaw_stray_rad, stray_m),
            progress,
        )
        seconds = time.perf_counter() - started
        return SyntheticSummary(
            root=str(folder),
            scenes=[scene_name(i) for i in range(scenes)],
            train_frames=scenes * train_frames,
            test_frames=scenes * test_frames,
            size=size,
            seconds=seconds,
            frames_per_second=scenes * (train_frames + test_frames) / seconds,
        )

    return write_whole(out, overwrite, render)


def _render(
    out: Path,
    scenes: int,
    train_frames: int,
    test_frames: int,
    size: int,
    seed: int,
    layout: tuple[float, float, float, float],
    progress: RenderProgress | None = None,
) -> None:
    """Render every scene into `out`: images first, label files last. ``layout``: the test
    offset, train lane (m), yaw stray (rad) and stray (m) of :func:`make_sequences`."""
    test_offset_m, train_lane_m, yaw_stray_rad, stray_m = layout
    total, done = scenes * (train_frames + test_frames), 0
    camera = PinholeCamera(size)
    label_tables: dict[tuple[str, str], LabelTable] = {}
    for index in range(scenes):
        scene = make_scene(index, seed, test_offset_m, train_lane_m)
        rows: dict[str, list[tuple[str, str, np.ndarray]]] = {"train": [], "test": []}
        sequences = make_sequences(
            index,
            scene,
            train_frames,
            test_frames,
            seed,
            test_offset_m,
            train_lane_m,
            yaw_stray_rad,
            stray_m,
        )
        for sequence in sequences:
            paths = [
                f"{scene.name}/{sequence.name}/frame-{frame:06d}.png"
                for frame in range(len(sequence.poses))
            ]
            noise = np.random.default_rng(list(sequence.noise_seed))
            render_frames(out, paths, scene, sequence.poses, camera, sequence.appearance, noise)
            done += len(paths)
            if progress is not None:
                progress(done, total)
            rows[sequence.split] += [
                (sequence.name, path, pose)
                for path, pose in zip(paths, sequence.poses, strict=True)
            ]
        for split, split_rows in rows.items():
            label_tables[scene.name, split] = LabelTable(
                scene=[scene.name] * len(split_rows),
                split=[split] * len(split_rows),
                seq=[r[0] for r in split_rows],
                img_path=[r[1] for r in split_rows],
                poses=np.array([r[2] for r in split_rows]),
                source=f"synthetic seed={seed}",
            )
    write_label_files(out / "labels", label_tables)


def measure_render_speed(frames: int = 200, size: int = DEFAULT_SIZE, seed: int = 0) -> float:
    """Rendering speed (frames/s) for ``frames`` poses along scene 0's route, without file I/O."""
    scene = make_scene(0, seed)
    rng = np.random.default_rng([seed, 0, 3])
    poses = _trajectory(scene, frames, 0.0, rng)
    appearance = Appearance.random(rng)
    camera = PinholeCamera(size)
    render_batch(scene, poses[:1], camera, appearance, rng)
    started = time.perf_counter()
    render_batch(scene, poses, camera, appearance, rng)
    return frames / (time.perf_counter() - started)
