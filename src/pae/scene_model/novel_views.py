"""Novel views for training a teacher: images a scene model renders at poses sampled around
the train cameras, mixed into the teacher's train batches.

Every pose is drawn from the train split alone (its poses, sequences and intrinsics): a train
camera, moved a random share of the way towards the nearest camera of another train sequence
of its scene (between the lanes where no image was taken), then jittered in position and
orientation (``pae.core.pose_sampling.perturb_poses``). Each view is rendered with the appearance
(``SceneModel.with_appearance``) of the train camera nearest to it, so that it looks like a
photograph taken there. Validation and test rows are never read.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor
from torch.utils.data import DataLoader, Dataset

from pae.core import streams
from pae.core.camera import resized_size, scale_intrinsics
from pae.core.geometry import canonicalize_quaternion
from pae.core.pose_sampling import perturb_poses
from pae.data.datamodule import PoseDataModule
from pae.data.order import trainer_epoch
from pae.scene_model.base import SceneModel

CHUNK_ROWS = 1024
"""Cameras compared at a time in the nearest-camera searches (memory: CHUNK_ROWS × N)."""
RENDER_VIEWS = 64
"""Views rendered in one call of the scene model."""


class NovelPoses(NamedTuple):
    """Sampled cameras: poses [M, 7] (camera-to-world, unit q, qw >= 0), scene ids [M], the
    train row each was drawn from [M] (its intrinsics are the view's) and the train row
    nearest to it [M] (its appearance is the view's)."""

    poses: Tensor
    scenes: Tensor
    source: Tensor
    nearest: Tensor


def _nearest_rows(
    points: Tensor, scenes: Tensor, positions: Tensor, camera_scenes: Tensor, exclude: Tensor
) -> Tensor:
    """For points [M, 3] of scene ids [M]: the row [M] of the nearest camera among
    ``positions`` [N, 3] of the same scene whose key in ``exclude`` [M, N] is False
    (-1 where every one is excluded)."""
    distances = torch.cdist(points.double(), positions.double())
    other_scene = scenes[:, None] != camera_scenes[None, :]
    distances = distances.masked_fill(other_scene | exclude, float("inf"))
    best = distances.min(1)
    return torch.where(best.values.isfinite(), best.indices, -1)


def nearest_train_rows(
    points: Tensor, scenes: Tensor, positions: Tensor, camera_scenes: Tensor
) -> Tensor:
    """The nearest train camera [M] (a row of ``positions`` [N, 3], scene ids ``camera_scenes``
    [N]) of the same scene to each of points [M, 3] of scenes [M]."""
    rows = []
    for chunk in torch.arange(len(points)).split(CHUNK_ROWS):
        none = torch.zeros(len(chunk), len(positions), dtype=torch.bool)
        rows.append(_nearest_rows(points[chunk], scenes[chunk], positions, camera_scenes, none))
    return torch.cat(rows) if rows else torch.zeros(0, dtype=torch.long)


def other_sequence_neighbours(positions: Tensor, scenes: Tensor, sequences: Tensor) -> Tensor:
    """For each train camera (positions [N, 3], scene ids [N], sequence ids [N]) the row [N]
    of the nearest camera of its scene in another sequence; its own row where its scene has
    a single sequence."""
    rows = []
    for chunk in torch.arange(len(positions)).split(CHUNK_ROWS):
        same = sequences[chunk][:, None] == sequences[None, :]
        found = _nearest_rows(positions[chunk], scenes[chunk], positions, scenes, same)
        rows.append(torch.where(found >= 0, found, chunk))
    return torch.cat(rows) if rows else torch.zeros(0, dtype=torch.long)


def partners_within(
    rows: Tensor,
    poses: Tensor,
    scenes: Tensor,
    sequences: Tensor,
    radius_m: float,
    max_turn_deg: float,
    generator: torch.Generator,
) -> Tensor:
    """For each train camera of ``rows`` [M] (rows of poses [N, 7], scene ids [N], sequence
    ids [N]) a camera [M] drawn uniformly among those of its scene and another sequence within
    ``radius_m`` (m) of it whose orientation differs from its own by at most ``max_turn_deg``;
    the nearest of another sequence where none does (its own row where its scene has a single
    sequence)."""
    positions, rotations = poses[:, :3].double(), poses[:, 3:].double()
    cos_half = math.cos(math.radians(max_turn_deg) / 2)
    partners = []
    for chunk in rows.split(CHUNK_ROWS):
        distances = torch.cdist(positions[chunk], positions)
        other = (scenes[chunk][:, None] == scenes[None, :]) & (
            sequences[chunk][:, None] != sequences[None, :]
        )
        closest = distances.masked_fill(~other, float("inf")).min(1)
        nearest = torch.where(closest.values.isfinite(), closest.indices, chunk)
        alignment = rotations[chunk] @ rotations.T
        allowed = other & (distances <= radius_m) & (alignment.abs() >= cos_half)
        found = allowed.any(1)
        weights = torch.where(found[:, None], allowed.double(), 1.0)
        drawn = torch.multinomial(weights, 1, generator=generator).squeeze(1)
        partners.append(torch.where(found, drawn, nearest))
    return torch.cat(partners) if partners else torch.zeros(0, dtype=torch.long)


@dataclass(frozen=True)
class NovelViewSettings:
    """``teacher.novel_views``: views the scene model renders at poses sampled around the
    train cameras, mixed into each train batch (their one home of defaults; the config
    schema reads them from this source)."""

    ratio: float = 0.5
    """Rendered images per real one in each train batch (0.5: batches of 32 real + 16
    rendered)."""
    views: float = 1.0
    """Rendered views per train image in the pool the batches draw from."""
    position_jitter_m: float = 0.1
    """Each view moved by a distance uniform in [0, 2 × this] (m) ..."""
    orientation_jitter_deg: float = 3.0
    """... and turned by a rotation uniform in [0, 2 × this] (deg)."""
    between: bool = True
    """Each view: a train camera first moved a share of the way (``between_share``) towards
    a camera of another train sequence of its scene: the nearest one (``between_radius_m``
    None) or one drawn among those within ``between_radius_m`` (m) whose orientation differs
    from its own by at most ``between_max_turn_deg``."""
    between_radius_m: float | None = None
    between_max_turn_deg: float = 180.0
    between_share: tuple[float, float] = (0.0, 1.0)
    """The range [lo, hi] the share of the way is drawn from ([0.4, 0.6]: about midway)."""
    between_orientation: str = "interpolated"
    """The view's orientation: ``interpolated`` between the two cameras' likewise, or
    ``either``: that of one of the two, drawn at random (interpolating two orientations
    shrinks their spread)."""
    min_distance_m: float = 0.0
    """Views only where no train image was taken: at least this far (m) from every train
    camera of their scene (candidates drawn until enough are; 0: anywhere)."""
    size: int | None = None
    """The rendered images' shorter edge (px), resized to the train images' (None: theirs)."""
    cache: bool = True
    """The pool rendered once, before the first epoch; false: afresh every epoch."""


MAX_DRAWS = 16
"""Rounds of candidate cameras drawn to find views ``min_distance_m`` from the train cameras."""


class _TrainCameras(NamedTuple):
    """The train cameras the views are drawn around: poses [N, 7] (float64), scene and
    sequence ids [N], and each one's nearest camera of another sequence [N] (the partner
    when ``between_radius_m`` is None; else None)."""

    poses: Tensor
    scenes: Tensor
    sequences: Tensor
    neighbours: Tensor | None


def _draw_cameras(
    train: _TrainCameras, count: int, settings: NovelViewSettings, generator: torch.Generator
) -> NovelPoses:
    """``count`` candidate cameras of :func:`sample_novel_poses`, wherever they fall."""
    poses, scenes, sequences, neighbours = train
    source = torch.randint(len(poses), (count,), generator=generator)
    start = poses[source]
    if settings.between:
        if neighbours is not None:
            partner_rows = neighbours[source]
        else:
            partner_rows = partners_within(
                source,
                poses,
                scenes,
                sequences,
                settings.between_radius_m,
                settings.between_max_turn_deg,
                generator,
            )
        partner = poses[partner_rows]
        low, high = settings.between_share
        share = low + (high - low) * torch.rand(count, 1, generator=generator, dtype=torch.float64)
        position = start[:, :3] + share * (partner[:, :3] - start[:, :3])
        q0, q1 = start[:, 3:], partner[:, 3:]
        if settings.between_orientation == "either":
            either = torch.rand(count, 1, generator=generator, dtype=torch.float64) < 0.5
            rotation = torch.where(either, q1, q0)
        else:
            q1 = torch.where((q0 * q1).sum(-1, keepdim=True) < 0, -q1, q1)  # the shorter arc
            rotation = canonicalize_quaternion(q0 + share * (q1 - q0))
        start = torch.cat([position, rotation], -1)
    moved = perturb_poses(
        start, settings.position_jitter_m, settings.orientation_jitter_deg, generator
    )
    nearest = nearest_train_rows(moved[:, :3], scenes[source], poses[:, :3], scenes)
    return NovelPoses(moved, scenes[source], source, nearest)


def sample_novel_poses(
    poses: Tensor,
    scenes: Tensor,
    sequences: Tensor,
    count: int,
    settings: NovelViewSettings,
    generator: torch.Generator,
) -> NovelPoses:
    """``count`` cameras around the train cameras poses [N, 7] (scene ids [N], sequence ids
    [N]): each from a train camera drawn uniformly, moved a share of the way towards a camera
    of another sequence of its scene, uniform in ``between_share`` (``settings.between``):
    the nearest one, or with ``between_radius_m`` one drawn among those within that many
    metres turned at most ``between_max_turn_deg`` from it (:func:`partners_within`); its
    orientation interpolated likewise, or with ``between_orientation`` "either" that of one
    of the two cameras drawn at random (interpolating two orientations shrinks their
    spread); then by a distance uniform in [0, 2·``position_jitter_m``] (m) in a random
    direction and a rotation uniform in [0, 2·``orientation_jitter_deg``] about a random
    axis. With ``min_distance_m`` only cameras at least that far from every train
    camera of their scene are kept (drawn in up to ``MAX_DRAWS`` rounds; the farthest of the
    others fill what is still missing)."""
    poses = poses.double()
    neighbours = None
    if settings.between and settings.between_radius_m is None:
        neighbours = other_sequence_neighbours(poses[:, :3], scenes, sequences)
    train = _TrainCameras(poses, scenes, sequences, neighbours)
    rounds: list[NovelPoses] = []
    clearances: list[Tensor] = []
    found = 0
    for _ in range(MAX_DRAWS if settings.min_distance_m > 0 else 1):
        drawn = _draw_cameras(train, count, settings, generator)
        rounds.append(drawn)
        clearances.append((drawn.poses[:, :3] - poses[drawn.nearest, :3]).norm(dim=-1))
        found += int((clearances[-1] >= settings.min_distance_m).sum())
        if found >= count:
            break
    drawn = NovelPoses(*(torch.cat(fields) for fields in zip(*rounds, strict=True)))
    clear = torch.cat(clearances)
    far = clear >= settings.min_distance_m
    near = torch.nonzero(~far).squeeze(1)
    order = torch.cat([torch.nonzero(far).squeeze(1), near[clear[near].argsort(descending=True)]])
    picked = order[:count]
    return NovelPoses(
        drawn.poses[picked].float(),
        drawn.scenes[picked],
        drawn.source[picked],
        drawn.nearest[picked],
    )


@torch.no_grad()
def render_views(
    scene_model: SceneModel,
    cameras: NovelPoses,
    intrinsics: Tensor,
    appearance: Tensor,
    image_hw: tuple[int, int],
    size: int | None = None,
) -> Tensor:
    """The scene model's views of ``cameras`` -> uint8 [M, 3, H, W] (``image_hw``: the train
    images' size), each with the intrinsics [N, 4] (px of ``image_hw`` images) of its source
    train row and the appearance id [N] of its nearest train row, rendered ``RENDER_VIEWS``
    at a time at ``size`` px shorter edge (None: ``image_hw``) and resized to ``image_hw``."""
    height, width = image_hw
    render_w, render_h = (width, height) if size is None else resized_size(width, height, size)
    scaled = scale_intrinsics(intrinsics.double(), render_w / width, render_h / height).float()
    out = torch.empty(len(cameras.poses), 3, height, width, dtype=torch.uint8)
    for rows in torch.arange(len(cameras.poses)).split(RENDER_VIEWS):
        rendering = scene_model.render(
            cameras.poses[rows],
            cameras.scenes[rows],
            scaled[cameras.source[rows]],
            render_w,
            render_h,
        )
        looks = appearance[cameras.nearest[rows]].repeat_interleave(render_h * render_w)
        rgb = rendering.rgb.permute(0, 2, 3, 1).reshape(-1, 3)
        rgb = scene_model.with_appearance(rgb, looks).view(len(rows), render_h, render_w, 3)
        rgb = rgb.permute(0, 3, 1, 2)
        if (render_h, render_w) != (height, width):
            rgb = F.interpolate(rgb, size=(height, width), mode="bilinear", align_corners=False)
        out[rows] = (rgb.clamp(0, 1) * 255).round().to(torch.uint8)
    return out


class NovelViewPool:
    """The rendered views of one epoch: sampled from the train split of a data module and
    rendered by ``scene_model`` (frozen, on the CPU), drawn from (``seed``, epoch) alone; with
    ``settings.cache`` the views of epoch 0 serve every epoch. ``render_s``: the seconds spent
    rendering so far."""

    def __init__(
        self,
        data: PoseDataModule,
        scene_model: SceneModel,
        settings: NovelViewSettings,
        appearance_per: str,
        seed: int,
    ) -> None:
        dataset = data.datasets["train"]
        self.poses, self.scenes = data.train_poses()
        self.sequences, _ = data.appearance_ids("train", "sequence")
        self.appearance, _ = data.appearance_ids("train", appearance_per)
        self.intrinsics = data.intrinsics("train", crop=False)
        self.image_hw = tuple(dataset.__getitems__([0])["image"].shape[-2:])
        self.scene_model = scene_model.eval().requires_grad_(False)
        self.settings = settings
        self.seed = seed
        self.count = max(1, round(settings.views * len(dataset)))
        self.render_s = 0.0
        self._views: tuple[int, dict[str, Tensor]] | None = None

    def cameras(self, epoch: int) -> NovelPoses:
        """The cameras of ``epoch``'s views (of epoch 0 with ``cache``)."""
        return sample_novel_poses(
            self.poses,
            self.scenes,
            self.sequences,
            self.count,
            self.settings,
            streams.generator(self.seed, "novel_views", 0 if self.settings.cache else epoch),
        )

    def views(self, epoch: int) -> dict[str, Tensor]:
        """``{"image": uint8 [M, 3, H, W], "pose": [M, 7], "scene": [M]}`` of ``epoch``."""
        number = 0 if self.settings.cache else epoch
        if self._views is None or self._views[0] != number:
            started = time.perf_counter()
            cameras = self.cameras(number)
            images = render_views(
                self.scene_model,
                cameras,
                self.intrinsics,
                self.appearance,
                self.image_hw,
                self.settings.size,
            )
            self._views = (
                number,
                {"image": images, "pose": cameras.poses, "scene": cameras.scenes},
            )
            self.render_s += time.perf_counter() - started
        return self._views[1]


class NovelViewBatches(Dataset):
    """The train batches of an epoch: every train image once in ``batch_size`` batches (the
    last partial one dropped; scenes drawn equally often with ``balance_scenes``), each
    followed by round(``ratio`` × ``batch_size``) views drawn from the epoch's pool. Item
    ``i`` is batch ``i`` of the epoch under way (``epoch``), drawn from (``seed``, epoch)
    alone: ``{"image": uint8 [B', 3, H, W], "pose": [B', 7], "scene": [B'], "index": [B']}``,
    ``index`` -1 for rendered views."""

    def __init__(
        self,
        data: PoseDataModule,
        pool: NovelViewPool,
        ratio: float,
        seed: int,
        epoch: Callable[[], int],
    ) -> None:
        super().__init__()
        self.dataset = data.datasets["train"]
        self.batch_size = data.batch_size
        self.balance = data.balance_scenes and data.n_scenes > 1
        self.extra = max(1, round(ratio * self.batch_size))
        self.pool = pool
        self.seed = seed
        self.epoch = epoch
        self._draws: tuple[int, Tensor, Tensor] | None = None

    def __len__(self) -> int:
        return len(self.dataset) // self.batch_size

    def draws(self, epoch: int) -> tuple[Tensor, Tensor]:
        """The epoch's train rows in batch order [len × batch_size] and pool picks [len, extra]."""
        if self._draws is None or self._draws[0] != epoch:
            draws = streams.generator(self.seed, "novel_view_batches", epoch)
            n = len(self.dataset)
            if self.balance:
                scenes = self.dataset.scenes
                weights = (1.0 / torch.bincount(scenes).double())[scenes]
                order = torch.multinomial(weights, n, replacement=True, generator=draws)
            else:
                order = torch.randperm(n, generator=draws)
            picks = torch.randint(self.pool.count, (len(self), self.extra), generator=draws)
            self._draws = (epoch, order, picks)
        return self._draws[1], self._draws[2]

    def __getitem__(self, index: int) -> dict[str, Tensor]:
        """Batch ``index`` of the epoch under way."""
        epoch = self.epoch()
        views = self.pool.views(epoch)
        order, picks = self.draws(epoch)
        rows = order[index * self.batch_size : (index + 1) * self.batch_size]
        real = self.dataset.__getitems__(rows.tolist())
        rendered = picks[index]
        return {
            "image": torch.cat([real["image"], views["image"][rendered]]),
            "pose": torch.cat([real["pose"], views["pose"][rendered]]),
            "scene": torch.cat([real["scene"], views["scene"][rendered]]),
            "index": torch.cat([real["index"], torch.full((self.extra,), -1)]),
        }


class NovelViewLoader:
    """A teacher's train batches with novel views, as a PoseDataModule's ``train_batches``:
    the views of :class:`NovelViewPool` (``scene_model``, ``settings``, the appearance keyed
    per ``appearance_per``: the scene model's ``sequence`` or ``image``) mixed into the train
    images' batches (:class:`NovelViewBatches`), drawn from ``seed`` and the data module's
    trainer's epoch under way. ``pools``: the pool of each loader made, for its timing."""

    def __init__(
        self,
        scene_model: SceneModel,
        settings: NovelViewSettings,
        appearance_per: str = "sequence",
        seed: int = 0,
    ) -> None:
        self.scene_model = scene_model
        self.settings = settings
        self.appearance_per = appearance_per
        self.seed = seed
        self.pools: list[NovelViewPool] = []

    def __call__(self, data: PoseDataModule) -> DataLoader:
        """The loader of mixed batches over ``data``'s train split."""
        pool = NovelViewPool(data, self.scene_model, self.settings, self.appearance_per, self.seed)
        self.pools.append(pool)
        epoch = partial(trainer_epoch, data)
        batches = NovelViewBatches(data, pool, self.settings.ratio, self.seed, epoch)
        return DataLoader(batches, batch_size=None, generator=torch.Generator())
