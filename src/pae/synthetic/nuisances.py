"""Nuisances of the synthetic benchmark, all off by default (``Nuisances``): what a real
camera sees beyond the scene and the pose, which no scene model explains.

- ``lighting_change`` (strength in ``[0, 1]``): between sequences a wider spread of gain, bias,
  ambient light and light position than :meth:`Appearance.random`'s; within a sequence a slow
  drift of the exposure and of the point light's intensity and position.
- ``occluder_fraction`` (share of frames in ``[0, 1]``): frames with a person-sized textured
  box standing 0.8–2.5 m in front of the camera, that no other frame sees.
- ``sensor_noise_std`` (std of values in ``[0, 1]``): Gaussian noise on top of each sequence's.
- ``motion_blur_px`` (px): each frame blurred along the image motion of the camera, over a
  random length of up to this many pixels.

:func:`sequence_nuisances` draws one sequence's: its appearance and the conditions of its
frames (:class:`FrameConditions`), from its own seed, each family from its own stream (so
turning one on leaves the others' draws unchanged).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from pae.synthetic.camera import PinholeCamera, pose_rotation_translation
from pae.synthetic.raycast import Appearance, FrameConditions, shade_rays
from pae.synthetic.scene import (
    TEXEL_SIZE_M,
    Box,
    FaceTexture,
    SyntheticScene,
    finish_texture,
    hsv_rgb,
    pattern_patch,
    texel_shape,
)
from pae.synthetic.settings import Nuisances
from pae.synthetic.trajectories import smooth_wave

OCCLUDER_SIZE_M = (0.5, 0.4, 1.7)
"""Mean width, depth and height (m) of an occluder: a person (each ±15 %)."""
OCCLUDER_DISTANCE_M = (0.8, 2.5)
"""Range of an occluder's distance (m) in front of the camera, kept 0.3 m clear of the scene
straight ahead."""
MOTION_DEPTH_M = 2.0
"""Depth (m) of the point whose image motion between frames sets a frame's blur direction."""


def _wave(rng: np.random.Generator, frames: int) -> np.ndarray:
    """Slow drift ``[frames]`` within ``[-1, 1]``: two sines, 0.3–1 and 2–3 cycles per
    sequence."""
    return smooth_wave(rng, np.arange(frames) / max(frames, 1), (0.3, 1.0), (0.8, 0.2))


def _lighting(
    rng: np.random.Generator,
    strength: float,
    scene: SyntheticScene,
    appearance: Appearance,
    frames: int,
) -> tuple[Appearance, np.ndarray, np.ndarray, np.ndarray]:
    """The sequence's appearance with ``strength`` times the extra spread (gain × e^±0.35,
    bias ±0.05, ambient ±0.2 within 0.1–0.8), its frames' exposure ``[frames]`` (× e^±0.25
    over the sequence), light positions ``[frames, 3]`` (m: moved up to ±1.5 m horizontally
    and 0.6 m down, then drifting ±0.8 m horizontally and ±0.2 m vertically, times the scene's
    scale, within the room) and light intensities ``[frames]`` (× e^±0.4)."""
    varied = dataclasses.replace(
        appearance,
        gain=appearance.gain * math.exp(strength * rng.uniform(-0.35, 0.35)),
        bias=appearance.bias + strength * rng.uniform(-0.05, 0.05),
        ambient=float(np.clip(appearance.ambient + strength * rng.uniform(-0.2, 0.2), 0.1, 0.8)),
    )
    offset = rng.uniform(-1.0, 1.0, 3) * np.array([1.5, 1.5, 0.3]) - np.array([0, 0, 0.3])
    drift = np.stack([0.8 * _wave(rng, frames), 0.8 * _wave(rng, frames), 0.2 * _wave(rng, frames)])
    light = scene.light_position + strength * scene.scale * (offset + drift.T)
    margin = 0.1 * scene.scale
    light = np.clip(light, scene.room.lo + margin, scene.room.hi - margin)
    exposure = np.exp(strength * 0.25 * _wave(rng, frames))
    intensity = np.exp(strength * 0.4 * _wave(rng, frames))
    return varied, exposure, light, intensity


