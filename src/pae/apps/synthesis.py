"""``pae-data synth``: its arguments and what it runs (the renderer is imported only when it
runs, so that ``pae-data``'s other commands start without torch)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from pae.core.console import Progress


def _render_progress(out: Path) -> Progress:
    """Rendering progress lines on stderr (stdout keeps the summary)."""
    return Progress(f"rendering {out}", "frames", lambda line: print(line, file=sys.stderr))


SYNTH_OPTIONS = {
    "scenes": "scenes",
    "train_frames": "train_frames",
    "test_frames": "test_frames",
    "test_offset_m": "test_offset",
    "train_lane_m": "train_lane",
    "val_lane_m": "val_lane",
    "val_walks": "val_walks",
    "yaw_stray_rad": "yaw_stray",
    "stray_m": "stray",
    "lighting_change": "lighting_change",
    "occluder_fraction": "occluder_fraction",
    "sensor_noise_std": "sensor_noise",
    "motion_blur_px": "motion_blur",
    "plain_surface_share": "plain_surfaces",
    "repeated_surface_share": "repeated_surfaces",
    "glossy_surface_share": "glossy_surfaces",
    "camera_pipeline": "camera_pipeline",
    "jpeg_quality": "jpeg_quality",
    "render_scale": "render_scale",
}
"""The benchmark's settings (:class:`pae.synthetic.settings.SyntheticSettings`) ->
``pae-data synth``'s options that set them (``--test-offset`` for ``test_offset``); one
not given keeps its default."""
DRESSING = (
    "lighting_change",
    "occluder_fraction",
    "sensor_noise_std",
    "motion_blur_px",
    "plain_surface_share",
    "repeated_surface_share",
    "glossy_surface_share",
    "camera_pipeline",
    "jpeg_quality",
    "render_scale",
)
"""The settings ``--poses`` takes too: the nuisances, surfaces and capture (not the layout's)."""


def run_synth(args: argparse.Namespace) -> int:
    """``pae-data synth``: render the benchmark (or the rows of ``--poses``) into ``OUT``."""
    from pae import synthetic

    given = {
        setting: getattr(args, option)
        for setting, option in SYNTH_OPTIONS.items()
        if getattr(args, option) is not None
    }
    if args.poses:
        layout = [s for s in given if s not in DRESSING]
        if layout:
            flags = ", ".join(f"--{SYNTH_OPTIONS[s].replace('_', '-')}" for s in layout)
            raise ValueError(f"--poses takes no layout option: drop {flags}")
        from pae.synthetic.poses import write_dataset_at_poses

        dataset = write_dataset_at_poses(
            args.out,
            args.poses,
            size=synthetic.SyntheticSettings.size if args.size is None else args.size,
            seed=args.seed,
            overwrite=args.overwrite,
            progress=_render_progress(args.out),
            options=synthetic.SyntheticSettings(**given),
        )
    else:
        if args.size is not None:
            given["size"] = args.size
        dataset = synthetic.write_synthetic_dataset(
            args.out,
            seed=args.seed,
            overwrite=args.overwrite,
            progress=_render_progress(args.out),
            **given,
        )
    print(dataset.summary())
    return 0


def add_synth_command(commands: Any) -> None:
    """Add ``synth`` to ``pae-data``'s sub-commands (``argparse`` sub-parsers)."""
    synth = commands.add_parser(
        "synth",
        help="render the synthetic benchmark",
        description="Render the synthetic benchmark: OUT/labels/*.csv and images under OUT/.",
    )
    synth.add_argument("out", type=Path, metavar="OUT", help="output folder")
    synth.add_argument("--scenes", type=int, help="number of scenes (default: module default)")
    synth.add_argument("--train-frames", type=int, help="train frames per scene")
    synth.add_argument("--test-frames", type=int, help="test frames per scene")
    synth.add_argument(
        "--test-offset",
        type=float,
        metavar="M",
        help="lateral offset of the test sequences from the route in metres, alternately "
        "left and right (default: 0, on the route)",
    )
    synth.add_argument(
        "--train-lane",
        type=float,
        metavar="M",
        help="lateral offset of the train sequences from the route in metres, alternately "
        "left and right (default: 0.5)",
    )
    synth.add_argument(
        "--val-lane",
        type=float,
        metavar="M",
        help="lateral offset (m, signed, within the train lanes) of the last train sequence of "
        "each scene, the validation split of data.val_sequences=1 (default: its lane; 0: "
        "between the lanes)",
    )
    synth.add_argument(
        "--val-walks",
        type=int,
        metavar="N",
        help="more validation sequences per scene, numbered after the test ones, each as long "
        "as the last train sequence and walking where it walks (default: 0; hold them out with "
        "data.val_walks=N)",
    )
    synth.add_argument(
        "--yaw-stray",
        type=float,
        metavar="RAD",
        help="how far each sequence's yaw strays from the route's heading (default: 0.15)",
    )
    synth.add_argument(
        "--stray",
        type=float,
        metavar="M",
        help="how far each camera strays horizontally from its lane (default: 0.1)",
    )
    synth.add_argument(
        "--lighting-change",
        type=float,
        metavar="S",
        help="strength in [0, 1] of lighting and exposure changing between and within "
        "sequences (default: 0, off)",
    )
    synth.add_argument(
        "--occluder-fraction",
        type=float,
        metavar="F",
        help="share in [0, 1] of frames with a person-sized box in front of the camera "
        "(default: 0, off)",
    )
    synth.add_argument(
        "--sensor-noise",
        type=float,
        metavar="STD",
        help="extra Gaussian sensor noise, std of values in [0, 1] (default: 0, off)",
    )
    synth.add_argument(
        "--motion-blur",
        type=float,
        metavar="PX",
        help="longest motion blur in pixels, each frame's random up to it (default: 0, off)",
    )
    synth.add_argument(
        "--plain-surfaces",
        type=float,
        metavar="F",
        help="share in [0, 1] of the surfaces (walls, floor, ceiling, boxes) plain-painted, "
        "no texture (default: 0, off)",
    )
    synth.add_argument(
        "--repeated-surfaces",
        type=float,
        metavar="F",
        help="share in [0, 1] of the surfaces covered by stair-, window- or tile-like periodic "
        "patterns of period 0.15-0.3 m (default: 0, off; with --plain-surfaces at most 1)",
    )
    synth.add_argument(
        "--glossy-surfaces",
        type=float,
        metavar="F",
        help="share in [0, 1] of the surfaces glossy, with highlights that move with the "
        "camera (default: 0, off)",
    )
    synth.add_argument(
        "--camera-pipeline",
        type=float,
        metavar="S",
        help="strength in [0, 1] of vignetting, gamma, auto-exposure and exposure and white "
        "balance drifting within each sequence (default: 0, off)",
    )
    synth.add_argument(
        "--jpeg-quality",
        type=int,
        metavar="Q",
        help="compress each image as JPEG at quality Q in [1, 100] and store the decoded "
        "pixels (default: 0, off)",
    )
    synth.add_argument(
        "--render-scale",
        type=int,
        metavar="K",
        help="render and store images K times the size, K in [1, 8], for the loaders to "
        "downsample (default: 1)",
    )
    synth.add_argument(
        "--poses",
        type=Path,
        nargs="+",
        metavar="LABELS.csv",
        help="render one image per row of these label files, at exactly its pose, in a world "
        "built around their camera positions (e.g. real Cambridge / 7-Scenes labels), with "
        "the surface, nuisance and capture options given",
    )
    synth.add_argument("--size", type=int, metavar="PX", help="image side in pixels")
    synth.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    synth.add_argument(
        "--overwrite",
        action="store_true",
        help="replace the dataset already in OUT (otherwise a non-empty OUT is refused)",
    )
    synth.set_defaults(run=run_synth)
