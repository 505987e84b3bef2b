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


def run_synth(args: argparse.Namespace) -> int:
    """``pae-data synth``: render the benchmark (or the rows of ``--poses``) into ``OUT``."""
    from pae import synthetic

    def chosen(value: int | float | None, default: int | float) -> int | float:
        return default if value is None else value

    if args.poses:
        ignored = [
            flag
            for flag, value in (
                ("--scenes", args.scenes),
                ("--train-frames", args.train_frames),
                ("--test-frames", args.test_frames),
                ("--test-offset", args.test_offset),
                ("--train-lane", args.train_lane),
                ("--val-lane", args.val_lane),
                ("--val-walks", args.val_walks),
                ("--yaw-stray", args.yaw_stray),
                ("--stray", args.stray),
                ("--lighting-change", args.lighting_change),
                ("--occluder-fraction", args.occluder_fraction),
                ("--sensor-noise", args.sensor_noise),
                ("--motion-blur", args.motion_blur),
                ("--plain-surfaces", args.plain_surfaces),
                ("--repeated-surfaces", args.repeated_surfaces),
                ("--glossy-surfaces", args.glossy_surfaces),
                ("--camera-pipeline", args.camera_pipeline),
                ("--jpeg-quality", args.jpeg_quality),
                ("--render-scale", args.render_scale),
            )
            if value is not None
        ]
        if ignored:
            raise ValueError(f"--poses renders the given rows only: drop {', '.join(ignored)}")
        from pae.synthetic.poses import write_dataset_at_poses

        dataset = write_dataset_at_poses(
            args.out,
            args.poses,
            size=chosen(args.size, synthetic.DEFAULT_SIZE),
            seed=args.seed,
            overwrite=args.overwrite,
            progress=_render_progress(args.out),
        )
    else:
        dataset = synthetic.write_synthetic_dataset(
            args.out,
            scenes=chosen(args.scenes, synthetic.DEFAULT_SCENES),
            train_frames=chosen(args.train_frames, synthetic.DEFAULT_TRAIN_FRAMES),
            test_frames=chosen(args.test_frames, synthetic.DEFAULT_TEST_FRAMES),
            size=chosen(args.size, synthetic.DEFAULT_SIZE),
            seed=args.seed,
            test_offset_m=chosen(args.test_offset, synthetic.DEFAULT_TEST_OFFSET_M),
            train_lane_m=chosen(args.train_lane, synthetic.DEFAULT_TRAIN_LANE_M),
            yaw_stray_rad=chosen(args.yaw_stray, synthetic.DEFAULT_YAW_STRAY_RAD),
            stray_m=chosen(args.stray, synthetic.DEFAULT_STRAY_M),
            val_lane_m=args.val_lane,
            val_walks=chosen(args.val_walks, 0),
            lighting_change=chosen(args.lighting_change, 0.0),
            occluder_fraction=chosen(args.occluder_fraction, 0.0),
            sensor_noise_std=chosen(args.sensor_noise, 0.0),
            motion_blur_px=chosen(args.motion_blur, 0.0),
            plain_surface_share=chosen(args.plain_surfaces, 0.0),
            repeated_surface_share=chosen(args.repeated_surfaces, 0.0),
            glossy_surface_share=chosen(args.glossy_surfaces, 0.0),
            camera_pipeline=chosen(args.camera_pipeline, 0.0),
            jpeg_quality=chosen(args.jpeg_quality, 0),
            render_scale=chosen(args.render_scale, 1),
            overwrite=args.overwrite,
            progress=_render_progress(args.out),
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
        "built around their camera positions (e.g. real Cambridge / 7-Scenes labels)",
    )
    synth.add_argument("--size", type=int, metavar="PX", help="image side in pixels")
    synth.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    synth.add_argument(
        "--overwrite",
        action="store_true",
        help="replace the dataset already in OUT (otherwise a non-empty OUT is refused)",
    )
    synth.set_defaults(run=run_synth)
