"""An audit, not a method: the teacher trained on views rendered at the *test* cameras.

The same run as ``pae-train experiment=demo_novel_views ...`` except that the pool of novel
views is drawn around the test split's poses (each jittered as the settings say, with the
appearance and intrinsics of its nearest train camera) instead of around the train cameras:
what a teacher could reach if the sampled views covered the test cameras exactly (a bound,
named ``*_oracle``). Its test figures read the test labels by construction; nothing is chosen
with them.

    python experiments/novel_views/test_pose_views_oracle.py LABELS.csv OVERRIDES...
"""

from __future__ import annotations

import sys

import torch

from pae.core import streams
from pae.core.pose_sampling import perturb_poses
from pae.data.labels import read_labels
from pae.scene_model import novel_views


def test_pose_cameras(labels: str):
    """A replacement of ``NovelViewPool.cameras``: the pool's views around ``labels``' poses."""
    table = read_labels(labels)

    def cameras(pool: novel_views.NovelViewPool, epoch: int) -> novel_views.NovelPoses:
        names = pool.scene_model_names
        poses = torch.tensor(table.poses, dtype=torch.float64)
        scenes = torch.tensor([names.index(name) for name in table.scene])
        draws = streams.generator(pool.seed, "novel_views", 0)
        picked = torch.randint(len(poses), (pool.count,), generator=draws)
        s = pool.settings
        moved = perturb_poses(poses[picked], s.position_jitter_m, s.orientation_jitter_deg, draws)
        nearest = novel_views.nearest_train_rows(
            moved[:, :3], scenes[picked], pool.poses[:, :3].double(), pool.scenes
        )
        return novel_views.NovelPoses(moved.float(), scenes[picked], nearest, nearest)

    return cameras


if __name__ == "__main__":
    labels, overrides = sys.argv[1], sys.argv[2:]
    original_init = novel_views.NovelViewPool.__init__

    def init(pool, data, *args, **kwargs) -> None:
        original_init(pool, data, *args, **kwargs)
        pool.scene_model_names = data.scene_names

    novel_views.NovelViewPool.__init__ = init
    novel_views.NovelViewPool.cameras = test_pose_cameras(labels)
    from pae.train import main

    sys.argv = [sys.argv[0], *overrides]
    main()
