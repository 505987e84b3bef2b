"""`pae-localize RUN_DIR INPUT... --out poses.csv`: the poses of images from a finished run's
checkpoints, in the label-file format (pae.apps.localization)."""

from __future__ import annotations

import argparse
import sys
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
    from pae.apps.queries import gather_queries
    from pae.core.atomic import check_writable_dir, check_writable_file
    from pae.core.checkpoints import load_teacher
    from pae.core.console import Progress
    from pae.core.errors import ConfigError
    from pae.data.pose_files import write_poses

    # before any work: a finished run is never lost to its output
    if args.format == "ace":
        check_writable_dir(args.out, "--out")
    else:
        check_writable_file(args.out, "--out")
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
    step = {loc.RENDER_COMPARE: "scene_model", loc.TEACHER: None}.get(method, "student")
    if step is not None:
        teacher_path = run.checkpoint(step, method)
    elif "teacher" in run.steps:
        teacher_path = run.checkpoint("teacher", method)
    else:  # a later step's checkpoint holds a copy of its teacher
        teacher_path = run.checkpoint(run.steps[0], method)
    if args.onnx is not None and method != loc.TEACHER:
        raise ConfigError(f"--onnx runs the teacher only, not --refine {method}")
    queries = gather_queries(args.inputs, args.root or run.data_root)
    if args.onnx is not None:
        from pae.apps.onnx_teacher import load_onnx_teacher

        teacher = load_onnx_teacher(args.onnx, run, teacher_path)
    else:
        teacher = load_teacher(teacher_path)
    data = loc.data_module(run)
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

    starts = None
    if args.init is not None:  # read before any work: a bad row is one line, nothing run
        from pae.data.starts import starts_for

        starts = starts_for(
            queries.shown, args.init, teacher.scene_names, args.init_axes, args.init_format
        )
    device = torch.device(args.device)
    emit = lambda line: print(line, file=sys.stderr, flush=True)  # noqa: E731
    found = loc.estimate(
        teacher.model,
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
        own = loc.are_estimates_of(pose, found.pose)
        gate = args.init_gate if args.init_gate != "auto" else ("run" if own else "any")
        found = found._replace(pose=pose, scene=found.scene if scene is None else scene)
        emit(f"pae-localize: {len(pose)} starts from {args.init} (render_compare gate: {gate})")
    if method == loc.TEACHER:
        poses = found.pose
    elif method == loc.RENDER_COMPARE:
        if f"test/{loc.RENDER_COMPARE}/accept_margin" not in run.metrics:
            emit(
                f"pae-localize: warning: {run.folder / 'metrics.json'} records no "
                "render_compare gate or steps: the configured ones are used"
            )
        emit(f"pae-localize: render_compare of {len(found.pose)} images")
        matching = loc.match_queries(run, queries, data, teacher.model.eval(), uncropped)
        poses, scenes = loc.render_compare(
            run, teacher.model.to(device), found, device, gate, matching
        )
        found = found._replace(scene=scenes)
    else:
        poses = loc.student_poses(run, method, teacher.model.cpu(), found)
    table = loc.output_table(queries, poses, found.scene, teacher.scene_names)
    write_poses(args.out, table, args.format)
    if queries.labelled:
        print(loc.summary_line(method, poses, queries, teacher.scene_names, found.scene))
    print(f"poses: {args.out} ({len(table)} images, {method}, {args.format})")


if __name__ == "__main__":
    raise SystemExit(main())
