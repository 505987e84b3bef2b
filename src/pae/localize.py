"""`pae-localize RUN_DIR INPUT... --out poses.csv`: the poses of images from a finished run's
checkpoints, in the label-file format (pae.apps.localization)."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

EPILOG = """examples:
  pae-localize outputs/demo my_images/ --out poses.csv
  pae-localize outputs/demo DATA/labels/all_test.csv --root DATA --refine render_compare \\
      --out poses.csv
  pae-localize outputs/demo my_images/ --onnx outputs/demo/onnx --out poses.csv
INPUT: image files, folders of images (searched recursively) or label files (their img_path
read under --root, by default the run's data root; their poses only give the printed errors).
The teacher's estimates by default, or another APR's with --init FILE; --refine
render_compare refines them against the run's scene model (with the gate, steps and, for a
multi-scene teacher, the scene decision the run chose on val for its teacher; another APR's
starts with those chosen on val for starts of any error scale: --init-gate), --refine refined
(knn_mean, student, or an entry of the run's refine.alternatives) with its student."""


def parser() -> argparse.ArgumentParser:
    """The command line of pae-localize."""
    parse = argparse.ArgumentParser(
        prog="pae-localize",
        description="Poses of images from a finished pae-train run's checkpoints.",
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parse.add_argument("run_dir", type=Path, help="a finished run directory (e.g. outputs/demo)")
    parse.add_argument("inputs", nargs="+", help="image files, folders or label files")
    parse.add_argument(
        "--out",
        type=Path,
        required=True,
        help="the file to write (--format ace: the folder that gets poses/)",
    )
    parse.add_argument(
        "--format",
        default="csv",
        choices=("csv", "lines", "hloc", "ace"),
        help="csv: a pae label file; lines: 'NAME x y z qw qx qy qz' per image; ace: "
        "OUT/poses/<name>.pose.txt, a 4x4 matrix per image (all camera-to-world, pae's axes); "
        "hloc: 'NAME qw qx qy qz tx ty tz' world-to-camera, as hloc's localize_sfm writes",
    )
    parse.add_argument("--refine", default="teacher", help="the method (default: teacher)")
    parse.add_argument("--root", type=Path, help="dataset root of a label file's img_path")
    parse.add_argument("--focal", type=float, help="focal length (px) of the images on disk")
    parse.add_argument(
        "--batch-size",
        type=int,
        help="images per teacher pass (default: the run's data.eval_batch_size, whose "
        "rounding the run's own figures carry)",
    )
    parse.add_argument("--device", default="cpu", help="torch device (default: cpu)")
    parse.add_argument(
        "--onnx",
        type=Path,
        metavar="EXPORT",
        help="run the teacher exported by pae-export (its folder or teacher.onnx) with "
        "onnxruntime on the CPU instead of its checkpoint (--refine teacher only)",
    )
    parse.add_argument(
        "--init",
        type=Path,
        metavar="FILE",
        help="refine the poses in FILE instead of the teacher's (--init-format), matched to "
        "the images by the longest common path suffix",
    )
    parse.add_argument(
        "--init-format",
        choices=("pae", "lines", "hloc", "matrix"),
        help="what --init FILE holds: pae, a pae label file; lines, 'NAME x y z qw qx qy qz' "
        "camera-to-world; hloc, 'NAME qw qx qy qz tx ty tz' world-to-camera (hloc's "
        "localize_sfm); matrix, NAME and a row-major 4x4 camera-to-world matrix (default: "
        "what FILE's header states, else matrix; lines of 7 numbers must state theirs)",
    )
    parse.add_argument(
        "--init-axes",
        default="pae",
        choices=("pae", "opengl"),
        help="camera axes of --init's orientations: pae (x right, y down, z forward) or "
        "opengl (y up, z backward: DFNet's and NeFeS's result files)",
    )
    parse.add_argument(
        "--init-gate",
        default="auto",
        choices=("auto", "run", "any"),
        help="render_compare from --init: run, the gate and steps the run chose on val for its "
        "own teacher; any, those chosen on the run's validation split for starts of any error "
        "scale (another APR's: a start is refined only where that helps); auto: run where "
        "FILE holds the teacher's own estimates, else any",
    )
    parse.add_argument(
        "--sequences",
        nargs="?",
        const="folders",
        choices=("folders", "column"),
        help="render_compare: refine each recording with its frames' order (the sequence "
        "passes and median window, --sequence-passes and --sequence-window); each frame's "
        "recording from the folder it sits in (folders, the default) or the --init file's "
        "seq column (column), its frames ordered by name",
    )
    parse.add_argument(
        "--sequence-passes",
        type=int,
        help="with --sequences: propagation passes (default: the run's recorded or "
        "configured render_compare.sequence_passes)",
    )
    parse.add_argument(
        "--sequence-window",
        type=int,
        help="with --sequences: the median window over frames, odd (default: the run's)",
    )
    parse.add_argument(
        "--sequence-fit",
        choices=("median", "hampel"),  # pae.render_compare.sequences.WINDOW_FITS
        help="with --sequences: what the window does, median (each pose its window's "
        "median) or hampel (only a pose off its window's median); default: the run's",
    )
    parse.add_argument(
        "--summary",
        type=Path,
        metavar="FILE",
        help="also write a JSON of the run: method, gate, the calibration applied (its "
        "correspondence stage too), the accepted share, the shares the stage solved and "
        "moved, the recordings and the seconds per query",
    )
    return parse


def main(argv: list[str] | None = None) -> int:
    """Localise the inputs with the run's checkpoints and write ``--out`` atomically."""
    args = parser().parse_args(argv)
    from pae.core.console import quiet_third_party
    from pae.core.error_reporting import reporting_errors
    from pae.core.threads import configure_threads

    quiet_third_party()
    with reporting_errors("pae-localize"):
        print(configure_threads().summary(), file=sys.stderr)
        localize(args)
    return 0


def localize(args: argparse.Namespace) -> None:
    """What main runs once the arguments are parsed."""
    import torch
    from omegaconf import OmegaConf

    from pae.apps import localization as loc
    from pae.apps.any_start import calibration_record
    from pae.apps.match_inputs import match_queries
    from pae.apps.queries import gather_queries, output_table, summary_line
    from pae.apps.recordings import recordings_of, reordered, sequence_options
    from pae.core.atomic import atomic_write, check_writable_dir, check_writable_file
    from pae.core.checkpoints import load_teacher
    from pae.core.console import Progress
    from pae.core.errors import ConfigError
    from pae.data.pose_files import write_poses
    from pae.render_compare.correspondences import MatchQueries, MatchSettings, TrainImages

    # before any work: a finished run is never lost to its output
    if args.format == "ace":
        check_writable_dir(args.out, "--out")
    else:
        check_writable_file(args.out, "--out")
    if args.summary is not None:
        check_writable_file(args.summary, "--summary")
    run = loc.read_run(args.run_dir)
    methods = loc.methods_of(run)
    method = args.refine
    if method not in methods:
        raise ConfigError(f"--refine {method}: unknown method; choose one of {methods}")
    if args.focal is not None and args.focal <= 0:
        raise ConfigError(f"--focal must be > 0 px, got {args.focal}")
    if args.batch_size is None:
        args.batch_size = int(OmegaConf.select(run.config, "data.eval_batch_size", default=64))
    if args.batch_size < 1:
        raise ConfigError(f"--batch-size must be >= 1, got {args.batch_size}")
    if method == loc.RENDER_COMPARE:
        loc.scene_model_path(run)  # before any work: the run has one
    elif method != loc.TEACHER:
        run.checkpoint("student", method)
    teacher_path = loc.teacher_checkpoint(run, method)
    if teacher_path is None and (method != loc.RENDER_COMPARE or args.init is None):
        raise ConfigError(
            f"{run.folder}: the run has no teacher (its steps are {run.steps}): only "
            "--refine render_compare --init FILE, from another APR's poses"
        )
    if args.sequences and method != loc.RENDER_COMPARE:
        raise ConfigError("--sequences: only --refine render_compare uses recordings")
    sequence_flags = (args.sequence_passes, args.sequence_window, args.sequence_fit)
    if not args.sequences and sequence_flags != (None, None, None):
        raise ConfigError(
            "--sequence-passes, --sequence-window and --sequence-fit apply with --sequences only"
        )
    if args.onnx is not None and method != loc.TEACHER:
        raise ConfigError(f"--onnx runs the teacher only, not --refine {method}")
    queries = gather_queries(args.inputs, args.root or run.data_root)
    if teacher_path is None:
        teacher = None
    elif args.onnx is not None:
        from pae.apps.onnx_teacher import load_onnx_teacher

        teacher = load_onnx_teacher(args.onnx, run, teacher_path)
    else:
        teacher = load_teacher(teacher_path)
    data = loc.data_module(run, cache_images=False)  # its labels and camera: no image read
    if teacher is None:
        data.setup()
    scene_names = data.scene_names if teacher is None else teacher.scene_names
    intrinsics = None
    width = None
    if method == loc.RENDER_COMPARE:
        width = loc.compare_width(loc.render_compare_settings(run)[0])

        def intrinsics(size: tuple[int, int], focal: object) -> torch.Tensor:
            return loc.query_intrinsics(
                data.camera, size, data.shorter_edge, data.crop, focal, args.focal
            )

        def uncropped(size: tuple[int, int], focal: object, shorter: int) -> torch.Tensor:
            return loc.query_intrinsics(data.camera, size, shorter, None, focal, args.focal)

    starts = starts_file = None
    if args.init is not None:  # read before any work: a bad row is one line, nothing run
        from pae.data.starts import placed_starts, read_starts

        starts_file = read_starts(args.init, args.init_axes, args.init_format)
        starts = placed_starts(queries.shown, starts_file, str(args.init), scene_names)
    device = torch.device(args.device)
    emit = lambda line: print(line, file=sys.stderr, flush=True)  # noqa: E731
    recordings = options = None
    if args.sequences:
        recordings = recordings_of(queries.shown, args.sequences, starts_file, str(args.init or ""))
        options = sequence_options(run, *sequence_flags)
    summary = {"method": method, "run": str(run.folder), "init": args.init and str(args.init)}
    started = time.perf_counter()
    found = loc.estimate(
        None if teacher is None else teacher.model,
        queries,
        data,
        intrinsics,
        width,
        args.batch_size,
        device,
        Progress(f"pae-localize: {method}", "images", emit),
    )
    gate = "run"
    if starts is not None:
        pose, scene = starts
        own = teacher is not None and loc.are_estimates_of(pose, found.pose)
        gate = args.init_gate if args.init_gate != "auto" else ("run" if own else "any")
        found = found._replace(pose=pose, scene=found.scene if scene is None else scene)
        emit(f"pae-localize: {len(pose)} starts from {args.init} (render_compare gate: {gate})")
    if method == loc.TEACHER:
        poses = found.pose
    elif method == loc.RENDER_COMPARE:
        if f"test/{loc.RENDER_COMPARE}/accept_margin" not in run.metrics and gate == "run":
            emit(
                f"pae-localize: warning: {run.folder / 'metrics.json'} records no "
                "render_compare gate or steps: the configured ones are used"
            )
        emit(f"pae-localize: render_compare of {len(found.pose)} images")
        model = None if teacher is None else teacher.model.eval()

        def matching(match: MatchSettings, train: TrainImages | None) -> MatchQueries | None:
            stated = (run.folder, run.config)
            return match_queries(stated, queries, data, model, uncropped, match, train)

        in_order = None
        if recordings is not None and options is not None:
            emit(f"pae-localize: {len(recordings.names)} recordings ({options})")
            found = reordered(found, recordings.order)
            in_order = (recordings.ids, options)
        refined = loc.render_compare(
            run, None if model is None else model.to(device), found, device, gate, matching,
            in_order,
        )  # fmt: skip
        poses, scenes, accepted = refined.poses, refined.scenes, refined.accepted
        if recordings is not None:
            poses, scenes, accepted = map(recordings.restore, (poses, scenes, accepted))
            found = reordered(found, torch.argsort(recordings.order))
        found = found._replace(scene=scenes)
        summary |= {
            "gate": gate,
            "calibration": calibration_record(refined.calibration),
            "accepted_share": float(accepted.float().mean()),
            "calibrate_s": refined.calibrate_s,
        }
        if refined.stage_shares is not None:  # the queries with no usable match, counted
            found_share, kept_share = refined.stage_shares
            summary |= {"keypoints_found_share": found_share, "other_start_kept_share": kept_share}
    else:
        poses = loc.student_poses(run, method, teacher.model.cpu(), found)
    seconds = time.perf_counter() - started
    table = output_table(queries, poses, found.scene, scene_names)
    write_poses(args.out, table, args.format)
    if args.summary is not None:
        summary |= {
            "images": len(table),
            "recordings": None if recordings is None else len(recordings.names),
            "seconds": seconds,
            "ms_per_query": 1000 * (seconds - summary.get("calibrate_s", 0.0)) / len(table),
        }
        with atomic_write(args.summary) as handle:
            json.dump(summary, handle, indent=1)
    if queries.labelled:
        print(summary_line(method, poses, queries, scene_names, found.scene))
    print(f"poses: {args.out} ({len(table)} images, {method}, {args.format})")


if __name__ == "__main__":
    raise SystemExit(main())
