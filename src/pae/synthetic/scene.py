"""The synthetic benchmark's rooms: boxes and panels, each face with its procedural texture,
and the camera route through each room (``make_scene``)."""

from __future__ import annotations

import colorsys
import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from pae.synthetic.settings import SyntheticSettings

TEXEL_SIZE_M = 0.02


@dataclass(frozen=True, eq=False)
class FaceTexture:
    """Texture of one face: ``image`` ``[rows, cols, 3]`` float32 linear RGB in ``[0, 1]``.

    Row index grows with face coordinate ``b``, column index with ``a`` (see module doc).
    ``specular`` (0: matte) is the weight of the face's Blinn–Phong highlights, of exponent
    ``shininess``.
    """

    image: np.ndarray
    texel_size: float = TEXEL_SIZE_M
    specular: float = 0.0
    shininess: float = 1.0


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
    fall-off distance grows with it. ``lamps`` ``[L, 3]`` (m): more fixed lights that only
    glossy faces show, as highlights (their diffuse light is part of the ambient term)."""

    name: str
    room: Box
    boxes: tuple[Box, ...]
    light_position: np.ndarray
    route: CameraRoute | None
    scale: float = 1.0
    lamps: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))

    @functools.cached_property
    def face_tables(self) -> FaceTables:
        return FaceTables.build(self)


@dataclass(frozen=True, eq=False)
class FaceTables:
    """All face textures flattened into one ``[T, 3]`` array, with per-face lookup arrays
    ``[F]``. Face ``6·k + f`` is face ``f`` of box ``k`` (of a scene: box 0 is the room); its
    normal, facing the free space, lies along axis ``f // 2`` with sign ``normal_sign``;
    ``specular`` and ``shininess`` are its highlights' weight and exponent (all 0: matte)."""

    texels: np.ndarray
    offset: np.ndarray
    cols: np.ndarray
    rows: np.ndarray
    inv_texel: np.ndarray
    origin_a: np.ndarray
    origin_b: np.ndarray
    normal_sign: np.ndarray
    specular: np.ndarray
    shininess: np.ndarray

    @property
    def glossy(self) -> bool:
        """Whether any face has highlights."""
        return bool(np.any(self.specular > 0))

    @classmethod
    def build(cls, scene: SyntheticScene) -> FaceTables:
        """The tables of ``scene``: its room (seen from inside), then its boxes."""
        return cls.from_boxes((scene.room, *scene.boxes), room_first=True)

    @classmethod
    def from_boxes(cls, boxes: Sequence[Box], room_first: bool) -> FaceTables:
        """The tables of ``boxes``, all seen from outside but the first if ``room_first``."""
        images, offset, cols, rows, inv_texel = [], [], [], [], []
        origin_a, origin_b, normal_sign, specular, shininess = [], [], [], [], []
        start = 0
        for index, box in enumerate(boxes):
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
                normal_sign.append(-outward if room_first and index == 0 else outward)
                specular.append(texture.specular)
                shininess.append(texture.shininess)
        return cls(
            texels=np.concatenate(images),
            offset=np.asarray(offset, dtype=np.int64),
            cols=np.asarray(cols, dtype=np.int64),
            rows=np.asarray(rows, dtype=np.int64),
            inv_texel=np.asarray(inv_texel, dtype=np.float32),
            origin_a=np.asarray(origin_a, dtype=np.float32),
            origin_b=np.asarray(origin_b, dtype=np.float32),
            normal_sign=np.asarray(normal_sign, dtype=np.float32),
            specular=np.asarray(specular, dtype=np.float32),
            shininess=np.asarray(shininess, dtype=np.float32),
        )


def scene_name(index: int) -> str:
    """Name of scene ``index``: ``scene00``, ``scene01``, …"""
    return f"scene{index:02d}"


def hsv_rgb(hue: float, saturation: float, value: float) -> tuple[float, float, float]:
    return colorsys.hsv_to_rgb(hue % 1.0, float(np.clip(saturation, 0, 1)), float(value))


def texel_shape(width_m: float, height_m: float) -> tuple[int, int]:
    """``(rows, cols)`` of a texture covering ``width_m × height_m``."""
    return max(2, math.ceil(height_m / TEXEL_SIZE_M)), max(2, math.ceil(width_m / TEXEL_SIZE_M))


def _smooth_field(
    shape: tuple[int, int], cells: tuple[int, int], colours: np.ndarray
) -> np.ndarray:
    """Image ``[rows, cols, 3]`` interpolating a ``cells`` grid of ``colours`` ``[cy, cx, 3]``."""
    rows, cols = shape
    grid = np.asarray(colours, dtype=np.float32).reshape(cells[0], cells[1], 3)
    return cv2.resize(grid, (cols, rows), interpolation=cv2.INTER_CUBIC)


