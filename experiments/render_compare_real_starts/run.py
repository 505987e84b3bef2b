"""Render-and-compare from real APRs' estimates on every real camera geometry.

For each 7-Scenes scene and the four Cambridge Landmarks scenes of the estimate files:
synthetic images at every pose of the real label files (no thinning), the scene model fitted
to the train images (``pae-train experiment=real_starts``), then, through the library
(``pae.render_compare.calibrate_any_start`` and ``refine``), the refinement of each APR's
starts. A start carries its image's real error: the APR's estimate against the file's ground
truth, taken in the camera frame (``dt = R_gt^T (t_apr - t_gt)``, ``dR = R_gt^T R_apr``) and
applied to the label file's pose of the same image. The gate and first steps are chosen on
the validation images (held-out train sequences) with starts at every error scale, never on
test. Finished scenes (``OUT/<scene>/real_starts_<APR>.json``) are skipped.

    python experiments/render_compare_real_starts/run.py --labels ../shared/reference/labels \\
        --estimates ../shared/reference/estimates --out outputs/render_compare_real_starts
    python experiments/render_compare_real_starts/table.py outputs/render_compare_real_starts
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from pae.apps.localization import data_module, read_run, scene_model_path, split_queries
from pae.core.atomic import atomic_write
from pae.core.checkpoints import load_scene_model
from pae.core.geometry import pose_errors, transfer_error
from pae.data.labels import LabelTable, read_labels
from pae.data.starts import match_starts, read_starts
from pae.render_compare import (
    ACCEPT_ALL,
    AnyStartOptions,
    Calibration,
    Queries,
    calibrate_any_start,
    refine,
)
from pae.render_compare.calibration import CONTRAST_PX, HIGHPASS_PX, SURFACE_SHARES, scene_size
from pae.render_compare.settings import RenderCompareSettings

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
            "experiment=real_starts",
            f"data.poses=[{files[0]},{files[1]}]",
            f"hydra.run.dir={run}",
            f"data.size={args.size}",
            f"data.crop={args.size}",
            f"scene_model.image_size={args.size}",
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


def figures(poses: torch.Tensor, truth: torch.Tensor) -> dict[str, float]:
    """Median position (m) and orientation (deg) errors and the share within 5 cm and 5 deg."""
    pos, rot = pose_errors(poses.float(), truth.float())
    within = ((pos < 0.05) & (rot < 5.0)).float().mean()
    return {
        "pos_median_m": float(pos.median()),
        "rot_median_deg": float(rot.median()),
        "within_5cm_5deg": float(within),
    }


def source_paths(rendered: LabelTable, source: Path) -> list[str]:
    """The source label file's image paths of the rendered test rows (the renderer names its
    own files; rows keep the file's order and poses, checked)."""
    table = read_labels(source)
    if len(table) != len(rendered) or not np.allclose(table.poses, rendered.poses, atol=1e-9):
        raise ValueError(f"{source}: its rows are not those rendered into the run's test split")
    return list(table.img_path)


