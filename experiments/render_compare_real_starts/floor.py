"""What limits render-and-compare's precision: the refiner's floor on the validation images.

For a fitted real-starts run (``run.py``), the validation queries are refined with settings
variants (``--variant key=value,key=value``; the first steps and high-pass that
``calibrate_any_start`` chose, read from ``real_starts_DFNet.json``, under every variant),
every refinement accepted, from two kinds of starts: the true poses (the floor: where the
scene model's best match lies) and starts of a good APR's error scale (1 % of the scene's size
and 1 deg, as :func:`pae.render_compare.calibration.ladder_starts` draws them). Only
validation labels are read. One table row per variant, printed and written to
``RUN/floor_val.json``.

    python experiments/render_compare_real_starts/floor.py outputs/rs128/chess \\
        --variant '' --variant final_reference_size=64 --variant final_reference_size=128
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import torch

from pae.apps.localization import data_module, read_run, scene_model_path, split_queries
from pae.core.atomic import atomic_write
from pae.core.checkpoints import load_scene_model
from pae.core.geometry import pose_errors
from pae.core.pose_sampling import perturb_poses
from pae.render_compare import ACCEPT_ALL, Calibration, refine
from pae.render_compare.calibration import scene_size
from pae.render_compare.settings import RenderCompareSettings

GOOD_START_SHARE = 0.01
"""A good APR's position error as a share of the scene's size (DFNet: 3 cm in a 3 m room)."""
GOOD_START_DEG = 1.0
STEP_KEYS = ("position_sigma_m", "orientation_sigma_deg", "highpass_sigma_px", "highpass_levels")


def parse_variant(text: str) -> dict[str, Any]:
    """``key=value,key=value`` -> settings (numbers as int or float)."""
    variant: dict[str, Any] = {}
    for item in filter(None, text.split(",")):
        key, _, value = item.partition("=")
        number = float(value)
        variant[key] = int(number) if number.is_integer() and "." not in value else number
    return variant


def medians(poses: torch.Tensor, truth: torch.Tensor) -> dict[str, float]:
    """Median position (m) and orientation (deg) errors of poses [N, 7]."""
    pos, rot = pose_errors(poses.float(), truth.float())
    return {"pos_median_m": float(pos.median()), "rot_median_deg": float(rot.median())}


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--variant", action="append", default=[], help="key=value,...")
    parser.add_argument("--queries", type=int, default=400, help="val queries (evenly spaced)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    run = read_run(args.run)
    size = int(run.config.data.size)
    data = data_module(run, cache_images=False, crop=size)
    data.setup()
    model = load_scene_model(scene_model_path(run), "scene_model_ckpt").model.eval()
    val = split_queries(data, "val", size)
    rows = torch.linspace(0, len(val["pose"]) - 1, min(args.queries, len(val["pose"]))).long()
    val = {key: value[rows] for key, value in val.items()}
    truth = val["pose"]
    train_positions, _ = data.train_poses()
    extent = scene_size(train_positions[:, :3].double())
    chosen = json.loads((args.run / "real_starts_DFNet.json").read_text())["calibration"]
    steps = {key: chosen[key] for key in STEP_KEYS if key in chosen}
    generator = torch.Generator().manual_seed(args.seed)
    count = len(truth)
    good = perturb_poses(
        truth.double(),
        torch.full((count,), GOOD_START_SHARE * extent, dtype=torch.float64),
        torch.full((count,), GOOD_START_DEG, dtype=torch.float64),
        generator,
    ).to(truth)
    out_path = args.run / "floor_val.json"
    results = json.loads(out_path.read_text()) if out_path.is_file() else {}
    print(f"{args.run.name}: {count} val queries, scene {extent:.2f} m, steps {steps}")
    print(f"start (1 % / 1 deg): {medians(good, truth)}")
    for text in args.variant or [""]:
        settings = RenderCompareSettings(resolution=size).__dict__ | parse_variant(text)
        calibration = Calibration(ACCEPT_ALL, ACCEPT_ALL, steps)
        row: dict[str, Any] = {}
        for name, starts in (("from_truth", truth), ("from_good", good)):
            begin = time.perf_counter()
            refined = refine(
                model, val["image"], val["intrinsics"], starts, val["scene"], settings,
                calibration,
            )  # fmt: skip
            row[name] = medians(refined.poses, truth)
            row[f"{name}_ms_per_query"] = 1000 * (time.perf_counter() - begin) / count
        results[text or "(chosen)"] = row
        print(
            f"{text or '(chosen)':60s} truth {100 * row['from_truth']['pos_median_m']:.2f} cm"
            f" / {row['from_truth']['rot_median_deg']:.2f} deg, good "
            f"{100 * row['from_good']['pos_median_m']:.2f} cm / "
            f"{row['from_good']['rot_median_deg']:.2f} deg, "
            f"{row['from_good_ms_per_query']:.1f} ms/query",
            flush=True,
        )
        with atomic_write(out_path) as handle:
            json.dump(results, handle, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