def person_textures(rng: np.random.Generator, size: np.ndarray) -> tuple[FaceTexture, ...]:
    """Six face textures of a person-like box of ``size`` ``[3]`` (m): around its sides legs,
    torso (plain, striped or checked) and head, in colours of their own; its top the head's."""
    height = size[2]
    legs, torso = (
        hsv_rgb(rng.random(), rng.uniform(0.3, 0.9), rng.uniform(0.15, 0.8)) for _ in "lt"
    )
    head = hsv_rgb(rng.uniform(0.02, 0.1), rng.uniform(0.3, 0.6), rng.uniform(0.35, 0.9))
    pattern = rng.integers(3)
    textures = []
    for face in range(6):
        _, a_axis, b_axis = Box.face_axes(face)
        width_m, height_m = size[a_axis], size[b_axis]
        image = np.empty((*texel_shape(width_m, height_m), 3), dtype=np.float32)
        if b_axis != 2:  # the top and bottom faces
            image[:] = head if face == 5 else legs
        else:
            z = (np.arange(len(image)) + 0.5) * TEXEL_SIZE_M
            image[:] = np.where(
                (z < 0.47 * height)[:, None, None],
                np.float32(legs),
                np.where((z < 0.85 * height)[:, None, None], np.float32(torso), np.float32(head)),
            )
            if pattern:
                centre = np.array([width_m / 2, 0.66 * height])
                pattern_patch(rng, image, centre, width_m / 2, 0.19 * height, pattern == 1)
        textures.append(finish_texture(rng, image))
    return tuple(textures)


def occluder_distances(free: np.ndarray, scale: float) -> tuple[float, np.ndarray]:
    """The nearest distance (m) an occluder stands ahead of a camera and the farthest ``[n]``
    for cameras with ``free`` ``[n]`` metres ahead (:data:`OCCLUDER_DISTANCE_M` times the
    world's ``scale``, 0.3 × scale short of what is ahead, never nearer than the nearest), in
    float64: a float32 distance at the nearest may round below it."""
    near, far = (d * scale for d in OCCLUDER_DISTANCE_M)
    return near, np.clip(np.asarray(free, dtype=np.float64) - 0.3 * scale, near, far)


def _occluders(
    rng: np.random.Generator,
    fraction: float,
    scene: SyntheticScene,
    poses: np.ndarray,
    camera: PinholeCamera,
) -> tuple[Box | None, ...]:
    """One box or None per pose ``[n, 7]``: ``round(fraction · n)`` frames chosen at random
    get a person-sized box (:data:`OCCLUDER_SIZE_M`, facing the camera with its width)
    standing on the floor straight ahead of the camera, at a distance in
    :data:`OCCLUDER_DISTANCE_M` (less where the scene is nearer) and a lateral offset of up
    to 60 % of the half view there (times the scene's scale; its textures those of a
    person in room metres, their texels times the scale)."""
    occluders: list[Box | None] = [None] * len(poses)
    chosen = np.sort(rng.choice(len(poses), round(fraction * len(poses)), replace=False))
    if not len(chosen):
        return tuple(occluders)
    rotations, positions = pose_rotation_translation(poses[chosen])
    forward, right = rotations[:, :2, 2], rotations[:, :2, 0]
    forward = forward / np.linalg.norm(forward, axis=1, keepdims=True).clip(min=1e-9)
    right = right / np.linalg.norm(right, axis=1, keepdims=True).clip(min=1e-9)
    ahead = np.concatenate([forward, np.zeros((len(chosen), 1))], axis=1)
    _, free = shade_rays(scene, positions, ahead)
    scale = scene.scale
    near, far = occluder_distances(free, scale)
    half_view = math.tan(math.radians(camera.fov_deg) / 2)
    for frame, position, f, r, limit in zip(chosen, positions, forward, right, far, strict=True):
        distance = rng.uniform(near, limit)
        lateral = rng.uniform(-0.6, 0.6) * distance * half_view
        size = np.array(OCCLUDER_SIZE_M) * rng.uniform(0.85, 1.15, 3) * scale
        if abs(f[0]) > abs(f[1]):  # looking along x: the width along y
            size = size[[1, 0, 2]]
        # textured in room metres, its texels scaled with the world's (a person 40 times
        # larger in a street's world keeps the texels of one in a room, not 1,600 times more)
        textures = tuple(
            dataclasses.replace(texture, texel_size=texture.texel_size * scale)
            for texture in person_textures(rng, size / scale)
        )
        centre = position[:2] + distance * f + lateral * r
        lo = np.array([*(centre - size[:2] / 2), scene.room.lo[2]])
        occluders[frame] = Box(lo, lo + size, textures)
    return tuple(occluders)


