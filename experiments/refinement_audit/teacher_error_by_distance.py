"""A teacher's median test position error by how far each test camera lies from the train
cameras: by position alone, and by position among train cameras facing within 10 degrees.

    python experiments/refinement_audit/teacher_error_by_distance.py CKPT DATA_ROOT

CKPT: a teacher (or student) checkpoint; DATA_ROOT: a dataset folder with labels/all_*.csv
(e.g. a `pae-data synth` output). Uses test labels: an audit, not an evaluation.
"""

from __future__ import annotations

import itertools
import sys

import numpy as np
import torch
from hydra.utils import instantiate

from pae.config.schemas import compose_config
from pae.core.checkpoints import load_teacher

BINS_M = (0.0, 0.1, 0.2, 0.4, 0.8, np.inf)
FACING_DEG = 10.0


def nearest_train_distances(
    test: np.ndarray, train: np.ndarray, facing_deg: float | None
) -> np.ndarray:
    """Distance (m) from each test pose [n, 7] to the nearest train pose [m, 7]; with
    ``facing_deg``, only among train poses whose orientation is within that angle."""
    position = np.linalg.norm(test[:, None, :3] - train[None, :, :3], axis=-1)
    if facing_deg is not None:
        cosine = np.abs(test[:, 3:] @ train[:, 3:].T).clip(max=1.0)
        position[np.degrees(2 * np.arccos(cosine)) > facing_deg] = np.inf
    return position.min(axis=1)


def main(checkpoint: str, root: str) -> None:
    cfg = compose_config("train", [f"data.root={root}", "data.num_workers=0"])
    data = instantiate(cfg.data)
    data.setup("fit")
    data.setup("test")
    teacher = load_teacher(checkpoint).model
    estimates, truths, scenes = [], [], []
    with torch.no_grad():
        for batch in data.test_dataloader():
            batch = data.on_after_batch_transfer(batch, 0)
            estimates.append(teacher.estimate(batch["image"], batch["scene"]).pose)
            truths.append(batch["pose"])
            scenes.append(batch["scene"])
    estimate, truth = torch.cat(estimates).numpy(), torch.cat(truths).numpy()
    scene = torch.cat(scenes).numpy()
    train, train_scene = (t.numpy() for t in data.train_poses())
    error = np.linalg.norm(estimate[:, :3] - truth[:, :3], axis=1)
    print(f"teacher median position error {np.median(error):.3f} m over {len(error)} queries")
    for facing, label in (
        (None, "position only"),
        (FACING_DEG, f"facing within {FACING_DEG:g} deg"),
    ):
        distance = np.empty(len(truth))
        for s in np.unique(scene):
            distance[scene == s] = nearest_train_distances(
                truth[scene == s], train[train_scene == s], facing
            )
        print(f"nearest train camera, {label}: median {np.median(distance):.3f} m")
        for lo, hi in itertools.pairwise(BINS_M):
            inside = (distance >= lo) & (distance < hi)
            if inside.any():
                print(
                    f"  [{lo:.1f}, {hi:.1f}) m: {inside.sum():4d} queries, "
                    f"teacher median error {np.median(error[inside]):.3f} m"
                )


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2])
