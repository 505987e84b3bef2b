"""Render-and-compare from real APRs' estimates on every real camera geometry, through the
product's own commands.

For each 7-Scenes scene and the four Cambridge Landmarks scenes of the estimate files:
``pae-train experiment=real_starts`` (synthetic images at every pose of the real label files,
no thinning, and the scene model fitted to the train images), then for each APR
``pae-localize RUN TEST_LABELS --init STARTS --refine render_compare`` (the gate, first steps,
filter and surface share chosen on the run's validation split for starts of any error scale,
kept in the run), each image on its own and, with ``--recordings``, each test recording with
its frames' order (``--sequences``). A start carries its image's real error: the APR's
estimate against the file's ground truth, taken in the camera frame
(``dt = R_gt^T (t_apr - t_gt)``, ``dR = R_gt^T R_apr``) and applied to the label file's pose of
the same image; run.py writes those starts as a label file, runs the two commands and scores
what pae-localize wrote. Finished scenes (``OUT/<scene>/real_starts_<APR>.json``) are skipped;
``--recordings`` on a scene refined per image only adds its recordings' figures; a
pae-localize pass whose poses and summary are already in the run (``RUN/<mode>_<APR>.csv``
and ``.json``, from the same starts file and images) is read back, not run again.
``--every K`` refines every K-th test image only (the rows of the label file in its order,
the same images for the start, NeFeS50 and the audit; each recording keeps its order), for
the scenes whose thousands of test images a table on two cores cannot afford otherwise.

    python experiments/render_compare_real_starts/run.py --labels ../shared/reference/labels \\
        --estimates ../shared/reference/estimates --out outputs/render_compare_real_starts
    python experiments/render_compare_real_starts/table.py outputs/render_compare_real_starts
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

from pae.apps.any_start import CALIBRATION_FILE, val_figures
from pae.apps.localization import (
    data_module,
    read_run,
    render_compare_settings,
    scene_model_path,
    split_queries,
)
from pae.core.atomic import atomic_write
from pae.core.checkpoints import load_scene_model
from pae.core.geometry import pose_errors, transfer_error
from pae.data.labels import LabelTable, read_labels, write_labels
from pae.data.starts import match_starts, read_starts
from pae.render_compare import ACCEPT_ALL, Calibration, Queries, refine

SCENES = {
    "7Scenes": ("chess", "fire", "heads", "office", "pumpkin", "redkitchen", "stairs"),
    "Cambridge": ("KingsCollege", "OldHospital", "ShopFacade", "StMarysChurch"),
}
LABEL_FOLDER = {"7Scenes": "7Scenes", "Cambridge": "CambridgeLandmarks"}
APRS = ("DFNet", "PoseNet")


def label_files(dataset: str, scene: str, args: argparse.Namespace) -> list[Path]:
    """The scene's train and test label files, camera-to-world (Cambridge's converted)."""
    files = [args.labels / LABEL_FOLDER[dataset] / f"{scene}_{s}.csv" for s in ("train", "test")]
    if dataset != "Cambridge":
        return files
    out = args.out / "labels"
    for source in files:
        if not (out / source.name).is_file():
            command = [sys.executable, "-m", "pae.data_cli", "convert", "authors-csv"]
            command += [str(source), str(out)]
            subprocess.run(command, check=True)
    return [out / f.name for f in files]


def fit(scene: str, files: list[Path], args: argparse.Namespace, overrides: list[str]) -> Path:
    """The scene-model run of ``scene`` (fitted unless its metrics.json exists)."""
    run = args.out / scene
    if not (run / "metrics.json").is_file():
        command = [
            sys.executable,
            "-m",
            "pae.train",
            f"experiment={args.experiment}",
            f"data.poses=[{files[0]},{files[1]}]",
            f"hydra.run.dir={run}",
            *overrides,
        ]
        print(" ".join(command[2:]), flush=True)
        with (args.out / f"{scene}.log").open("w") as log:
            subprocess.run(command, stdout=log, stderr=subprocess.STDOUT, check=True)
    return run


def real_starts(
    folder: Path, scene: str, img_paths: list[str], truth: torch.Tensor
) -> dict[str, torch.Tensor]:
    """Each image's start with its real error (the APR's file against its ground truth, in
    the camera frame, applied to the label pose ``truth`` [N, 7]), and NeFeS50's refinement
    of it likewise, in the order of ``img_paths``."""
    gt = read_starts(folder / f"{scene}_test_gt.txt", axes="opengl", form="lines")
    gt_poses = torch.as_tensor(gt.poses[match_starts(img_paths, gt, "gt")], dtype=torch.float64)
    poses = {}
    for name, suffix in (("start", "predict"), ("nefes50", "Nefes_50")):
        found = read_starts(folder / f"{scene}_{suffix}.txt", axes="opengl", form="lines")
        rows = match_starts(img_paths, found, suffix)
        estimate = torch.as_tensor(found.poses[rows], dtype=torch.float64)
        poses[name] = transfer_error(gt_poses, estimate, truth.double()).float()
    return poses


def source_paths(rendered: LabelTable, source: Path) -> list[str]:
    """The source label file's image paths of the rendered test rows (the renderer names its
    own files; rows keep the file's order and poses, checked)."""
    table = read_labels(source)
    if len(table) != len(rendered) or not np.allclose(table.poses, rendered.poses, atol=1e-9):
        raise ValueError(f"{source}: its rows are not those rendered into the run's test split")
    return list(table.img_path)


