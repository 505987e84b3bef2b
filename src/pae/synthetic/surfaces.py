"""Surfaces of real rooms that the plain benchmark lacks, all off by default
(``SurfaceOptions``): each a share of the scene's surfaces, a surface being one face of the
room (four walls, floor, ceiling) or one box or panel (all its faces).

- ``plain_surface_share``: plain-painted, one pale colour near the surface's own mean colour,
  no texture at all: only the shading of the light varies across it (white walls, bare
  floors).
- ``repeated_surface_share``: covered by a periodic pattern of period
  :data:`REPEAT_PERIOD_M`, 3–6 px of a 64 px, 65° camera 2.5 m away: stair-like steps or
  window-like panes on upright faces, tiles on level ones (stairs, rows of windows).
- ``glossy_surface_share``: glossy, with Blinn–Phong highlights of the point light and of
  :data:`LAMPS` fixed lamps under the ceiling, which move over the surface as the camera
  moves.

Plain and repeated surfaces are distinct (their shares sum to at most 1); glossy ones are
drawn on their own and may be either. :func:`dress_surfaces` redraws a scene's surfaces from
a seed of their own, so the rooms, boxes and camera routes stay those of the plain benchmark,
and a larger share keeps the surfaces of a smaller one.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from pae.synthetic.scene import Box, FaceTexture, SyntheticScene
from pae.synthetic.settings import SurfaceOptions

REPEAT_PERIOD_M = (0.15, 0.3)
"""Range (m) of a repeated surface's period."""
GLOSS_SPECULAR = (0.3, 0.7)
"""Range of a glossy surface's highlight weight (on linear colour in ``[0, 1]``)."""
GLOSS_SHININESS = (12.0, 48.0)
"""Range of a glossy surface's Blinn–Phong exponent."""
LAMPS = 2
"""Fixed lamps whose highlights glossy surfaces show, beside the point light's."""
PLAIN_VALUE = (0.6, 0.9)
"""Range of a plain surface's grey level before its own colour is mixed in (30 %)."""


def _face_grid(texture: FaceTexture) -> tuple[np.ndarray, np.ndarray]:
    """Face coordinates ``a`` ``[1, cols]`` and ``b`` ``[rows, 1]`` (m) of the texel centres."""
    rows, cols = texture.image.shape[:2]
    a = (np.arange(cols, dtype=np.float32) + 0.5) * texture.texel_size
    b = (np.arange(rows, dtype=np.float32) + 0.5) * texture.texel_size
    return a[None, :], b[:, None]


def _mean_colour(textures: tuple[FaceTexture, ...]) -> np.ndarray:
    """Mean colour ``[3]`` of ``textures`` (each face counted once)."""
    return np.mean([t.image.reshape(-1, 3).mean(0) for t in textures], axis=0)


def _plain(rng: np.random.Generator, textures: tuple[FaceTexture, ...]) -> tuple[FaceTexture, ...]:
    """The faces painted one uniform pale colour: 70 % grey of :data:`PLAIN_VALUE`, 30 % their
    mean colour."""
    paint = 0.7 * rng.uniform(*PLAIN_VALUE) + 0.3 * _mean_colour(textures)
    return tuple(
        dataclasses.replace(t, image=np.broadcast_to(paint, t.image.shape).astype(np.float32))
        for t in textures
    )


def _pattern(
    kind: str, texture: FaceTexture, period: float, aspect: float
) -> tuple[np.ndarray, np.ndarray]:
    """Periodic pattern of ``kind`` over ``texture``'s face, period ``period`` (m; windows:
    ``period × aspect`` tall): its brightness ``[rows, cols, 1]`` in ``[0.3, 1]`` and the
    mask ``[rows, cols, 1]`` of its window panes (0 for stairs and tiles)."""
    a, b = _face_grid(texture)
    rows, cols = texture.image.shape[:2]
    panes = np.zeros((rows, cols), np.float32)
    if kind == "stairs":  # a riser lit from above, a dark nosing at each step's top
        phase = np.broadcast_to((b / period) % 1.0, (rows, cols))
        shade = np.where(phase > 0.85, 0.3, 0.55 + 0.45 * phase / 0.85)
    elif kind == "windows":  # panes in frames a quarter of the period wide
        in_pane = ((a / period) % 1.0 > 0.25) & ((b / (period * aspect)) % 1.0 > 0.25)
        panes = in_pane.astype(np.float32)
        shade = np.where(in_pane, 0.45, 1.0)
    else:  # tiles: grid lines an eighth of the period wide
        joint = ((a / period) % 1.0 < 0.125) | ((b / period) % 1.0 < 0.125)
        shade = np.where(joint, 0.4, 1.0)
    return shade.astype(np.float32)[:, :, None], panes[:, :, None]


