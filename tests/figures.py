"""Checks of reported error figures against bounds taken from the label files."""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from pae.data.labels import read_labels

MAX_ANGLE_DEG = 180.0
"""No orientation error in degrees exceeds this: a larger figure has the wrong units."""

WORSE_THAN_MEAN_POSE = 3.0
"""How many times the mean-pose baseline's position figure a method may reach on the tiny
dataset: runs there, trained or not, stay under 2×; metres reported in millimetres do not."""


def assert_error_figure(metrics: Mapping[str, float], key: str, upper: float) -> float:
    """Assert that ``metrics[key]`` is present, finite and in ``(0, upper)``; return it.

    An error of exactly 0 on held-out queries means a leak or a metric that measures nothing."""
    assert key in metrics, f"{key} is not reported"
    value = metrics[key]
    assert math.isfinite(value), f"{key} = {value}"
    assert 0 < value < upper, f"{key} = {value}, expected in (0, {upper:g})"
    return value


def _markley_mean(quaternions: np.ndarray) -> np.ndarray:
    """The eigenvector of the largest eigenvalue of Σ qqᵀ over unit quaternions [N, 4]."""
    q = quaternions / np.linalg.norm(quaternions, axis=1, keepdims=True)
    return np.linalg.eigh(q.T @ q)[1][:, -1]


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Rotation angles in degrees between unit quaternions a [N, 4] and b [4]."""
    dot = np.abs(a @ b) / np.linalg.norm(a, axis=1) / np.linalg.norm(b)
    return np.degrees(2 * np.arccos(np.clip(dot, 0.0, 1.0)))


def label_reference(root: Path, split: str) -> dict[str, float]:
    """What the labels alone say the ``split`` (``val`` or ``test``) figures must be.

    The store is every train row but the last sequence of each scene (the validation split).
    Returns the ``mean_pose`` method's figures (per scene, the error of the mean store
    position and the Markley-average store orientation; keyed as the metrics: ``<figure>``
    averaged over scenes and ``<scene>/<figure>``) and ``gt_to_train_m``, the median over all
    queries of the distance from the true position to the nearest store position of its
    scene."""
    train = read_labels(root / "labels" / "all_train.csv")
    held = np.zeros(len(train), dtype=bool)
    for scene in train.scene_names:
        rows = np.asarray(train.scene) == scene
        held |= rows & (np.asarray(train.seq) == max(np.asarray(train.seq)[rows]))
    store = train.select(~held)
    queries = (
        train.select(held) if split == "val" else read_labels(root / "labels" / "all_test.csv")
    )
    figures: dict[str, float] = {}
    per_scene: dict[str, list[float]] = {}
    nearest: list[np.ndarray] = []
    for scene in queries.scene_names:
        mine = queries.poses[np.asarray(queries.scene) == scene]
        known = store.poses[np.asarray(store.scene) == scene]
        pos = np.linalg.norm(mine[:, :3] - known[:, :3].mean(axis=0), axis=1)
        rot = _angle_deg(mine[:, 3:], _markley_mean(known[:, 3:]))
        for name, value in (
            ("pos_median_m", np.median(pos)),
            ("rot_median_deg", np.median(rot)),
            ("pos_mean_m", pos.mean()),
            ("rot_mean_deg", rot.mean()),
        ):
            per_scene.setdefault(name, []).append(float(value))
            figures[f"{scene}/{name}"] = float(value)
        gaps = np.linalg.norm(mine[:, None, :3] - known[None, :, :3], axis=-1)
        nearest.append(gaps.min(axis=1))
    figures |= {name: float(np.mean(values)) for name, values in per_scene.items()}
    return figures | {"gt_to_train_m": float(np.median(np.concatenate(nearest)))}