def chosen_steps(run_dir: Path) -> dict[str, float]:
    """The first steps, filter and surface share chosen on the scene's val images (the
    calibration for any start that pae-localize kept in the run; a one-line error where it
    has not chosen one yet)."""
    path = run_dir / CALIBRATION_FILE
    if not path.is_file():
        raise SystemExit(f"{path} is missing: run run.py on this scene first (it calibrates)")
    return dict(json.loads(path.read_text())["calibration"]["steps"])


def localize(run: Path, test: Path, starts: Path, tag: str, sequences: list[str]) -> dict:
    """``pae-localize`` of the run's test images from ``starts`` -> its poses (``RUN/<tag>.csv``)
    and its summary (``RUN/<tag>.json``), both read back."""
    root = yaml_root(run)
    out, summary = run / f"{tag}.csv", run / f"{tag}.json"
    if out.is_file() and summary.is_file():  # both written atomically: a finished pass
        done = json.loads(summary.read_text())
        if done.get("init") == str(starts) and done.get("images") == len(read_labels(test)):
            print(f"{tag}: read back from {summary}", flush=True)
            return {"poses": read_labels(out), **done}
    command = [sys.executable, "-m", "pae.localize", str(run), str(test), "--root", root]
    command += ["--init", str(starts), "--refine", "render_compare", "--out", str(out)]
    command += ["--summary", str(summary), *sequences]
    print(" ".join(command[2:]), flush=True)
    with (run / f"{tag}.log").open("w") as log:
        subprocess.run(command, stdout=log, stderr=subprocess.STDOUT, check=True)
    return {"poses": read_labels(out), **json.loads(summary.read_text())}


def yaml_root(run: Path) -> str:
    """The dataset root the run recorded (``.hydra/data.yaml``)."""
    from omegaconf import OmegaConf

    return str(OmegaConf.load(run / ".hydra" / "data.yaml").root)


def truth_audit(run_dir: Path, every: int) -> None:
    """The scene model's floor, an audit reading the test labels as starts: every
    ``every``-th test image refined from its true pose with the first steps chosen on val,
    every refinement accepted (through the library: no product path refines from the truth)
    -> ``OUT/<scene>/truth_audit.json`` (``from_truth_oracle``)."""
    run = read_run(run_dir)
    size = int(run.config.data.size)
    data = data_module(run, cache_images=False)
    data.setup()
    model = load_scene_model(scene_model_path(run), "scene_model_ckpt").model.eval()
    test = {key: value[::every] for key, value in split_queries(data, "test", size).items()}
    queries = Queries(test["image"], test["intrinsics"], test["scene"])
    calibration = Calibration(ACCEPT_ALL, ACCEPT_ALL, chosen_steps(run_dir))
    settings, _ = render_compare_settings(run)  # as pae-localize refines with the run
    refined = refine(model, queries, test["pose"], calibration, settings=settings)
    audit = {"every": every, "from_truth_oracle": val_figures(refined.poses, test["pose"])}
    with atomic_write(run_dir / "truth_audit.json") as handle:
        json.dump(audit, handle, indent=1)


