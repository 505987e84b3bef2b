"""`pae-localize`'s poses against a run's own test figures: the median position and
orientation errors of the poses in ``--out`` FILE against the label file, per scene and
averaged over scenes as `pae-eval` does, beside the run's `metrics.json`.

    python experiments/ms_scene_decision/parity.py RUN DATA/labels/all_test.csv poses.csv
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import torch

from pae.core.geometry import pose_errors
from pae.data.labels import read_labels


def main(run: Path, labels: Path, poses: Path) -> None:
    truth, found = read_labels(labels), read_labels(poses)
    estimate = dict(zip(found.img_path, torch.as_tensor(found.poses), strict=True))
    missing = [path for path in truth.img_path if path not in estimate]
    if missing:
        sys.exit(f"{poses}: no pose for {len(missing)} of {labels}'s images, e.g. {missing[0]}")
    rows = torch.stack([estimate[path] for path in truth.img_path]).float()
    position, orientation = pose_errors(rows, torch.as_tensor(truth.poses).float())
    scenes = torch.as_tensor(truth.scene_ids())
    medians = [
        (position[scenes == s].quantile(0.5), orientation[scenes == s].quantile(0.5))
        for s in range(len(truth.scene_names))
    ]
    metrics = json.loads((run / "metrics.json").read_text())
    print(
        f"pae-localize {sum(m[0] for m in medians) / len(medians):.6f} m / "
        f"{sum(m[1] for m in medians) / len(medians):.5f}°; the run "
        f"{metrics['test/render_compare/pos_median_m']:.6f} m / "
        f"{metrics['test/render_compare/rot_median_deg']:.5f}°"
    )


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3]))