def _blur(
    rng: np.random.Generator, max_px: float, poses: np.ndarray, camera: PinholeCamera
) -> tuple[np.ndarray, np.ndarray]:
    """Blur lengths ``[n]`` (px, uniform in ``[0, max_px]``) and directions ``[n]`` (rad,
    from ``+u`` towards ``+v``) of poses ``[n, 7]``: the image motion, towards the next frame
    (the last frame: from the previous one), of the point :data:`MOTION_DEPTH_M` ahead of the
    camera; a random direction where it does not move (a single frame)."""
    frames = len(poses)
    length = rng.uniform(0.0, max_px, frames)
    angle = rng.uniform(0.0, np.pi, frames)
    if frames < 2:
        return length, angle
    rotations, positions = pose_rotation_translation(poses)
    ahead = positions + MOTION_DEPTH_M * rotations[:, :, 2]
    other = np.r_[1:frames, frames - 2]
    local = np.einsum("ni,nij->nj", ahead - positions[other], rotations[other])
    motion = camera.focal_px * local[:, :2] / np.maximum(local[:, 2:], 1e-6)
    motion[-1] *= -1
    moves = np.linalg.norm(motion, axis=1) > 1e-3
    angle[moves] = np.arctan2(motion[moves, 1], motion[moves, 0])
    return length, angle


def sequence_nuisances(
    nuisances: Nuisances,
    scene: SyntheticScene,
    poses: np.ndarray,
    camera: PinholeCamera,
    appearance: Appearance,
    seed: tuple[int, ...],
) -> tuple[Appearance, FrameConditions]:
    """One sequence's nuisances: its ``appearance`` with the lighting spread and the extra
    sensor noise (combined with its own: the root of the sum of squares), and the conditions
    of its frames (poses ``[n, 7]``). ``seed`` seeds the draws (the same seed, the same
    nuisances); the lighting, occluders and blur each draw from a stream of their own."""
    lighting, occluder, blur = (np.random.default_rng([*seed, k]) for k in (1, 2, 3))
    conditions = FrameConditions.plain(scene, len(poses))
    if nuisances.lighting_change:
        appearance, exposure, light, intensity = _lighting(
            lighting, nuisances.lighting_change, scene, appearance, len(poses)
        )
        conditions = dataclasses.replace(
            conditions, exposure=exposure, light_position=light, light_intensity=intensity
        )
    if nuisances.occluder_fraction:
        conditions = dataclasses.replace(
            conditions,
            occluders=_occluders(occluder, nuisances.occluder_fraction, scene, poses, camera),
        )
    if nuisances.motion_blur_px:
        length, angle = _blur(blur, nuisances.motion_blur_px, poses, camera)
        conditions = dataclasses.replace(conditions, blur_px=length, blur_angle=angle)
    if nuisances.sensor_noise_std:
        appearance = dataclasses.replace(
            appearance, noise_std=math.hypot(appearance.noise_std, nuisances.sensor_noise_std)
        )
    return appearance, conditions