def _repeated(
    rng: np.random.Generator, textures: tuple[FaceTexture, ...], upright: tuple[bool, ...]
) -> tuple[FaceTexture, ...]:
    """The faces covered by one periodic pattern (period in :data:`REPEAT_PERIOD_M`): stairs
    or windows on ``upright`` faces, tiles on the others, in the faces' mean colour (window
    panes: a dark bluish glass), softened by 0.7 texel."""
    period = rng.uniform(*REPEAT_PERIOD_M)
    kind = "stairs" if rng.random() < 0.5 else "windows"
    aspect = rng.uniform(1.0, 1.5)
    base = _mean_colour(textures)
    base = (0.6 * base + 0.4 * base.mean()).astype(np.float32)
    glass = np.array([0.15, 0.2, 0.3], np.float32) * rng.uniform(0.7, 1.3)
    dressed = []
    for texture, vertical in zip(textures, upright, strict=True):
        shade, panes = _pattern(kind if vertical else "tiles", texture, period, aspect)
        image = shade * (base + panes * (glass - base))
        image = cv2.GaussianBlur(image, (0, 0), 0.7)
        dressed.append(dataclasses.replace(texture, image=np.clip(image, 0, 1).astype(np.float32)))
    return tuple(dressed)


def _glossy(rng: np.random.Generator, textures: tuple[FaceTexture, ...]) -> tuple[FaceTexture, ...]:
    """The faces glossy, with one highlight weight and exponent."""
    specular, shininess = rng.uniform(*GLOSS_SPECULAR), rng.uniform(*GLOSS_SHININESS)
    return tuple(dataclasses.replace(t, specular=specular, shininess=shininess) for t in textures)


def _chosen(rng: np.random.Generator, units: int, share: float, last: bool = False) -> set[int]:
    """``round(share · units)`` of ``units`` in an order drawn from ``rng``: its first ones, or
    its ``last`` ones."""
    order = rng.permutation(units)
    count = round(share * units)
    return set((order[units - count :] if last else order[:count]).tolist())


def dress_surfaces(
    scene: SyntheticScene, options: SurfaceOptions, seed: tuple[int, ...]
) -> SyntheticScene:
    """``scene`` with ``options``' share of its surfaces plain, repeated and glossy (the same
    ``seed``, the same surfaces); the scene itself when none is on. The choice of surfaces and
    each surface's draws come from streams of ``seed`` of their own."""
    if not options.active:
        return scene
    surfaces = [(scene.room, face) for face in range(6)] + [(box, None) for box in scene.boxes]
    units = len(surfaces)
    plain = _chosen(np.random.default_rng([*seed, 0]), units, options.plain_surface_share)
    repeated = _chosen(
        np.random.default_rng([*seed, 0]), units, options.repeated_surface_share, last=True
    )
    repeated -= plain
    glossy = _chosen(np.random.default_rng([*seed, 1]), units, options.glossy_surface_share)
    room_textures = list(scene.room.textures)
    boxes = []
    for unit, (box, face) in enumerate(surfaces):
        faces = range(6) if face is None else [face]
        textures = tuple(box.textures[f] for f in faces)
        upright = tuple(f < 4 for f in faces)
        if unit in plain:
            textures = _plain(np.random.default_rng([*seed, 2, unit]), textures)
        elif unit in repeated:
            textures = _repeated(np.random.default_rng([*seed, 3, unit]), textures, upright)
        if unit in glossy:
            textures = _glossy(np.random.default_rng([*seed, 4, unit]), textures)
        if face is None:
            boxes.append(Box(box.lo, box.hi, textures))
        else:
            room_textures[face] = textures[0]
    room = Box(scene.room.lo, scene.room.hi, tuple(room_textures))
    lamps = scene.lamps
    if glossy:
        rng = np.random.default_rng([*seed, 5])
        margin = scene.scale
        lo, hi = scene.room.lo + margin, scene.room.hi - margin
        xy = rng.uniform(lo[:2], hi[:2], (LAMPS, 2))
        lamps = np.column_stack([xy, np.full(LAMPS, scene.room.hi[2] - 0.3 * scene.scale)])
    return dataclasses.replace(scene, room=room, boxes=tuple(boxes), lamps=lamps)
