"""Can a label-free signal tell where render-and-compare will make real starts worse?

For each scene of ``run.py``'s output: the gate and steps chosen on val as ``run.py`` does,
then how well the scene model explains each query at its refined pose (the PSNR of the
rendering against the query after a gain and bias per channel, ``fitted_psnr_db``), on val
and on test. A floor at a low quantile of the val queries' values keeps a test query's start
wherever the model explains it worse than nearly every val query; the test medians under
each floor are an audit (they read the test labels to score), never a setting.

    python experiments/render_compare_real_starts/gate_signals.py \\
        --labels ../shared/reference/labels --estimates ../shared/reference/estimates \\
        --out outputs/render_compare_real_starts --scenes heads KingsCollege stairs chess
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch
from run import APRS, SCENES, label_files, real_starts, source_paths  # beside this script

from pae.apps.localization import data_module, read_run, scene_model_path, split_queries
from pae.callbacks.scene_quality import fitted_psnr_db
from pae.core.atomic import atomic_write
from pae.core.checkpoints import load_scene_model
from pae.core.geometry import pose_errors
from pae.render_compare import Queries, calibrate_any_start, refine
from pae.render_compare.calibration import scene_size
from pae.render_compare.settings import RenderCompareSettings

FLOOR_QUANTILES = (0.05, 0.1, 0.25)
RENDER_ROWS = 256


@torch.no_grad()
def explained_db(
    model: object, queries: dict[str, torch.Tensor], poses: torch.Tensor
) -> torch.Tensor:
    """PSNR [N] (dB) of the scene model's rendering at poses [N, 7] against the queries."""
    h, w = queries["image"].shape[-2:]
    parts = []
    for rows in torch.arange(len(poses)).split(RENDER_ROWS):
        rendering = model.render(
            poses[rows], queries["scene"][rows], queries["intrinsics"][rows], w, h
        )
        parts.append(fitted_psnr_db(rendering.rgb, queries["image"][rows]))
    return torch.cat(parts)


def signals(dataset: str, scene: str, args: argparse.Namespace) -> dict[str, object]:
    """The scene's explained PSNRs on val and test and the test medians under each floor."""
    files = label_files(dataset, scene, args)
    run = read_run(args.out / scene)
    size = int(run.config.data.size)
    data = data_module(run, cache_images=False, crop=size)
    data.setup()
    model = load_scene_model(scene_model_path(run), "scene_model_ckpt").model.eval()
    settings = RenderCompareSettings(resolution=size)
    val = split_queries(data, "val", size)
    test = split_queries(data, "test", size)
    positions, _ = data.train_poses()
    calibration, val_refined, _ = calibrate_any_start(
        model, Queries(val["image"], val["intrinsics"], val["scene"]), val["pose"],
        scene_size(positions[:, :3].double()), settings,
    )  # fmt: skip
    val_db = explained_db(model, val, val_refined.result.poses)
    record: dict[str, object] = {"val_explained_db_median": float(val_db.median())}
    paths = source_paths(data.tables["test"], files[1])
    for apr in APRS:
        starts = real_starts(args.estimates / apr / dataset, scene, paths, test["pose"])["start"]
        queries = Queries(test["image"], test["intrinsics"], test["scene"])
        refined = refine(model, queries, starts, calibration, settings=settings)
        test_db = explained_db(model, test, refined.result.poses)
        start_m = pose_errors(starts, test["pose"])[0]
        refined_m = pose_errors(refined.poses, test["pose"])[0]
        figures = {
            "test_explained_db_median": float(test_db.median()),
            "start_m": float(start_m.median()),
            "render_compare_m": float(refined_m.median()),
        }
        for quantile in FLOOR_QUANTILES:
            kept = test_db >= val_db.quantile(quantile)
            final = torch.where(kept, refined_m, start_m)
            figures[f"floor_q{quantile}_kept_share"] = float(kept.float().mean())
            figures[f"floor_q{quantile}_test_m"] = float(final.median())
        record[apr] = figures
    return record


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--labels", type=Path, required=True)
    parser.add_argument("--estimates", type=Path, required=True)
    parser.add_argument("--out", type=Path, default=Path("outputs/render_compare_real_starts"))
    parser.add_argument("--scenes", nargs="+", required=True)
    args = parser.parse_args(argv)
    dataset_of = {scene: dataset for dataset, names in SCENES.items() for scene in names}
    for scene in args.scenes:
        if scene not in dataset_of:
            parser.error(f"unknown scene {scene!r}; choose from {sorted(dataset_of)}")
        record = signals(dataset_of[scene], scene, args)
        with atomic_write(args.out / scene / "gate_signals.json") as handle:
            json.dump(record, handle, indent=1)
        for apr in APRS:
            f = record[apr]
            assert isinstance(f, dict)
            floors = "  ".join(
                f"q{q}: {f[f'floor_q{q}_test_m']:.3f} m ({f[f'floor_q{q}_kept_share']:.0%})"
                for q in FLOOR_QUANTILES
            )
            print(
                f"{scene} {apr}: start {f['start_m']:.3f} m, render_compare "
                f"{f['render_compare_m']:.3f} m; explained {record['val_explained_db_median']:.1f} "
                f"dB val, {f['test_explained_db_median']:.1f} dB test; with a floor {floors}",
                flush=True,
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
