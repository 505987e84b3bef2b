"""The synthetic benchmark's camera sequences: train lanes beside each room's route, test
sequences between them, with the layout's strays (``make_sequences``)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pae.core.geometry import matrix_to_quaternion
from pae.synthetic.camera import look_rotations
from pae.synthetic.raycast import Appearance
from pae.synthetic.scene import CameraRoute, SyntheticScene
from pae.synthetic.settings import SyntheticSettings

TRAIN_SEQUENCES = 6
TEST_SEQUENCES = 2


@dataclass(frozen=True, eq=False)
class CameraSequence:
    """One recorded sequence: ``name`` (``seq-01``…), ``split``, poses ``[n, 7]`` and its
    appearance; ``noise_seed`` seeds its sensor noise, ``nuisance_seed`` its nuisances (see
    :mod:`pae.synthetic.nuisances`)."""

    name: str
    split: str
    poses: np.ndarray
    appearance: Appearance
    noise_seed: tuple[int, ...]
    nuisance_seed: tuple[int, ...]


def _split_counts(total: int, parts: int) -> list[int]:
    """``total`` frames over ``min(parts, total)`` sequences, as evenly as possible."""
    parts = min(parts, total)
    return [total // parts + (1 if i < total % parts else 0) for i in range(parts)]


def walk_frames(train_frames: int) -> int:
    """Frames of each validation walk of :func:`make_sequences`: the last train sequence's."""
    return _split_counts(train_frames, TRAIN_SEQUENCES)[-1]


def smooth_wave(
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


def trajectory(
    scene: SyntheticScene,
    frames: int,
    start: float,
    rng: np.random.Generator,
    offset_m: float = 0.0,
    yaw_stray_rad: float = SyntheticSettings.yaw_stray_rad,
    stray_m: float = SyntheticSettings.stray_m,
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
            stray_m * smooth_wave(rng, t, (0.5, 1.5), (0.7, 0.3)),
            stray_m * smooth_wave(rng, t, (0.5, 1.5), (0.7, 0.3)),
            0.1 * smooth_wave(rng, t, (0.5, 1.5), (0.7, 0.3)),
        ],
        axis=1,
    )
    yaw = route_yaw + yaw_stray_rad * smooth_wave(rng, t, (0.5, 1.5), (0.7, 0.3))
    pitch = np.radians(-3.0) + np.radians(11.0) * smooth_wave(rng, t, (0.5, 1.5), (0.8, 0.2))
    roll = np.radians(5.0) * smooth_wave(rng, t, (0.5, 1.5), (0.7, 0.3))
    rotations = look_rotations(yaw, pitch, roll)
    quaternions = matrix_to_quaternion(torch.from_numpy(rotations)).numpy()
    return np.concatenate([position, quaternions], axis=1)


def make_sequences(
    scene_index: int, scene: SyntheticScene, settings: SyntheticSettings
) -> list[CameraSequence]:
    """Train sequences ``seq-01…``, test sequences, then ``val_walks`` validation walks
    (numbered on) of scene ``scene_index``.

    Up to 6 train and 2 test sequences share the frames of each split. Each walks most of the
    scene's route with its own deviations and :class:`Appearance`; the sequences of a split
    start at staggered route times, so that together they cover the whole route. Test
    sequences walk ``test_offset_m`` beside the route, alternately to its left and right (0:
    on the route, like the train sequences). ``val_lane_m`` not None: the last train sequence
    (the validation sequence of ``val_sequences: 1``) walks that far from the route instead of
    on its lane (signed, positive to the left; 0: on the route, between the lanes); the others
    are the same sequences as without it. The validation walks are train-split sequences
    with as many frames as the last train sequence, staggered along the route like the
    others and walking where it walks (``val_lane_m``, or alternately its lane and the
    other): more validation data from the same layout, every other sequence unchanged.
    """
    train_frames, seed, val_lane_m = settings.train_frames, settings.seed, settings.val_lane_m
    train_lane_m, val_walks = settings.train_lane_m, settings.val_walks
    train_counts = _split_counts(train_frames, TRAIN_SEQUENCES)
    test_counts = _split_counts(settings.test_frames, TEST_SEQUENCES)
    splits = [("train", i, len(train_counts), n) for i, n in enumerate(train_counts)]
    splits += [("test", i, len(test_counts), n) for i, n in enumerate(test_counts)]
    splits += [("walk", i, val_walks, walk_frames(train_frames)) for i in range(val_walks)]
    last_lane = train_lane_m * (-1) ** (len(train_counts) - 1)
    sequences = []
    for number, (kind, index_in_split, count, frames) in enumerate(splits, start=1):
        rng = np.random.default_rng([seed, scene_index, 1, number])
        start = (index_in_split + rng.uniform(0, 0.3)) / count
        lane = settings.test_offset_m if kind == "test" else train_lane_m
        offset = lane * (-1) ** index_in_split
        last_train = kind == "train" and index_in_split == count - 1
        if (last_train or kind == "walk") and val_lane_m is not None:
            offset = val_lane_m
        elif kind == "walk":
            offset = last_lane * (-1) ** index_in_split
        split = "test" if kind == "test" else "train"
        poses = trajectory(
            scene, frames, start, rng, offset, settings.yaw_stray_rad, settings.stray_m
        )
        appearance = Appearance.random(rng)
        sequences.append(
            CameraSequence(
                f"seq-{number:02d}",
                split,
                poses,
                appearance,
                (seed, scene_index, 2, number),
                (seed, scene_index, 3, number),
            )
        )
    return sequences
