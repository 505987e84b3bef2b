"""Where the demo's test cameras lie against its train cameras, and where a teacher errs.

    python experiments/novel_views/geometry.py DATA_ROOT [POSES.csv ...]

DATA_ROOT: the benchmark's folder (labels/all_train.csv, labels/all_test.csv); the train
labels without the validation sequence seq-06 (the demo's). Prints, per scene and median
over cameras: the gap from each train camera to the nearest camera of another train sequence
(what a view's partner was before ``between_radius_m``), and from each test camera to the
nearest train camera and to the nearest one turned at most 30 degrees from it, and from each
validation camera to the nearest train camera. For each
POSES.csv (``pae-localize RUN DATA_ROOT/labels/all_test.csv --out POSES.csv``): the median
position error along the test sequence's path, across it (horizontal) and in height. Reads
the test labels: an analysis, nothing is chosen with it.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

from pae.core.geometry import orientation_error_deg
from pae.data.labels import LabelTable, read_labels

VAL_SEQUENCE = "seq-06"
TURN_DEG = 30.0


def _camera_gaps(train: LabelTable, val: LabelTable, test: LabelTable) -> None:
    """Print the partner gap and the val and test cameras' distances to the train cameras."""
    for scene in train.scene_names:
        rows = np.asarray(train.scene) == scene
        poses = torch.from_numpy(train.poses[rows])
        sequences = np.asarray(train.seq)[rows]
        gaps = torch.cdist(poses[:, :3], poses[:, :3])
        gaps[torch.from_numpy(sequences[:, None] == sequences[None, :])] = float("inf")
        queries = torch.from_numpy(test.poses[np.asarray(test.scene) == scene])
        distances = torch.cdist(queries[:, :3], poses[:, :3])
        turns = orientation_error_deg(queries[:, None, 3:], poses[None, :, 3:])
        aligned = distances.masked_fill(turns > TURN_DEG, float("inf"))
        held = torch.from_numpy(val.poses[np.asarray(val.scene) == scene])
        held_gap = torch.cdist(held[:, :3], poses[:, :3]).min(1).values.median()
        print(
            f"{scene}: train camera -> nearest of another sequence "
            f"{gaps.min(1).values.median():.3f} m; test camera -> nearest train camera "
            f"{distances.min(1).values.median():.3f} m, -> nearest turned <= {TURN_DEG:g} deg "
            f"{aligned.min(1).values.median():.3f} m; val camera -> nearest train camera "
            f"{held_gap:.3f} m"
        )


def _error_directions(test: LabelTable, estimates: LabelTable) -> tuple[float, float, float]:
    """Median |error| (m) along each test sequence's path, across it and in height."""
    along, across, height = [], [], []
    keys = list(zip(test.scene, test.seq, strict=True))
    for key in dict.fromkeys(keys):
        rows = np.flatnonzero([k == key for k in keys])
        truth, error = test.poses[rows, :3], estimates.poses[rows, :3] - test.poses[rows, :3]
        path = np.gradient(truth, axis=0)
        path[:, 2] = 0
        path /= np.linalg.norm(path, axis=1, keepdims=True).clip(1e-9)
        side = np.stack([-path[:, 1], path[:, 0], np.zeros(len(rows))], 1)
        along.append(np.abs((error * path).sum(1)))
        across.append(np.abs((error * side).sum(1)))
        height.append(np.abs(error[:, 2]))
    return tuple(float(np.median(np.concatenate(part))) for part in (along, across, height))


def main(root: str, estimate_paths: list[str]) -> None:
    labels = Path(root) / "labels"
    rows = read_labels(labels / "all_train.csv")
    held = np.asarray(rows.seq) == VAL_SEQUENCE
    train, val = rows.select(np.flatnonzero(~held)), rows.select(np.flatnonzero(held))
    test = read_labels(labels / "all_test.csv")
    _camera_gaps(train, val, test)
    for path in estimate_paths:
        estimates = read_labels(path)
        if len(estimates) != len(test) or list(estimates.seq) != list(test.seq):
            sys.exit(
                f"{path}: not pae-localize's estimates of {labels / 'all_test.csv'} row by row"
            )
        along, across, height = _error_directions(test, estimates)
        print(f"{path}: along {along:.3f} m, across {across:.3f} m, height {height:.3f} m")


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2:])