def _palette_field(
    rng: np.random.Generator,
    shape: tuple[int, int],
    cells: tuple[int, int],
    hue: float,
    hue_sd: float,
    saturation: tuple[float, float],
    value: tuple[float, float],
) -> np.ndarray:
    """:func:`_smooth_field` ``[rows, cols, 3]`` of a ``cells`` grid of colours around ``hue``:
    per cell (row-major) a hue ``hue + N(0, hue_sd)``, a saturation and a value uniform in
    their ``(low, high)`` ranges, drawn in that order."""
    colours = [
        hsv_rgb(hue + rng.normal(0, hue_sd), rng.uniform(*saturation), rng.uniform(*value))
        for _ in range(cells[0] * cells[1])
    ]
    return _smooth_field(shape, cells, np.array(colours))


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
        colour = hsv_rgb(rng.random(), rng.uniform(0.5, 1.0), rng.uniform(0.3, 1.0))
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
                pattern_patch(rng, image, centre_m, half_w / scale, half_h / scale, kind == 4)


def pattern_patch(
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
        hsv_rgb(rng.random(), rng.uniform(0.3, 1.0), rng.uniform(0.2, 1.0)), dtype=np.float32
    )
    patch = image[r0:r1, c0:c1]
    patch += mask[:, :, None] * (colour - patch)


def finish_texture(rng: np.random.Generator, image: np.ndarray) -> FaceTexture:
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
    shape = texel_shape(width_m, height_m)
    cells = (2, max(2, round(width_m / 1.5)))
    image = _palette_field(rng, shape, cells, hue, 0.05, (0.3, 0.8), (0.35, 0.9))
    band_lo, band_hi = sorted(rng.uniform(0.3, 1.2, 2))
    band = slice(int(band_lo / TEXEL_SIZE_M), int(band_hi / TEXEL_SIZE_M) + 2)
    image[band] = 0.5 * image[band] + 0.5 * np.float32(
        hsv_rgb(hue + 0.5, 0.6, rng.uniform(0.2, 0.8))
    )
    _draw_shapes(rng, image, 3 + int(width_m * height_m / 1.5), (0.3, 1.1))
    _draw_shapes(rng, image, int(width_m * height_m), (0.08, 0.3))
    return finish_texture(rng, image)


def _floor_texture(rng: np.random.Generator, width_m: float, depth_m: float) -> FaceTexture:
    """Tiled floor shaded by a gradient, with a few rugs."""
    rows, cols = texel_shape(width_m, depth_m)
    hue = rng.random()
    image = _palette_field(rng, (rows, cols), (3, 3), hue, 0.08, (0.2, 0.6), (0.4, 0.9))
    tile = int(rng.uniform(0.4, 0.7) / TEXEL_SIZE_M)
    jj, ii = np.meshgrid(np.arange(cols), np.arange(rows))
    checker = ((jj // tile + ii // tile) % 2).astype(np.float32)[:, :, None]
    image *= 1.0 - 0.3 * checker
    _draw_shapes(rng, image, 3 + int(width_m * depth_m / 8), (0.8, 2.0))
    return finish_texture(rng, image)


def _ceiling_texture(rng: np.random.Generator, width_m: float, depth_m: float) -> FaceTexture:
    """Pale ceiling with a grid of light panels and a few shapes."""
    rows, cols = texel_shape(width_m, depth_m)
    hue = rng.random()
    image = _palette_field(rng, (rows, cols), (2, 2), hue, 0.1, (0.05, 0.4), (0.6, 0.95))
    spacing = rng.uniform(1.2, 2.0) / TEXEL_SIZE_M
    panel = int(0.25 / TEXEL_SIZE_M)
    for r in np.arange(spacing / 2, rows, spacing):
        for c in np.arange(spacing / 2, cols, spacing):
            image[
                max(0, int(r) - panel) : int(r) + panel,
                max(0, int(c) - 2 * panel) : int(c) + 2 * panel,
            ] = 1.0
    _draw_shapes(rng, image, 2 + int(width_m * depth_m / 10), (0.3, 1.0))
    return finish_texture(rng, image)


def _box_textures(
    rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray
) -> tuple[FaceTexture, ...]:
    """Six textures of a box: one base colour, a pattern and a shape or two per face."""
    hue = rng.random()
    textures = []
    for face in range(6):
        _, a_axis, b_axis = Box.face_axes(face)
        width_m, height_m = hi[a_axis] - lo[a_axis], hi[b_axis] - lo[b_axis]
        shape = texel_shape(width_m, height_m)
        base = hsv_rgb(hue + rng.normal(0, 0.04), rng.uniform(0.4, 0.9), rng.uniform(0.3, 0.9))
        image = np.empty((*shape, 3), dtype=np.float32)
        image[:] = base
        centre = np.array([width_m, height_m]) / 2
        pattern_patch(rng, image, centre, width_m / 2, height_m / 2, bool(rng.random() < 0.5))
        image = 0.6 * image + 0.4 * np.float32(base)
        _draw_shapes(rng, image, 1 + int(width_m * height_m), (0.15, 0.5))
        textures.append(finish_texture(rng, image))
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
    test_offset_m: float = SyntheticSettings.test_offset_m,
    train_lane_m: float = SyntheticSettings.train_lane_m,
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
