"""The random-guess check from label files alone: what retrieval does without any image or PAE.

The paper's supplementary checks its refinement by encoding a random guess around the true
pose (true position + N(0, σ²I₃) m, true orientation) and refining it. The authors' public
script retrieves the guess's neighbours among the *test* poses; then the plain mean of the k
nearest test poses, with no PAE at all, already lands close to the truth, because the true
pose and its sequence neighbours are in the store. ``guess_audit`` measures that mean from
the test store and from the train store, per scene, from label files only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pae.core.pose_sampling import perturb_positions
from pae.data.labels import LabelTable
from pae.refine.index import PoseDistance, PoseIndex


@dataclass(frozen=True)
class GuessAuditRow:
    """One scene: row counts, the median distance (m) from a test camera to the nearest train
    camera, and median position errors (m) of the guess and of the mean of its k nearest
    poses in the test store and in the train store."""

    scene: str
    test_rows: int
    train_rows: int
    test_to_train_m: float
    guess_m: float
    knn_mean_test_store_m: float
    knn_mean_m: float


def _median_error(estimate: torch.Tensor, truth: torch.Tensor) -> float:
    return float((estimate - truth).norm(dim=-1).quantile(0.5))


def guess_audit(
    test: LabelTable,
    train: LabelTable,
    sigma_m: float = 1.0,
    k: int = 3,
    seed: int = 0,
    distance: PoseDistance = "normalized",
) -> list[GuessAuditRow]:
    """Per scene of ``test`` (each must have train rows): the guess table, all scenes batched.

    ``distance`` is the kNN distance of :class:`PoseIndex` (default: the public code's rule,
    each of position and orientation distance divided by its maximum over the store).
    """
    if not sigma_m > 0:
        raise ValueError(f"sigma must be > 0 m, got {sigma_m}")
    if k < 1:
        raise ValueError(f"k must be >= 1, got {k}")
    missing = sorted(set(test.scene_names) - set(train.scene_names))
    if missing:
        raise ValueError(f"{train.source}: no train rows for the test scenes {missing}")
    names = train.scene_names
    test_poses = torch.from_numpy(test.poses).float()
    test_scenes = torch.from_numpy(test.scene_ids(names))
    train_poses = torch.from_numpy(train.poses).float()
    train_scenes = torch.from_numpy(train.scene_ids(names))
    guess = perturb_positions(test_poses, sigma_m, torch.Generator().manual_seed(seed))
    means = {}
    for store_name, poses, scenes in (
        ("test", test_poses, test_scenes),
        ("train", train_poses, train_scenes),
    ):
        index = PoseIndex(poses, scenes, distance=distance)
        neighbours, _ = index.query(guess, test_scenes, k)
        means[store_name] = index.poses[neighbours, :3].mean(dim=1)
    nearest_train, _ = PoseIndex(train_poses, train_scenes, distance="fixed", rot_weight=0.0).query(
        test_poses, test_scenes, 1
    )
    to_train = (train_poses[nearest_train[:, 0], :3] - test_poses[:, :3]).norm(dim=-1)
    rows = []
    for name in test.scene_names:
        mask = test_scenes == names.index(name)
        truth = test_poses[mask, :3]
        rows.append(
            GuessAuditRow(
                scene=name,
                test_rows=int(mask.sum()),
                train_rows=int((train_scenes == names.index(name)).sum()),
                test_to_train_m=float(to_train[mask].quantile(0.5)),
                guess_m=_median_error(guess[mask, :3], truth),
                knn_mean_test_store_m=_median_error(means["test"][mask], truth),
                knn_mean_m=_median_error(means["train"][mask], truth),
            )
        )
    return rows


def format_guess_audit(rows: list[GuessAuditRow], sigma_m: float, k: int) -> str:
    """Markdown table of ``rows`` with their average and a footnote on the test store."""
    header = (
        "| scene | test rows | test→train [m] | guess [m] "
        f"| mean of {k} nearest, test store * [m] | mean of {k} nearest, train store [m] |"
    )
    lines = [header, "|---|---:|---:|---:|---:|---:|"]
    for row in rows:
        lines.append(
            f"| {row.scene} | {row.test_rows} | {row.test_to_train_m:.2f} | {row.guess_m:.2f} "
            f"| {row.knn_mean_test_store_m:.2f} | {row.knn_mean_m:.2f} |"
        )
    if len(rows) > 1:
        average = [
            np.mean([getattr(r, name) for r in rows])
            for name in ("test_to_train_m", "guess_m", "knn_mean_test_store_m", "knn_mean_m")
        ]
        lines.append("| average | | " + " | ".join(f"{v:.2f}" for v in average) + " |")
    lines.append(
        f"\nguess = true position + N(0, {sigma_m:g}² I₃) m, true orientation; medians of the "
        "position error. * retrieves among the test poses themselves (the authors' public "
        "scripts do): the true pose is in the store, so no image and no PAE is needed."
    )
    return "\n".join(lines)
