"""Which of the hard benchmark's options break render-and-compare itself: the benchmark's own
renderer (the oracle scene model, a bound) refines validation queries from their true poses
moved by 0.2 m and 3 degrees, on the easy benchmark with each option alone, with the
surfaces and capture together, with everything on (experiment=demo_hard) and with everything
but one, under the refiner's defaults and under filters demo_hard tries on val and their
variants (--rows and --filters pick some; the default: every row and filter).

    python experiments/benchmark_hard/oracle_basin.py [--train-frames 300] [--every 2]
        [--rows ROW ...] [--filters COLUMN ...] [--start M DEG] [--seeds S ...]

Reads the val split's labels only (the starts are its true poses moved: an audit of the
refiner's basin, not a method). Each cell: median position (m) / orientation (deg) (the mean
over the seeds' draws of starts) and the share within 5 cm / 5 deg. Renders each dataset on
first use under data/synthetic/ (train_frames per scene, which the val split is carved from).
Prints one markdown table.
"""

from __future__ import annotations

import argparse

import torch
from hydra.utils import instantiate

from pae.config.schemas import compose_config
from pae.core.geometry import pose_errors
from pae.core.metrics import WITHIN
from pae.core.pose_sampling import perturb_poses
from pae.render_compare import Queries, refine
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
CONTRAST_4 = FILTERS["high-pass 4 px + contrast 4 px"]
WIDER = {"rounds": 8, "candidates": 24, "hypotheses": 8}
FILTERS |= {
    "contrast 4 px, 2 levels": CONTRAST_4 | {"levels": 2},
    "contrast 4 px, 2 levels, reference 32 px": CONTRAST_4 | {"levels": 2, "reference_size": 32},
    "contrast 4 px, wider search": CONTRAST_4 | {"levels": 2, "reference_size": 32} | WIDER,
    "contrast 3 px, wider search": {
        "highpass_sigma_px": 3.0,
        "contrast_sigma_px": 3.0,
        "levels": 2,
        "reference_size": 32,
    }
    | WIDER,
}
"""The search of experiment=demo_hard: two pyramid levels (the coarsest 28 px, not 14), a
32-px reference (four times the surface points) and 8 rounds of 24 candidates for each of 8
hypotheses (the defaults: 4, 12, 4)."""


def basin_row(
    overrides: list[str],
    train_frames: int,
    every: int,
    filters: dict[str, dict],
    start: tuple[float, float] = (0.2, 3.0),
    seeds: tuple[int, ...] = (0,),
) -> list[str]:
    """Median position (m) / orientation (deg) error (the mean over the ``seeds`` of the
    starts' draws) and the share within 5 cm / 5 deg of the starts and of each of
    ``filters``' refinements on every ``every``-th val query of the benchmark ``overrides``
    make, from the true poses moved by ``start`` (m, deg)."""
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
    model = OracleSceneModel(data.oracle_scenes())
    figures = torch.zeros(1 + len(filters), 3)
    for seed in seeds:
        generator = torch.Generator().manual_seed(seed)
        starts = perturb_poses(truth, *start, generator=generator)
        for column, poses in enumerate(
            [starts]
            + [
                refine(model, Queries(images, intrinsics, scenes), starts, settings=chosen).poses
                for chosen in filters.values()
            ]
        ):
            position, orientation = pose_errors(poses, truth)
            metres, degrees = WITHIN["5cm_5deg"]
            within = ((position <= metres) & (orientation <= degrees)).double().mean()
            figures[column] += torch.stack([position.median(), orientation.median(), within])
    figures /= len(seeds)
    return [f"{p:.3f} / {o:.2f} ({100 * w:.0f} %)" for p, o, w in figures.tolist()]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--train-frames", type=int, default=300, help="train frames per scene")
    parser.add_argument("--every", type=int, default=2, help="every n-th val query")
    parser.add_argument("--rows", nargs="+", choices=list(OPTIONS), default=list(OPTIONS))
    parser.add_argument("--filters", nargs="+", choices=list(FILTERS), default=list(FILTERS))
    parser.add_argument(
        "--start",
        nargs=2,
        type=float,
        default=(0.2, 3.0),
        metavar=("M", "DEG"),
        help="the starts' median distance (m) and angle (deg) from the true poses",
    )
    parser.add_argument("--seeds", nargs="+", type=int, default=[0], help="the starts' draws")
    args = parser.parse_args()
    filters = {name: FILTERS[name] for name in args.filters}
    print(f"| benchmark | starts | {' | '.join(filters)} |")
    print(f"|---|---|{'---|' * len(filters)}")
    for name in args.rows:
        cells = basin_row(
            OPTIONS[name],
            args.train_frames,
            args.every,
            filters,
            tuple(args.start),
            tuple(args.seeds),
        )
        print(f"| {name} | {' | '.join(cells)} |", flush=True)


if __name__ == "__main__":
    main()