def refiner_settings(size: int) -> RenderCompareSettings:
    """The refiner's settings at a ``size``-px comparison: the final reference at half of
    it (the default 32 px at 64 px; at 128 px 64, chosen on chess's val with floor.py)."""
    return RenderCompareSettings(resolution=size, final_reference_size=size // 2)


def chosen_steps(run_dir: Path) -> dict[str, float]:
    """The first steps, filter and surface share that ``calibrate_any_start`` chose on the
    scene's val images, read from its ``real_starts_<APR>.json`` (a one-line error where
    run.py has not calibrated the scene yet)."""
    path = run_dir / f"real_starts_{APRS[0]}.json"
    if not path.is_file():
        raise SystemExit(f"{path} is missing: run run.py on this scene first (it calibrates)")
    chosen = json.loads(path.read_text())["calibration"]
    gate = ("accept_margin", "accept_score")
    return {key: value for key, value in chosen.items() if key not in gate}


def truth_audit(
    run_dir: Path, model: object, test: dict[str, torch.Tensor], settings: object
) -> None:
    """The scene model's floor, an audit reading the test labels as starts: the test images
    refined from their true poses with the first steps chosen on val (every refinement
    accepted) -> ``OUT/<scene>/truth_audit.json`` (``from_truth_oracle``)."""
    calibration = Calibration(ACCEPT_ALL, ACCEPT_ALL, chosen_steps(run_dir))
    truth = test["pose"]
    queries = Queries(test["image"], test["intrinsics"], test["scene"])
    refined = refine(model, queries, truth, calibration, settings=settings)
    with atomic_write(run_dir / "truth_audit.json") as handle:
        json.dump({"from_truth_oracle": figures(refined.poses, truth)}, handle, indent=1)


def refine_scene(
    dataset: str, scene: str, run_dir: Path, files: list[Path], args: argparse.Namespace
) -> None:
    """Calibrate on val, refine each APR's test starts, write one JSON per APR; then the
    truth audit (:func:`truth_audit`)."""
    todo = [a for a in APRS if not (run_dir / f"real_starts_{a}.json").is_file()]
    audit = not (run_dir / "truth_audit.json").is_file()
    if not todo and not audit:
        print(f"{scene}: done", flush=True)
        return
    run = read_run(run_dir)
    size = int(run.config.data.size)
    data = data_module(run, cache_images=False, crop=size)  # the whole image is compared
    data.setup()
    loaded = load_scene_model(scene_model_path(run), "scene_model_ckpt")
    model = loaded.model.eval()
    settings = refiner_settings(size)
    val = split_queries(data, "val", settings.resolution)
    test = split_queries(data, "test", settings.resolution)
    if not todo:
        truth_audit(run_dir, model, test, settings)
        return
    train_positions, _ = data.train_poses()
    extent = scene_size(train_positions[:, :3].double())
    start = time.perf_counter()
    tried = AnyStartOptions(args.highpass_px, args.contrast_px, args.surface_shares)
    calibration, val_refined, val_starts = calibrate_any_start(
        model, Queries(val["image"], val["intrinsics"], val["scene"]), val["pose"], extent,
        settings, tried,
    )  # fmt: skip
    calibrate_s = time.perf_counter() - start
    metrics = json.loads((run_dir / "metrics.json").read_text())
    img_paths = source_paths(data.tables["test"], files[1])
    for apr in todo:
        starts = real_starts(args.estimates / apr / dataset, scene, img_paths, test["pose"])
        start = time.perf_counter()
        queries = Queries(test["image"], test["intrinsics"], test["scene"])
        refined = refine(model, queries, starts["start"], calibration, settings=settings)
        seconds = time.perf_counter() - start
        ungated = refined.result.poses
        record = {
            "scene": scene,
            "dataset": dataset,
            "apr": apr,
            "queries": len(test["pose"]),
            "val_queries": len(val["pose"]),
            "scene_size_m": extent,
            "image_px": size,
            "final_reference_px": settings.final_reference_size,
            "calibration": {
                "accept_margin": calibration.accept_margin,
                "accept_score": calibration.accept_score,
                **dict(calibration.steps),
            },
            "val": {
                "start": figures(val_starts, val["pose"]),
                "render_compare": figures(val_refined.poses, val["pose"]),
            },
            "start": figures(starts["start"], test["pose"]),
            "render_compare": figures(refined.poses, test["pose"]),
            "render_compare_ungated": figures(ungated, test["pose"]),
            "nefes50": figures(starts["nefes50"], test["pose"]),
            "accepted_share": float(refined.accepted.float().mean()),
            "worse_than_start_share": float(
                (pose_errors(refined.poses, test["pose"])[0]
                 > pose_errors(starts["start"], test["pose"])[0]).float().mean()
            ),
            "psnr_db": metrics.get("test/scene_model/psnr_db"),
            "fit_s": metrics.get("bench/scene_fit/fit_s"),
            "calibrate_s": calibrate_s,
            "ms_per_query": 1000 * seconds / len(test["pose"]),
        }  # fmt: skip
        with atomic_write(run_dir / f"real_starts_{apr}.json") as handle:
            json.dump(record, handle, indent=1)
        print(
            f"{scene} {apr}: start {record['start']['pos_median_m']:.3f} m -> render_compare "
            f"{record['render_compare']['pos_median_m']:.3f} m (NeFeS50 "
            f"{record['nefes50']['pos_median_m']:.3f} m), accepted {record['accepted_share']:.2f}",
            flush=True,
        )
    truth_audit(run_dir, model, test, settings)


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
        "--size",
        type=int,
        default=64,
        help="px of the rendered images, the scene model's "
        "train images and the comparison (default: 64)",
    )
    parser.add_argument(
        "--highpass-px",
        type=float,
        nargs="+",
        default=[HIGHPASS_PX],
        help=f"the high-passes (px) the calibration tries (default: {HIGHPASS_PX:g})",
    )
    parser.add_argument(
        "--contrast-px",
        type=float,
        nargs="*",
        default=list(CONTRAST_PX),
        help="the local contrasts (px) the calibration tries with each high-pass besides none "
        f"(default: {' '.join(f'{c:g}' for c in CONTRAST_PX)}; none given: none tried)",
    )
    parser.add_argument(
        "--surface-shares",
        type=float,
        nargs="*",
        default=list(SURFACE_SHARES),
        help="the references' surface shares the calibration tries besides the light's mean "
        f"depth (default: {' '.join(f'{c:g}' for c in SURFACE_SHARES)}; none given: none)",
    )
    args = parser.parse_args(own)
    if min(args.highpass_px + args.contrast_px, default=0.0) < 0:
        parser.error("--highpass-px and --contrast-px take sigmas (px) >= 0")
    if not all(0 < share < 1 for share in args.surface_shares):
        parser.error("--surface-shares take shares of a ray's opacity in (0, 1)")
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
