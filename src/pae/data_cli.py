"""``pae-data``: make, convert and check label files.

::

    pae-data synth OUT [--scenes N --train-frames N --test-frames N --test-offset M
                        --train-lane M --val-lane M --yaw-stray RAD --stray M --size PX
                        --seed S]
                       [--lighting-change S --occluder-fraction F --sensor-noise STD
                        --motion-blur PX]
                       [--plain-surfaces F --repeated-surfaces F --glossy-surfaces F
                        --camera-pipeline S --jpeg-quality Q --render-scale K] [--overwrite]
    pae-data synth OUT --poses LABELS.csv [LABELS.csv ...] [--size PX --seed S] [--overwrite]
    pae-data convert {cambridge,7scenes} RAW_ROOT OUT_DIR
    pae-data convert authors-csv LABELS.csv OUT_DIR
    pae-data convert ace ROOT OUT_DIR [--scene NAME]
    pae-data convert colmap MODEL_DIR IMAGE_DIR OUT_DIR [--split-list FILE | --every K |
                            --test-folders NAME ...] [--scale S] [--scene NAME]
    pae-data convert kapture ROOT OUT_DIR [--train NAME] [--test NAME] [--scene NAME]
    pae-data check LABELS.csv [LABELS.csv ...] ROOT
    pae-data store LABELS.csv [LABELS.csv ...] ROOT --store STORE [--shorter-edge PX]
    pae-data audit-guess --test TEST.csv [...] --train TRAIN.csv [...] [--sigma M --k K --seed S]

Bad input ends with exit status 1 and a one-line ``pae-data: error: ...`` message on stderr.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pae.apps.synthesis import add_synth_command, run_synth
from pae.core.errors import LabelError, LabelWarning, OrientationWarning
from pae.core.quaternion_sign import canonical_sign
from pae.core.threads import configure_threads
from pae.data.label_images import find_image_problems
from pae.data.labels import (
    FOCAL_COLUMN,
    LabelTable,
    focal_column_mismatch,
    read_labels,
    read_labels_lenient,
    write_labels,
)
from pae.data.orientation import conjugate

if TYPE_CHECKING:
    from pae.data.converted import SceneFrames

PROG = "pae-data"


def _convert_authors_csv(source: Path, out_dir: Path) -> int:
    """A label file whose orientations are world-to-camera (the authors' Cambridge CSVs) ->
    ``out_dir/<its name>`` with camera-to-world orientations (conjugated)."""
    table = _read_tables([source], world_to_camera=True)
    quaternions = canonical_sign(conjugate(table.poses[:, 3:]))
    poses = np.concatenate([table.poses[:, :3], quaternions], 1)
    out = out_dir / source.name
    if out.resolve() == source.resolve():
        raise ValueError(f"{out}: would overwrite its source; give another OUT_DIR")
    out_dir.mkdir(parents=True, exist_ok=True)
    write_labels(out, dataclasses.replace(table, poses=poses))
    print(f"wrote {len(table)} rows with camera-to-world orientations to {out}")
    return 0


def _convert(args: argparse.Namespace) -> int:
    from pae.core.atomic import check_writable_dir
    from pae.data.raw import convert_raw

    check_writable_dir(args.out_dir, "OUT_DIR")
    if args.dataset == "authors-csv":
        return _convert_authors_csv(args.raw_root, args.out_dir)

    written = convert_raw(args.dataset, args.raw_root, args.out_dir)
    scene_files = [name for name in written if not name.startswith("all_")]
    scenes = sorted({name.rsplit("_", 1)[0] for name in scene_files})
    print(f"wrote {len(written)} label files for {len(scenes)} scenes to {args.out_dir}:")
    width = max(len(name) for name in written)
    for name, rows in written.items():
        print(f"  {name:<{width}}  {rows:>7} rows")
    print(f"img_path is relative to {args.raw_root}: use it as data.root")
    return 0


def _convert_ace(args: argparse.Namespace) -> int:
    from pae.core.atomic import check_writable_dir
    from pae.data.ace import read_ace_scene

    check_writable_dir(args.out_dir, "OUT_DIR")
    frames = read_ace_scene(args.root)
    return _write_converted(frames, args.scene or args.root.resolve().name, args.root, args)


def _convert_colmap(args: argparse.Namespace) -> int:
    from pae.core.atomic import check_writable_dir
    from pae.data.colmap import read_colmap_scene

    check_writable_dir(args.out_dir, "OUT_DIR")
    frames = read_colmap_scene(
        args.model_dir,
        args.image_dir,
        scale=args.scale,
        split_list=args.split_list,
        every=args.every,
        test_folders=args.test_folders,
    )
    print(
        f"COLMAP's units are arbitrary: positions were multiplied by {args.scale:g} and pae "
        "reads them as metres (--scale S makes one unit S metres)"
    )
    if args.every is not None:
        print(
            f"{PROG}: warning: --every {args.every} puts each test image between train images "
            "of the same walk, a frame or two away: a leaky split for localisation (the test "
            "figures flatter a method that recalls its train views); --test-folders NAME or "
            "--split-list FILE holds out whole walks",
            file=sys.stderr,
        )
    scene = args.scene or args.image_dir.resolve().name
    return _write_converted(frames, scene, args.image_dir, args)


def _convert_kapture(args: argparse.Namespace) -> int:
    from pae.core.atomic import check_writable_dir
    from pae.data.kapture import read_kapture_scene

    check_writable_dir(args.out_dir, "OUT_DIR")
    frames = read_kapture_scene(args.root, args.train, args.test)
    return _write_converted(frames, args.scene or args.root.resolve().name, args.root, args)


def _write_converted(frames: SceneFrames, scene: str, root: Path, args: argparse.Namespace) -> int:
    """Write a converted scene's label files and print what they hold, its scale and up
    direction, its camera and the overrides that train on it."""
    from pae.data.converted import camera_of, camera_override, scene_shape, write_scene

    if scene == "all" or "/" in scene or not scene:
        raise ValueError(f"--scene {scene!r}: a scene name is not empty, 'all' or a path")
    camera = camera_of(frames)
    written = write_scene(args.out_dir, scene, frames)
    print(f"wrote {len(written)} label files for scene {scene} to {args.out_dir}:")
    width = max(len(name) for name in written)
    for name, rows in written.items():
        print(f"  {name:<{width}}  {rows:>7} rows")
    for line in scene_shape(frames.poses):
        print(line)
    low, high = float(frames.focal.min()), float(frames.focal.max())
    print(
        f"camera: {camera.width}x{camera.height} px, principal point ({camera.cx:g}, "
        f"{camera.cy:g}), focal lengths {low:g} to {high:g} px (each row's own: focal column)"
    )
    overrides = [f"data.root={root}", f"'{camera_override(camera)}'"]
    if args.out_dir.resolve() != (root / "labels").resolve():
        overrides[1:1] = [
            f"data.train_labels={args.out_dir / 'all_train.csv'}",
            f"data.test_labels={args.out_dir / 'all_test.csv'}",
        ]
    print(
        f"img_path is relative to {root}; train on it: pae-train data=converted "
        + " ".join(overrides)
    )
    return 0


def _check(args: argparse.Namespace) -> int:
    """Every row of each label file, then whether the files agree on the focal column."""
    failed, tables = False, []
    for labels in args.labels:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", LabelWarning)
            table, label_errors = read_labels_lenient(labels)
        for warning in caught:
            print(f"{PROG}: warning: {warning.message}", file=sys.stderr)
        image_problems = find_image_problems(table, args.root)
        problems = [str(error) for error in label_errors] + image_problems
        rows = len(table) + len(label_errors)
        tables.append(table)
        if problems:
            for problem in problems:
                print(problem)
            print(f"FAILED: {len(problems)} of {rows} rows in {labels} have problems")
            failed = True
        else:
            print(f"OK: {rows} rows, {len(table.scene_names)} scenes")
    mismatch = focal_column_mismatch(tables)
    if mismatch is not None:
        print(mismatch)
        print(f"FAILED: the {len(tables)} label files disagree on the {FOCAL_COLUMN} column")
        failed = True
    return 1 if failed else 0


def _read_tables(paths: Sequence[Path], world_to_camera: bool = False) -> LabelTable:
    """The rows of all label files; repairs are reported as one warning line per file
    (``world_to_camera``: files known to be, not warned about it)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", LabelWarning)
        table = LabelTable.concat(read_labels(path) for path in paths)
    for warning in caught:
        if world_to_camera and issubclass(warning.category, OrientationWarning):
            continue
        print(f"{PROG}: warning: {warning.message}", file=sys.stderr)
    return table


def _store(args: argparse.Namespace) -> int:
    """Decode every image of the label files into the store folder."""
    from pae.core.threads import current_budget
    from pae.data.image_store import ImageStore

    table = _read_tables(args.labels)
    paths = list(dict.fromkeys(str(args.root / path) for path in table.img_path))
    started = time.perf_counter()
    decoded = ImageStore(args.store).fill(paths, args.shorter_edge, current_budget().threads)
    seconds = time.perf_counter() - started
    print(f"{decoded} of {len(paths)} images decoded into {args.store} in {seconds:.1f} s")
    return 0


def _audit_guess(args: argparse.Namespace) -> int:
    from pae.refine.audit import format_guess_audit, guess_audit

    test, train = _read_tables(args.test), _read_tables(args.train)
    rows = guess_audit(test, train, sigma_m=args.sigma, k=args.k, seed=args.seed)
    print(format_guess_audit(rows, args.sigma, args.k))
    return 0


def _add_command(
    commands: argparse._SubParsersAction,
    name: str,
    summary: str,
    description: str,
    run: Callable[[argparse.Namespace], int],
    paths: Sequence[str] = (),
) -> argparse.ArgumentParser:
    """The sub-command ``name`` of ``commands`` (``summary`` in the list of commands,
    ``description`` in its own help), which runs ``run`` on the parsed arguments; ``paths``
    name its leading positional arguments, each a Path shown in upper case."""
    command = commands.add_parser(name, help=summary, description=description)
    for path in paths:
        command.add_argument(path, type=Path, metavar=path.upper())
    command.set_defaults(run=run)
    return command


def _add_labels_and_root(command: argparse.ArgumentParser) -> None:
    """The positional arguments of a command over label files and their images."""
    command.add_argument("labels", type=Path, nargs="+", metavar="LABELS.csv")
    command.add_argument("root", type=Path, metavar="ROOT", help="dataset root of img_path")


def build_parser() -> argparse.ArgumentParser:
    """The ``pae-data`` argument parser."""
    parser = argparse.ArgumentParser(prog=PROG, description="Make, convert and check label files.")
    commands = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    add_synth_command(commands)

    convert = commands.add_parser(
        "convert",
        help="write label files from a raw download, an ACE-layout folder, a COLMAP model or "
        "kapture folders",
        description="Write label files (OUT_DIR/<scene>_{train,test}.csv and "
        "OUT_DIR/all_{train,test}.csv) from another layout.",
    )
    formats = convert.add_subparsers(dest="dataset", required=True, metavar="FORMAT")
    every_scene = "; every scene folder under RAW_ROOT, img_path relative to it"
    for name, about, where in (
        (
            "cambridge",
            "dataset_{train,test}.txt (world-to-camera quaternions, conjugated)",
            every_scene,
        ),
        ("7scenes", "TrainSplit.txt / TestSplit.txt with frame-*.pose.txt", every_scene),
        (
            "authors-csv",
            "RAW_ROOT is one label file whose orientations are world-to-camera, written to "
            "OUT_DIR camera-to-world",
            "",
        ),
    ):
        _add_command(formats, name, about, f"{about}{where}.", _convert, ("raw_root", "out_dir"))

    ace = _add_command(
        formats,
        "ace",
        "the ACE / DSAC* layout: {train,test}/{rgb,poses,calibration}",
        "One scene in the ACE / DSAC* layout: ROOT/{train,test}/rgb/* images, "
        "poses/*.txt 4x4 camera-to-world matrices, calibration/*.txt focal lengths (px) or "
        "3x3 matrices; img_path relative to ROOT, each row with its own focal length.",
        _convert_ace,
        ("root", "out_dir"),
    )
    ace.add_argument("--scene", metavar="NAME", help="the scene's name (default: ROOT's name)")

    colmap = _add_command(
        formats,
        "colmap",
        "a COLMAP model (cameras, images; text or binary) and its images",
        "A COLMAP sparse model (MODEL_DIR: cameras and images, .bin or .txt) of "
        "the images under IMAGE_DIR: camera-to-world poses, each image's focal length, "
        "img_path relative to IMAGE_DIR. Pinhole cameras only (a distorted one is refused "
        "with the colmap image_undistorter command). Test images: those under test/ (the "
        "rest under train/), or as an option says.",
        _convert_colmap,
        ("model_dir", "image_dir", "out_dir"),
    )
    split = colmap.add_mutually_exclusive_group()
    split.add_argument(
        "--split-list",
        type=Path,
        metavar="FILE",
        help="the test images, one name per line as in the model; the rest are train",
    )
    split.add_argument(
        "--every", type=int, metavar="K", help="every K-th image in name order is a test image"
    )
    split.add_argument(
        "--test-folders",
        nargs="+",
        metavar="NAME",
        help="the images under these top folders of IMAGE_DIR (held-out sequences) are test",
    )
    colmap.add_argument(
        "--scale",
        type=float,
        default=1.0,
        metavar="S",
        help="multiply positions by S: COLMAP's units are arbitrary and pae reads metres "
        "(S = a known distance in metres / the same distance in the model; default: 1)",
    )
    colmap.add_argument(
        "--scene", metavar="NAME", help="the scene's name (default: IMAGE_DIR's name)"
    )

    kapture = _add_command(
        formats,
        "kapture",
        "kapture folders (sensors.txt, records_camera.txt, trajectories.txt): train and test",
        "Two kapture folders under ROOT, the train split's (--train, default mapping) and the "
        "test split's (--test, default query): each one's sensors/sensors.txt cameras "
        "(pinhole), records_camera.txt images under sensors/records_data/ and "
        "trajectories.txt world-to-camera poses, written camera-to-world; img_path relative "
        "to ROOT, each row with its own focal length.",
        _convert_kapture,
        ("root", "out_dir"),
    )
    kapture.add_argument(
        "--train", default="mapping", metavar="NAME", help="the train split's kapture folder"
    )
    kapture.add_argument(
        "--test", default="query", metavar="NAME", help="the test split's kapture folder"
    )
    kapture.add_argument("--scene", metavar="NAME", help="the scene's name (default: ROOT's name)")

    check = _add_command(
        commands,
        "check",
        "validate label files and their images",
        "Validate every row of each LABELS.csv (its focal length, if any, "
        "against the width of its images) and decode its image under ROOT; with the files of "
        "several splits, check that all or none have a focal column; exit 1 listing every "
        "problem.",
        _check,
    )
    _add_labels_and_root(check)

    store = _add_command(
        commands,
        "store",
        "decode the images of label files once, into a data.image_store folder",
        "Decode and resize every image of each LABELS.csv (under ROOT) that the STORE "
        "folder does not hold yet, on pae's threads, so that runs with data.image_store=STORE "
        "read them back instead of decoding them (pae.data.image_store).",
        _store,
    )
    _add_labels_and_root(store)
    store.add_argument("--store", type=Path, required=True, metavar="STORE", help="the folder")
    store.add_argument(
        "--shorter-edge",
        type=int,
        default=256,
        metavar="PX",
        help="the size runs read them at, data.shorter_edge (default: 256)",
    )

    audit = _add_command(
        commands,
        "audit-guess",
        "the random-guess check from label files alone (no images, no PAE)",
        "Per scene: a guess around each test pose (true position + Gaussian "
        "noise, true orientation) and the mean of its k nearest poses, retrieved from the test "
        "poses (the authors' public scripts) and from the train poses.",
        _audit_guess,
    )
    audit.add_argument("--test", type=Path, nargs="+", required=True, metavar="TEST.csv")
    audit.add_argument("--train", type=Path, nargs="+", required=True, metavar="TRAIN.csv")
    audit.add_argument("--sigma", type=float, default=1.0, metavar="M", help="noise std (m)")
    audit.add_argument("--k", type=int, default=3, help="neighbours (default: 3)")
    audit.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``pae-data``; returns the exit status (argparse usage errors exit with 2)."""
    args = build_parser().parse_args(argv)
    try:
        budget = configure_threads(load_libraries=False)
        if args.run in (run_synth, _store):  # the commands whose work runs on those threads
            print(budget.summary(), file=sys.stderr)
        return args.run(args)
    except (LabelError, OSError, ValueError) as error:
        message = " ".join(str(error).split()) or type(error).__name__
        print(f"{PROG}: error: {message}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    raise SystemExit(main())
