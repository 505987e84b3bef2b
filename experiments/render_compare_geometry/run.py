"""Render-and-compare on every real camera geometry: for each 7-Scenes and Cambridge
Landmarks scene, synthetic images at the camera poses of its label files (poses only), then
`pae-train experiment=audit_geometry` (teacher -> student -> scene model ->
render-and-compare) in ``OUT/<scene>``. Scenes whose run finished (metrics.json) are skipped,
so the script resumes where it stopped.

Long scenes are subsampled: every k-th row of a label file, k the smallest that leaves at
most ``--max-train`` train and ``--max-test`` test rows (whole sequences stay, thinned). The
teacher and student train for about ``--steps`` optimiser steps whatever the scene's size
(epochs = steps x batch / train rows, within [20, 150]).

    python experiments/render_compare_geometry/run.py --labels ../shared/reference/labels \
        --out outputs/render_compare_geometry [--scenes chess ShopFacade] [-- OVERRIDES]
"""

from __future__ import annotations

import argparse
import math
import subprocess
import sys
from pathlib import Path

DATASETS = {
    "7Scenes": ("chess", "fire", "heads", "office", "pumpkin", "redkitchen", "stairs"),
    "CambridgeLandmarks": (
        "GreatCourt",
        "KingsCollege",
        "OldHospital",
        "ShopFacade",
        "StMarysChurch",
        "Street",
    ),
}
BATCH_SIZE = 32


def thinned(source: Path, target: Path, max_rows: int) -> tuple[int, int]:
    """Write every k-th data row of label file ``source`` to ``target`` (header kept), k the
    smallest with at most ``max_rows`` rows -> (k, rows written)."""
    header, *rows = source.read_text().splitlines()
    step = max(1, math.ceil(len(rows) / max_rows))
    kept = rows[::step]
    target.write_text("\n".join([header, *kept]) + "\n")
    return step, len(kept)


def run_scene(dataset: str, scene: str, args: argparse.Namespace, overrides: list[str]) -> None:
    out = args.out / scene
    if (out / "metrics.json").is_file():
        print(f"{scene}: done ({out / 'metrics.json'})", flush=True)
        return
    labels = args.out / "labels"
    labels.mkdir(parents=True, exist_ok=True)
    files = []
    for split, limit in (("train", args.max_train), ("test", args.max_test)):
        target = labels / f"{scene}_{split}.csv"
        step, rows = thinned(args.labels / dataset / f"{scene}_{split}.csv", target, limit)
        print(f"{scene} {split}: every {step}. row, {rows} rows", flush=True)
        files.append(target)
        if split == "train":
            epochs = min(150, max(20, math.ceil(args.steps * BATCH_SIZE / rows)))
    command = [
        sys.executable,
        "-m",
        "pae.train",
        "experiment=audit_geometry",
        f"data.poses=[{files[0]},{files[1]}]",
        f"teacher.max_epochs={epochs}",
        f"student.max_epochs={epochs}",
        f"hydra.run.dir={out}",
        *overrides,
    ]
    print(" ".join(command[2:]), flush=True)
    log = args.out / f"{scene}.log"
    with log.open("w") as handle:
        result = subprocess.run(command, stdout=handle, stderr=subprocess.STDOUT)
    print(f"{scene}: exit {result.returncode} (log {log})", flush=True)


def main(argv: list[str]) -> int:
    own, overrides = argv, []
    if "--" in argv:
        own, overrides = argv[: argv.index("--")], argv[argv.index("--") + 1 :]
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--labels", type=Path, required=True)
    parser.add_argument("--out", type=Path, default=Path("outputs/render_compare_geometry"))
    parser.add_argument(
        "--scenes", nargs="+", help="in this order (default: every scene of both datasets)"
    )
    parser.add_argument("--max-train", type=int, default=600)
    parser.add_argument("--max-test", type=int, default=150)
    parser.add_argument("--steps", type=int, default=400)
    args = parser.parse_args(own)
    dataset_of = {scene: dataset for dataset, names in DATASETS.items() for scene in names}
    for scene in args.scenes or list(dataset_of):
        if scene not in dataset_of:
            parser.error(f"unknown scene {scene!r}; choose from {sorted(dataset_of)}")
        run_scene(dataset_of[scene], scene, args, overrides)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