def refine_scene(
    dataset: str, scene: str, run_dir: Path, files: list[Path], args: argparse.Namespace
) -> None:
    """Each APR's test starts refined by pae-localize per image (and per recording), one JSON
    per APR, what it lacks added to one already there; then the truth audit
    (:func:`truth_audit`)."""
    test_labels = Path(yaml_root(run_dir)) / "labels" / "all_test.csv"
    all_test = read_labels(test_labels)
    img_paths = source_paths(all_test, files[1])
    all_truth = torch.as_tensor(all_test.poses, dtype=torch.float32)
    kept = np.arange(0, len(all_test), args.every)
    rendered = all_test.select(kept)
    if args.every > 1:
        test_labels = run_dir / f"test_every{args.every}.csv"
        write_labels(test_labels, rendered)
    truth = all_truth[kept]
    metrics = json.loads((run_dir / "metrics.json").read_text())
    wanted: dict[str, list[str]] = {"render_compare": []}
    if args.recordings:
        passes, window = args.recordings
        wanted["per_recording"] = ["--sequences", "--sequence-passes", str(passes)]
        wanted["per_recording"] += ["--sequence-window", str(window)]
    for apr in APRS:
        path = run_dir / f"real_starts_{apr}.json"
        record = json.loads(path.read_text()) if path.is_file() else None
        if record is not None and record.get("every", 1) != args.every:
            every = record.get("every", 1)
            raise SystemExit(
                f"{path}: refined on one test image in {every}, not one in {args.every}: "
                f"give --every {every}"
            )
        modes = {m: o for m, o in wanted.items() if record is None or m not in record}
        if not modes:
            continue
        # the estimate files hold every test image: matched to all of them, then thinned
        found_starts = real_starts(args.estimates / apr / dataset, scene, img_paths, all_truth)
        starts = {name: poses[kept] for name, poses in found_starts.items()}
        start_file = run_dir / f"starts_{apr}.csv"
        write_labels(
            start_file, dataclasses.replace(rendered, poses=starts["start"].double().numpy())
        )
        found = {
            m: localize(run_dir, test_labels, start_file, f"{m}_{apr}", o) for m, o in modes.items()
        }
        if record is None:
            chosen = json.loads((run_dir / CALIBRATION_FILE).read_text())
            alone = found["render_compare"]
            record = {
                "scene": scene,
                "dataset": dataset,
                "apr": apr,
                "queries": len(truth),
                "every": args.every,
                "val_queries": chosen["val_queries"],
                "scene_size_m": chosen["scene_size_m"],
                "image_px": int(rendered_size(run_dir)),
                "calibration": {
                    "accept_margin": alone["calibration"]["accept_margin"],
                    "accept_score": alone["calibration"]["accept_score"],
                    **alone["calibration"]["steps"],
                },
                "val": chosen["val"],
                "start": val_figures(starts["start"], truth),
                "nefes50": val_figures(starts["nefes50"], truth),
                "accepted_share": alone["accepted_share"],
                "psnr_db": metrics.get("test/scene_model/psnr_db"),
                "fit_s": metrics.get("bench/scene_fit/fit_s"),
                "calibrate_s": alone["calibrate_s"],
                "ms_per_query": alone["ms_per_query"],
            }
        for mode, answer in found.items():
            poses = torch.as_tensor(answer["poses"].poses, dtype=torch.float32)
            record[mode] = val_figures(poses, truth)
            worse = pose_errors(poses, truth)[0] > pose_errors(starts["start"], truth)[0]
            record[f"{mode}_worse_than_start_share"] = float(worse.float().mean())
        if "per_recording" in found:
            record["recordings"] = found["per_recording"]["recordings"]
            record["per_recording_ms_per_query"] = found["per_recording"]["ms_per_query"]
            record["sequence_passes_window"] = list(args.recordings)
        with atomic_write(path) as handle:
            json.dump(record, handle, indent=1)
        print(
            f"{scene} {apr}: start {record['start']['pos_median_m']:.3f} m -> render_compare "
            f"{record['render_compare']['pos_median_m']:.3f} m (NeFeS50 "
            f"{record['nefes50']['pos_median_m']:.3f} m), accepted {record['accepted_share']:.2f}",
            flush=True,
        )
    audit = run_dir / "truth_audit.json"
    if not audit.is_file() or json.loads(audit.read_text()).get("every", 1) != args.every:
        truth_audit(run_dir, args.every)


def rendered_size(run: Path) -> int:
    """The px the run rendered and compared (its ``data.size``)."""
    from omegaconf import OmegaConf

    return int(OmegaConf.load(run / ".hydra" / "config.yaml").data.size)


def main(argv: list[str]) -> int:
    own, overrides = argv, []
    if "--" in argv:
        own, overrides = argv[: argv.index("--")], argv[argv.index("--") + 1 :]
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--labels", type=Path, required=True)
    parser.add_argument("--estimates", type=Path, required=True)
    parser.add_argument("--out", type=Path, default=Path("outputs/render_compare_real_starts"))
    parser.add_argument("--scenes", nargs="+", help="in this order (default: all eleven)")
    parser.add_argument(
        "--experiment",
        default="real_starts",
        help="the pae-train experiment of each scene (default: real_starts, 64 px; "
        "real_starts_px128: 128 px); further pae-train overrides after --",
    )
    parser.add_argument(
        "--recordings",
        type=int,
        nargs=2,
        metavar=("PASSES", "WINDOW"),
        help="also refine each test recording with its frames' order (pae-localize "
        "--sequences) with these sequence passes and median window",
    )
    parser.add_argument(
        "--every",
        type=int,
        default=1,
        metavar="K",
        help="refine every K-th test image only (default 1: all)",
    )
    args = parser.parse_args(own)
    if args.every < 1:
        parser.error(f"--every must be at least 1, got {args.every}")
    dataset_of = {scene: dataset for dataset, names in SCENES.items() for scene in names}
    for scene in args.scenes or list(dataset_of):
        if scene not in dataset_of:
            parser.error(f"unknown scene {scene!r}; choose from {sorted(dataset_of)}")
        args.out.mkdir(parents=True, exist_ok=True)
        files = label_files(dataset_of[scene], scene, args)
        run_dir = fit(scene, files, args, overrides)
        refine_scene(dataset_of[scene], scene, run_dir, files, args)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
