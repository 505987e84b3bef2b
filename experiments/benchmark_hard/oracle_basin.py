"""Which of the hard benchmark's options break render-and-compare itself: the benchmark's own
renderer (the oracle scene model, a bound) refines validation queries from their true poses
moved by 0.2 m and 3 degrees, on the easy benchmark with each option alone, with the
surfaces and capture together, with everything on (experiment=demo_hard) and with everything
but one, under the refiner's defaults and under filters demo_hard tries on val and their
variants (--rows and --filters pick some; the default: every row and filter).

    python experiments/benchmark_hard/oracle_basin.py [--train-frames 300] [--every 2]
        [--rows ROW ...] [--filters COLUMN ...]

Reads the val split's labels only (the starts are its true poses moved: an audit of the
refiner's basin, not a method). Renders each dataset on first use under data/synthetic/
(train_frames per scene, which the val split is carved from). Prints one markdown table.
"""

from __future__ import annotations

import argparse

import torch
from hydra.utils import instantiate

from pae.config.schemas import compose_config
from pae.core.geometry import pose_errors
from pae.core.pose_sampling import perturb_poses
from pae.render_compare import refine
from pae.scene_model.oracle import OracleSceneModel

OPTIONS = {
    "none (the easy benchmark)": [],
    "glossy_surface_share=0.5": ["data.glossy_surface_share=0.5"],
    "plain_surface_share=0.3": ["data.plain_surface_share=0.3"],
    "repeated_surface_share=0.2": ["data.repeated_surface_share=0.2"],
    "camera_pipeline=1": ["data.camera_pipeline=1.0"],
    "jpeg_quality=75": ["data.jpeg_quality=75"],
    "render_scale=4": ["data.render_scale=4"],
    "lighting_change=1": ["data.lighting_change=1.0"],
    "occluder_fraction=0.3": ["data.occluder_fraction=0.3"],
    "sensor noise 0.02 + motion blur 3 px": [
        "data.sensor_noise_std=0.02",
        "data.motion_blur_px=3",
    ],
    "surfaces and capture together": [
        "data.plain_surface_share=0.3",
        "data.repeated_surface_share=0.2",
        "data.glossy_surface_share=0.5",
        "data.camera_pipeline=1.0",
        "data.jpeg_quality=75",
        "data.render_scale=4",
    ],
    "all on (demo_hard)": ["experiment=demo_hard"],
    "all on but the occluders": ["experiment=demo_hard", "data.occluder_fraction=0"],
    "all on but the lighting change": ["experiment=demo_hard", "data.lighting_change=0"],
    "all on but the glossy surfaces": ["experiment=demo_hard", "data.glossy_surface_share=0"],
    "all on but the plain surfaces": ["experiment=demo_hard", "data.plain_surface_share=0"],
    "all on but the camera pipeline": ["experiment=demo_hard", "data.camera_pipeline=0"],
    "all on but noise and blur": [
        "experiment=demo_hard",
        "data.sensor_noise_std=0",
        "data.motion_blur_px=0",
    ],
}
"""Row name -> the overrides of experiment=demo that make its benchmark."""
FILTERS = {
    "defaults": {},
    "high-pass 4 px": {"highpass_sigma_px": 4.0},
    "high-pass 4 px + trim 2.5": {"highpass_sigma_px": 4.0, "trim_sigma": 2.5},
    "high-pass 4 px + contrast 4 px": {"highpass_sigma_px": 4.0, "contrast_sigma_px": 4.0},
    "high-pass 4 px + contrast 8 px": {"highpass_sigma_px": 4.0, "contrast_sigma_px": 8.0},
    "high-pass 4 px + contrast 2 px": {"highpass_sigma_px": 4.0, "contrast_sigma_px": 2.0},
    "high-pass 4 px + contrast 4 px + trim 2.5": {
        "highpass_sigma_px": 4.0,
        "contrast_sigma_px": 4.0,
        "trim_sigma": 2.5,
    },
    "high-pass 4 px + contrast 4 px + blur 1 px": {
        "highpass_sigma_px": 4.0,
        "contrast_sigma_px": 4.0,
        "blur_sigma_px": 1.0,
    },
}
"""Column name -> the refiner settings it replaces (demo_hard's filters_from_val)."""
START_M, START_DEG = 0.2, 3.0


def basin_row(
    overrides: list[str], train_frames: int, every: int, filters: dict[str, dict]
) -> list[str]:
    """Median position (m) / orientation (deg) error of the starts and of each of
    ``filters``' refinements on every ``every``-th val query of the benchmark ``overrides``
    make."""
    base = [] if any(o.startswith("experiment=") for o in overrides) else ["experiment=demo"]
    cfg = compose_config("train", [*base, *overrides, f"data.train_frames={train_frames}"])
    data = instantiate(cfg.data, order_seed=0)
    data.prepare_data()
    data.setup("fit")
    images, truth, scenes = [], [], []
    for batch in data.val_dataloader():
        batch = data.on_after_batch_transfer(batch, 0)
        images.append(batch["image"])
        truth.append(batch["pose"])
        scenes.append(batch["scene"])
    images, truth = torch.cat(images)[::every], torch.cat(truth)[::every]
    scenes, intrinsics = torch.cat(scenes)[::every], data.intrinsics("val")[::every]
    starts = perturb_poses(truth, START_M, START_DEG, generator=torch.Generator().manual_seed(0))
    model = OracleSceneModel(data.oracle_scenes())
    cells = []
    for poses in [starts] + [
        refine(model, images, intrinsics, starts, scenes, chosen).poses
        for chosen in filters.values()
    ]:
        position, orientation = pose_errors(poses, truth)
        cells.append(f"{position.median():.3f} / {orientation.median():.2f}")
    return cells


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--train-frames", type=int, default=300, help="train frames per scene")
    parser.add_argument("--every", type=int, default=2, help="every n-th val query")
    parser.add_argument("--rows", nargs="+", choices=list(OPTIONS), default=list(OPTIONS))
    parser.add_argument("--filters", nargs="+", choices=list(FILTERS), default=list(FILTERS))
    args = parser.parse_args()
    filters = {name: FILTERS[name] for name in args.filters}
    print(f"| benchmark | starts | {' | '.join(filters)} |")
    print(f"|---|---|{'---|' * len(filters)}")
    for name in args.rows:
        cells = basin_row(OPTIONS[name], args.train_frames, args.every, filters)
        print(f"| {name} | {' | '.join(cells)} |", flush=True)


if __name__ == "__main__":
    main()
