"""Where a run's teacher errs, in each true camera's frame, on its validation split.

    python experiments/novel_views/error_frame.py RUN [RUN ...]

RUN: a `pae-train` run directory (its `.hydra/config.yaml` and `teacher/checkpoints/last.ckpt`).
Prints per run the median absolute position error across the view (camera x), in height
(camera y) and along it (camera z), the median yaw error (about camera y), their correlation
and how much of the across error a linear function of the yaw error leaves (median absolute
residual). A camera turned by a small angle and one moved sideways by the angle times the
scene's depth see about the same image: where the two are confused the correlation is strong.
Reads the validation split only.
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch
from omegaconf import OmegaConf

from pae.core.checkpoints import load_teacher
from pae.core.geometry import quaternion_conjugate, quaternion_multiply, quaternion_to_matrix
from pae.runs.inputs import build_data


@torch.no_grad()
def errors_in_camera_frame(run: Path) -> tuple[torch.Tensor, torch.Tensor]:
    """The teacher's position errors [N, 3] (m) in the true cameras' frames and its yaw errors
    [N] (deg) on the validation split of ``run``."""
    cfg = OmegaConf.load(run / ".hydra" / "config.yaml")
    data = build_data(cfg, augment=False)
    teacher = load_teacher(run / "teacher" / "checkpoints" / "last.ckpt").model.eval()
    predicted, true = [], []
    for batch in data.val_dataloader():
        pose, _ = teacher(data.preprocess(batch["image"], train=False))
        predicted.append(pose)
        true.append(batch["pose"])
    pred, gt = torch.cat(predicted), torch.cat(true)
    rotation = quaternion_to_matrix(gt[:, 3:])
    across_height_along = torch.einsum("bji,bj->bi", rotation, pred[:, :3] - gt[:, :3])
    q = pred[:, 3:] / pred[:, 3:].norm(dim=-1, keepdim=True)
    turn = quaternion_multiply(quaternion_conjugate(gt[:, 3:]), q)  # true -> predicted, camera
    turn = turn * torch.sign(turn[:, :1])
    yaw = torch.rad2deg(2 * torch.atan2(turn[:, 2], turn[:, 0]))
    return across_height_along, yaw


def main() -> None:
    for run in map(Path, sys.argv[1:]):
        error, yaw = errors_in_camera_frame(run)
        across = error[:, 0]
        slope = (across * yaw).sum() / (yaw * yaw).sum()
        corr = torch.corrcoef(torch.stack([across, yaw]))[0, 1]
        medians = error.abs().median(0).values.tolist()
        residual = (across - slope * yaw).abs().median()
        print(
            f"{run}: val n={len(yaw)} |error| across {medians[0]:.3f} m, height "
            f"{medians[1]:.3f} m, along {medians[2]:.3f} m; |yaw| {yaw.abs().median():.2f} deg; "
            f"corr(across, yaw) {corr:+.2f}; |across - ({slope:+.4f} m/deg) yaw| {residual:.3f} m"
        )


if __name__ == "__main__":
    main()
