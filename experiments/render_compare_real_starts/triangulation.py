"""How well the train views' triangulated keypoints (``scene_model.depth_rays``,
:mod:`pae.scene_model.sparse_depth`) hold the true depth: on a fitted real-starts run's train
images (as the fit reads them), the keypoints' depth against the benchmark's own renderer's at
the same pixels. Only the train split is read (images, poses, and the benchmark's scenes).

    python experiments/render_compare_real_starts/triangulation.py OUT/StMarysChurch \\
        --min-baseline 0.03 --min-parallax 1.0
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from pae.apps.localization import data_module, read_run
from pae.lit.eval_outputs import oracle_scenes
from pae.scene_model.oracle import OracleSceneModel
from pae.scene_model.rays import fit_images
from pae.scene_model.sparse_depth import MIN_BASELINE, MIN_PARALLAX_DEG, sparse_depths


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--min-baseline", type=float, default=MIN_BASELINE)
    parser.add_argument("--min-parallax", type=float, default=MIN_PARALLAX_DEG)
    parser.add_argument(
        "--images", type=int, default=200, help="train images whose keypoints are checked"
    )
    args = parser.parse_args(argv)
    run = read_run(args.run)
    data = data_module(run)
    data.setup("fit")
    scenes = oracle_scenes(data)
    if scenes is None:
        raise SystemExit(f"{args.run}: its data does not know the true scenes")
    train = data.datasets["train"]
    images, intrinsics = fit_images(
        train, data.intrinsics("train", crop=False), run.config.scene_model.image_size
    )
    depths = sparse_depths(
        images, train.poses, intrinsics, train.scenes, args.min_baseline, args.min_parallax
    )
    checked = depths.row.unique()[: args.images]
    height, width = images.shape[-2:]
    truth = (
        OracleSceneModel(scenes)
        .render(train.poses[checked], train.scenes[checked], intrinsics[checked], width, height)
        .depth
    )
    keep = torch.isin(depths.row, checked)
    at = torch.searchsorted(checked, depths.row[keep])
    true = truth[at, depths.v[keep].round().long(), depths.u[keep].round().long()]
    error = (depths.depth[keep] / true).log().abs()
    print(
        f"{args.run.name}: partners at {args.min_baseline:g} x the camera extent, "
        f"{args.min_parallax:g} deg: {len(depths.row)} keypoints in {len(depths.row.unique())} "
        f"of {len(train)} train images; on {len(checked)} images ({len(error)} keypoints) "
        f"the depth a median {100 * float(error.median()):.1f} % off, "
        f"{100 * float((error > 0.1).float().mean()):.0f} % more than 10 % off"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
