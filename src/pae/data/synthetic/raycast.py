"""The synthetic benchmark's exact ray caster: face tables, a point light, 2×2 supersampling,
and each sequence's camera response (``Appearance``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pae.data.synthetic.camera import EPS_DIRECTION, PinholeCamera, pose_rotation_translation
from pae.data.synthetic.scene import SyntheticScene

SUPERSAMPLE = 2
"""Rays per pixel along each image axis (``SUPERSAMPLE²`` rays are averaged per pixel)."""
RAYS_PER_CHUNK = 1 << 17
"""Rays cast at once: bounds memory (about 100 bytes per ray) and keeps arrays cache-friendly."""


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


def _cast(
    scene: SyntheticScene, origins: np.ndarray, directions: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest hits of rays with origins ``[3, B, 1]`` inside the room and directions
    ``[3, B, R]`` (axis first): face index ``[B, R]`` (see :class:`FaceTables`) and the
    distance ``[B, R]`` along each direction, in units of its length."""
    directions = np.where(np.abs(directions) < EPS_DIRECTION, EPS_DIRECTION, directions)
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
    tables = scene.face_tables
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
