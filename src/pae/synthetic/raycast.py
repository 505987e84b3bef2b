"""The synthetic benchmark's exact ray caster: face tables, a point light, 2×2 supersampling,
highlights of glossy faces, each sequence's camera response (``Appearance``: gain, tint,
gamma, noise and, optionally, vignetting, auto-exposure and JPEG compression) and,
optionally, each frame's nuisances (``FrameConditions``: exposure, white balance, light, an
occluder, motion blur)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from pae.synthetic.camera import EPS_DIRECTION, PinholeCamera, pose_rotation_translation
from pae.synthetic.scene import Box, FaceTables, SyntheticScene

SUPERSAMPLE = 2
"""Rays per pixel along each image axis (``SUPERSAMPLE²`` rays are averaged per pixel)."""
RAYS_PER_CHUNK = 1 << 17
"""Rays cast at once: bounds memory (about 100 bytes per ray) and keeps arrays cache-friendly."""
AUTO_EXPOSURE_TARGET = 0.4
"""Mean linear level (values in ``[0, 1]``) the auto-exposure brings each frame towards."""
AUTO_EXPOSURE_RANGE = (0.25, 4.0)
"""Range of the auto-exposure's factor on a frame's gain."""


@dataclass(frozen=True)
class Appearance:
    """Lighting and camera response of one sequence.

    The shaded linear colour ``c`` becomes ``clip(c·tint·gain + bias)^gamma + noise``;
    ``ambient`` is the share of light not coming from the scene's point light. Off by
    default (0): ``vignetting``, the share of light lost at the image corners (``1 −
    vignetting·r²``, ``r`` the distance from the image centre, 1 at the corners);
    ``metering``, the auto-exposure's strength: each frame's gain times ``(target / level)^
    metering`` (its mean linear level after the sequence's gain and tint and the vignetting,
    before the frame's own exposure and white balance, which come on top as the
    auto-exposure's wander; :data:`AUTO_EXPOSURE_TARGET`, within
    :data:`AUTO_EXPOSURE_RANGE`); ``jpeg_quality`` (1–100), each image compressed as
    JPEG (OpenCV, 4:2:0 chroma) and decoded again.
    """

    gain: float = 1.0
    bias: float = 0.0
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)
    gamma: float = 1.0
    noise_std: float = 0.0
    ambient: float = 0.45
    vignetting: float = 0.0
    metering: float = 0.0
    jpeg_quality: int = 0

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


@dataclass(frozen=True, eq=False)
class FrameConditions:
    """What changes from frame to frame of a sequence besides the pose, for ``n`` frames (drawn
    by :func:`pae.synthetic.nuisances.sequence_nuisances`).

    - ``exposure`` ``[n]``: factor on the sequence's ``Appearance.gain`` (1: none).
    - ``white_balance`` ``[n, 3]``: factor on each colour channel (1: none).
    - ``light_position`` ``[n, 3]`` (m): the point light of each frame.
    - ``light_intensity`` ``[n]``: factor on the point light's direct term (1: the scene's).
    - ``occluders``: ``n`` boxes or None: a box standing in front of the camera that is no part
      of the scene (no other frame sees it), ray cast together with the scene.
    - ``blur_px`` ``[n]``: length (px) of each frame's linear motion blur (0: none), along
      ``blur_angle`` ``[n]`` (rad, from the image's ``+u`` axis towards ``+v``).
    """

    exposure: np.ndarray
    light_position: np.ndarray
    light_intensity: np.ndarray
    occluders: tuple[Box | None, ...]
    blur_px: np.ndarray
    blur_angle: np.ndarray
    white_balance: np.ndarray

    @classmethod
    def plain(cls, scene: SyntheticScene, frames: int) -> FrameConditions:
        """``frames`` frames without nuisances: the scene's light, no occluder, no blur."""
        return cls(
            exposure=np.ones(frames),
            light_position=np.tile(scene.light_position, (frames, 1)),
            light_intensity=np.ones(frames),
            occluders=(None,) * frames,
            blur_px=np.zeros(frames),
            blur_angle=np.zeros(frames),
            white_balance=np.ones((frames, 3)),
        )

    def __len__(self) -> int:
        return len(self.exposure)

    def __getitem__(self, frames: slice) -> FrameConditions:
        """The conditions of the frames ``frames`` selects."""
        return FrameConditions(
            self.exposure[frames],
            self.light_position[frames],
            self.light_intensity[frames],
            self.occluders[frames],
            self.blur_px[frames],
            self.blur_angle[frames],
            self.white_balance[frames],
        )


def motion_kernel(length_px: float, angle_rad: float) -> np.ndarray:
    """Linear motion-blur kernel ``[k, k]`` float32 summing to 1 (``k`` odd): the average
    along a segment of ``length_px`` pixels through the kernel's centre, at ``angle_rad`` from
    ``+u`` towards ``+v``, splatted bilinearly (so sub-pixel lengths blur a little)."""
    half = math.ceil(length_px / 2) + 1
    steps = max(2, math.ceil(4 * length_px) + 1)
    along = np.linspace(-length_px / 2, length_px / 2, steps)
    u = half + along * math.cos(angle_rad)
    v = half + along * math.sin(angle_rad)
    u0, v0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    fu, fv = u - u0, v - v0
    kernel = np.zeros((2 * half + 1, 2 * half + 1))
    for du, dv, weight in (
        (0, 0, (1 - fu) * (1 - fv)),
        (1, 0, fu * (1 - fv)),
        (0, 1, (1 - fu) * fv),
        (1, 1, fu * fv),
    ):
        np.add.at(kernel, (v0 + dv, u0 + du), weight)
    return (kernel / kernel.sum()).astype(np.float32)


def _enter_box(
    origins: np.ndarray,
    inverse: np.ndarray,
    positive: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    t_best: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays (origins ``[3, B, 1]``, inverse directions ``[3, B, R]``, ``positive`` their signs)
    that enter the box ``lo..hi`` (each ``[3]``, or ``[3, B, 1]`` per frame) in front of them and
    before ``t_best`` ``[B, R]``: the mask ``[B, R]``, their entry distances ``[M]`` and the
    box's face ``[M]`` (0–5) they enter through."""
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
        return hit, t_near[hit], np.zeros(0, dtype=np.int64)
    t_hit = t_near[hit]
    axis = np.where(near[0][hit] == t_hit, 0, np.where(near[1][hit] == t_hit, 1, 2))
    entered_hi = ~positive[:, hit][axis, np.arange(len(axis))]
    return hit, t_hit, 2 * axis + entered_hi


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
        hit, t_hit, box_face = _enter_box(origins, inverse, positive, lo, hi, t_best)
        if not len(t_hit):
            continue
        t_best[hit] = t_hit
        face[hit] = 6 * index + box_face
    return face, t_best


def _lit_texture(
    tables: FaceTables,
    face: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    z: np.ndarray,
    light: np.ndarray | Sequence[np.ndarray],
    intensity: np.ndarray | None,
    ambient: float,
    scale: float,
) -> np.ndarray:
    """Linear colours ``[..., 3]`` float32 of surface points ``x, y, z`` (m, each ``[...]``) on
    faces ``face`` ``[...]`` of ``tables``: the bilinearly sampled texture × (ambient + the
    point light at ``light`` (``[3]``, or 3 arrays broadcasting to ``[...]``) times
    ``intensity`` (None: 1), its fall-off distance growing with ``scale``)."""
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

    to_light = (light[0] - x, light[1] - y, light[2] - z)
    distance_sq = to_light[0] ** 2 + to_light[1] ** 2 + to_light[2] ** 2
    along_normal = np.where(
        normal_axis == 0, to_light[0], np.where(normal_axis == 1, to_light[1], to_light[2])
    )
    cosine = along_normal * tables.normal_sign[face] / np.sqrt(distance_sq)
    direct = np.maximum(cosine, 0.0) * 2.2 / (1.0 + distance_sq / (6.0 * scale**2))
    if intensity is not None:
        direct = direct * intensity
    return colour * (ambient + (1.0 - ambient) * direct)[..., None]


def _highlights(
    tables: FaceTables,
    face: np.ndarray,
    points: Sequence[np.ndarray],
    directions: Sequence[np.ndarray],
    lights: Sequence[tuple[np.ndarray | Sequence[np.ndarray], np.ndarray | None]],
    scale: float,
) -> np.ndarray:
    """Blinn–Phong highlights ``[...]`` float32 (white, on linear colour) at surface points
    (3 arrays ``[...]``, m) on faces ``face`` ``[...]`` seen along ray ``directions`` (3 arrays
    broadcasting to ``[...]``): per light ``(position, intensity)`` (as in :func:`_lit_texture`)
    the face's ``specular · (n·h)^shininess`` where it faces the light, with the diffuse
    term's fall-off; 0 on matte faces."""
    highlight = np.zeros(face.shape, np.float32)
    glossy = tables.specular[face] > 0
    if not glossy.any():
        return highlight
    hit_face = face[glossy]
    point = [np.broadcast_to(c, face.shape)[glossy] for c in points]
    view = [-np.broadcast_to(c, face.shape)[glossy] for c in directions]
    view_length = np.sqrt(view[0] ** 2 + view[1] ** 2 + view[2] ** 2)
    view = [c / view_length for c in view]
    axis = (hit_face % 6) // 2
    sign = tables.normal_sign[hit_face]
    shininess = tables.shininess[hit_face]
    total = np.zeros(len(hit_face), np.float32)
    for position, intensity in lights:
        to_light = [np.broadcast_to(position[k], face.shape)[glossy] - point[k] for k in range(3)]
        distance_sq = to_light[0] ** 2 + to_light[1] ** 2 + to_light[2] ** 2
        distance = np.sqrt(distance_sq)
        half = [to_light[k] / distance + view[k] for k in range(3)]
        half_length = np.sqrt(half[0] ** 2 + half[1] ** 2 + half[2] ** 2).clip(min=1e-9)
        facing = np.choose(axis, to_light) * sign > 0
        cosine = np.maximum(np.choose(axis, half) * sign / half_length, 0.0)
        lobe = (
            np.where(facing, cosine**shininess, 0.0) * 2.2 / (1.0 + distance_sq / (6.0 * scale**2))
        )
        if intensity is not None:
            lobe = lobe * np.broadcast_to(intensity, face.shape)[glossy]
        total += lobe.astype(np.float32)
    highlight[glossy] = tables.specular[hit_face] * total
    return highlight


def _shade(
    scene: SyntheticScene,
    origins: np.ndarray,
    directions: np.ndarray,
    ambient: float,
    light: np.ndarray | None = None,
    intensity: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Linear colours ``[B, R, 3]`` float32 of rays (origins ``[3, B, 1]``, directions
    ``[3, B, R]``): bilinearly sampled texture × (ambient + point light), and the distance
    ``[B, R]`` to the hit along each direction (in units of its length). ``light``
    ``[3, B, 1]`` (m) and ``intensity`` ``[B, 1]`` give each frame its own point light (None:
    the scene's)."""
    face, t = _cast(scene, origins, directions)
    x, y, z = (origins[k] + t * directions[k] for k in range(3))
    if light is None:
        light = scene.light_position.astype(np.float32)
    tables = scene.face_tables
    colour = _lit_texture(tables, face, x, y, z, light, intensity, ambient, scene.scale)
    if tables.glossy:
        lights = [(light, intensity), *((lamp, None) for lamp in scene.lamps)]
        shine = _highlights(tables, face, (x, y, z), directions, lights, scene.scale)
        colour += shine[..., None]
    return colour, t


def _shade_occluders(
    scene: SyntheticScene,
    origins: np.ndarray,
    directions: np.ndarray,
    ambient: float,
    frames: FrameConditions,
    colour: np.ndarray,
    t_scene: np.ndarray,
) -> np.ndarray:
    """Paint each frame's occluder into ``colour`` ``[B, R, 3]`` (in place) where it lies
    nearer than the scene (hit distances ``t_scene`` ``[B, R]``; rays as in :func:`_shade`,
    lit by the frames' lights): -> the share ``[B]`` of each frame's rays it covers."""
    share = np.zeros(len(frames))
    rows = np.array([i for i, box in enumerate(frames.occluders) if box is not None], dtype=int)
    if not len(rows):
        return share
    boxes = [frames.occluders[i] for i in rows]
    lo = np.stack([box.lo for box in boxes], axis=1)[:, :, None].astype(np.float32)
    hi = np.stack([box.hi for box in boxes], axis=1)[:, :, None].astype(np.float32)
    origins, directions = origins[:, rows], directions[:, rows]
    safe = np.where(np.abs(directions) < EPS_DIRECTION, EPS_DIRECTION, directions)
    hit, t_hit, box_face = _enter_box(origins, 1.0 / safe, safe > 0, lo, hi, t_scene[rows])
    if not len(t_hit):
        return share
    slot = np.broadcast_to(np.arange(len(rows))[:, None], hit.shape)[hit]
    x, y, z = (
        np.broadcast_to(origins[k], hit.shape)[hit] + t_hit * directions[k][hit] for k in range(3)
    )
    light = frames.light_position[rows].T[:, :, None].astype(np.float32)
    light_hit = [np.broadcast_to(light[k], hit.shape)[hit] for k in range(3)]
    intensity = frames.light_intensity[rows][:, None].astype(np.float32)
    painted = _lit_texture(
        FaceTables.from_boxes(boxes, room_first=False),
        6 * slot + box_face,
        x,
        y,
        z,
        light_hit,
        np.broadcast_to(intensity, hit.shape)[hit],
        ambient,
        scene.scale,
    )
    selected = colour[rows]
    selected[hit] = painted
    colour[rows] = selected
    share[rows] = hit.mean(axis=1)
    return share


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


def vignette(size: int, strength: float) -> np.ndarray:
    """Vignetting factor ``[size, size]`` float32: ``1 − strength·r²``, ``r`` the distance of
    each pixel centre from the image centre, 1 at the corner pixels' centres."""
    centre = (size - 1) / 2
    offset = (np.arange(size) - centre) / max(centre, 0.5)
    radius_sq = (offset[None, :] ** 2 + offset[:, None] ** 2) / 2
    return (1.0 - strength * radius_sq).astype(np.float32)


def jpeg_roundtrip(image: np.ndarray, quality: int) -> np.ndarray:
    """RGB image ``[H, W, 3]`` uint8 compressed as JPEG at ``quality`` (1–100) and decoded."""
    bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    ok, encoded = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise OSError("could not encode an image as JPEG")
    return cv2.cvtColor(cv2.imdecode(encoded, cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def render_batch(
    scene: SyntheticScene,
    poses: np.ndarray,
    camera: PinholeCamera,
    appearance: Appearance | None = None,
    rng: np.random.Generator | None = None,
    supersample: int = SUPERSAMPLE,
    conditions: FrameConditions | None = None,
    occluded: np.ndarray | None = None,
    exposed: np.ndarray | None = None,
) -> np.ndarray:
    """Images ``[B, H, W, 3]`` uint8 RGB of ``scene`` from camera-to-world ``poses`` ``[B, 7]``.

    ``rng`` draws the sensor noise (``appearance.noise_std``); ``None`` renders without noise.
    ``conditions`` (``B`` frames) gives each frame its own point light, an occluder ray cast
    with the scene, its motion blur (applied to the linear colour, before the camera response)
    and its exposure (a factor on the gain); without them the frames share the appearance's
    light. ``occluded`` ``[B]``, when given, receives the share (in ``[0, 1]``) of each image
    that its occluder covers (0 without ``conditions``); ``exposed`` ``[B]`` each frame's total
    gain (the appearance's gain × its exposure × its auto-exposure).
    """
    appearance = appearance or Appearance()
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 7)
    if conditions is not None and len(conditions) != len(poses):
        raise ValueError(f"conditions for {len(conditions)} frames, {len(poses)} poses")
    rotations, positions = pose_rotation_translation(poses)
    local = camera.ray_directions(supersample).reshape(-1, 3)
    size = camera.size
    frames_per_chunk = max(1, RAYS_PER_CHUNK // len(local))
    images = np.empty((len(poses), size, size, 3), dtype=np.uint8)
    shares = np.zeros(len(poses)) if occluded is None else occluded
    shares[:] = 0.0
    gains = np.zeros(len(poses)) if exposed is None else exposed
    shading = vignette(size, appearance.vignetting) if appearance.vignetting else None
    tint = np.asarray(appearance.tint, dtype=np.float32) * np.float32(appearance.gain)
    for start in range(0, len(poses), frames_per_chunk):
        stop = min(start + frames_per_chunk, len(poses))
        directions = np.einsum("bij,nj->ibn", rotations[start:stop], local).astype(np.float32)
        origins = positions[start:stop].T[:, :, None].astype(np.float32)
        if conditions is None:
            colour, _ = _shade(scene, origins, directions, appearance.ambient)
            gain = tint
            frame_gain = np.ones(stop - start)
        else:
            frames = conditions[start:stop]
            light = frames.light_position.T[:, :, None].astype(np.float32)
            intensity = frames.light_intensity[:, None].astype(np.float32)
            colour, t = _shade(scene, origins, directions, appearance.ambient, light, intensity)
            shares[start:stop] = _shade_occluders(
                scene, origins, directions, appearance.ambient, frames, colour, t
            )
            frame_gain = frames.exposure.copy()
            exposure = frames.exposure.astype(np.float32)[:, None, None, None]
            white_balance = frames.white_balance.astype(np.float32)[:, None, None, :]
            gain = tint * exposure * white_balance
        colour = colour.reshape(stop - start, supersample * supersample, size, size, 3).mean(1)
        if conditions is not None:
            for frame in np.flatnonzero(frames.blur_px > 0):
                kernel = motion_kernel(frames.blur_px[frame], frames.blur_angle[frame])
                colour[frame] = cv2.filter2D(
                    colour[frame], -1, kernel, borderType=cv2.BORDER_REFLECT
                )
        if appearance.metering:
            measured = colour * tint
            if shading is not None:
                measured *= shading[:, :, None]
            level = np.maximum(measured.mean(axis=(1, 2, 3)), 1e-4)
            metered = np.clip(
                (AUTO_EXPOSURE_TARGET / level) ** appearance.metering, *AUTO_EXPOSURE_RANGE
            )
        colour = colour * gain
        if shading is not None:
            colour *= shading[:, :, None]
        if appearance.metering:
            colour *= metered.astype(np.float32)[:, None, None, None]
            frame_gain *= metered
        gains[start:stop] = appearance.gain * frame_gain
        colour = np.clip(colour + np.float32(appearance.bias), 0.0, 1.0)
        colour **= np.float32(appearance.gamma)
        if rng is not None and appearance.noise_std > 0:
            colour += np.float32(appearance.noise_std) * rng.standard_normal(
                colour.shape, dtype=np.float32
            )
        images[start:stop] = np.clip(np.rint(colour * 255.0), 0, 255).astype(np.uint8)
        if appearance.jpeg_quality:
            for frame in range(start, stop):
                images[frame] = jpeg_roundtrip(images[frame], appearance.jpeg_quality)
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
