"""Your own scene through COLMAP: the demo's benchmark (one scene) written as a COLMAP model,
converted with ``pae-data convert colmap`` and trained on with ``data=converted``, beside the
same benchmark read as pae's synthetic dataset: the same pipeline (teacher, student, scene
model, render-and-compare) on the same images and poses, two ways in.

    python experiments/own_scene/run.py --out outputs/own_scene

Steps (each skipped where its output exists): ``pae-data synth OUT/bench --scenes 1``; the
COLMAP text model ``OUT/sparse`` (one PINHOLE camera, the images' world-to-camera poses, the
benchmark's own image names) and ``OUT/test_images.txt``; ``pae-data convert colmap OUT/sparse
OUT/bench OUT/labels --split-list OUT/test_images.txt``; ``pae-train experiment=demo`` on each
(``OUT/run_benchmark``, ``OUT/run_colmap``). Prints their test figures side by side.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

from pae.core.geometry import quaternion_to_matrix
from pae.data.labels import read_labels
from pae.synthetic import DEFAULT_SIZE, PinholeCamera

METHODS = ("teacher", "student", "render_compare", "render_compare_oracle")


def command(*arguments: str) -> None:
    """Run a pae entry point (``python -m``), its output on this one's."""
    print(" ".join(arguments), flush=True)
    subprocess.run([sys.executable, "-m", *arguments], check=True)


def write_model(bench: Path, sparse: Path, split_list: Path) -> None:
    """The COLMAP text model of the benchmark's train and test images and the test list."""
    tables = [read_labels(bench / "labels" / f"all_{s}.csv") for s in ("train", "test")]
    names = [name for table in tables for name in table.img_path]
    poses = np.concatenate([table.poses for table in tables])
    rotation = quaternion_to_matrix(torch.from_numpy(poses[:, 3:])).numpy()  # camera to world
    translation = -np.einsum("nji,nj->ni", rotation, poses[:, :3])
    conjugate = poses[:, 3:] * np.array([1.0, -1.0, -1.0, -1.0])  # world to camera
    camera = PinholeCamera(DEFAULT_SIZE)
    f, c = camera.focal_px, camera.principal_point
    sparse.mkdir(parents=True, exist_ok=True)
    (sparse / "cameras.txt").write_text(
        f"1 PINHOLE {DEFAULT_SIZE} {DEFAULT_SIZE} {f!r} {f!r} {c!r} {c!r}\n"
    )
    lines = []
    for image_id, (name, q, t) in enumerate(zip(names, conjugate, translation, strict=True), 1):
        numbers = " ".join(repr(float(v)) for v in (*q, *t))
        lines += [f"{image_id} {numbers} 1 {name}", ""]
    (sparse / "images.txt").write_text("\n".join(lines) + "\n")
    (sparse / "points3D.txt").write_text("")
    split_list.write_text("\n".join(tables[1].img_path) + "\n")


def figures(run: Path) -> dict[str, tuple[float, float]]:
    """Test median position (m) and orientation (deg) of each method in ``run``."""
    metrics = json.loads((run / "metrics.json").read_text())
    return {
        method: (metrics[f"test/{method}/pos_median_m"], metrics[f"test/{method}/rot_median_deg"])
        for method in METHODS
        if f"test/{method}/pos_median_m" in metrics
    }


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("outputs/own_scene"))
    args = parser.parse_args(argv)
    out = args.out.resolve()
    bench, sparse, labels = out / "bench", out / "sparse", out / "labels"
    if not (bench / "labels" / "all_train.csv").is_file():
        command("pae.data_cli", "synth", str(bench), "--scenes", "1")
    split_list = out / "test_images.txt"
    if not (sparse / "images.txt").is_file():
        write_model(bench, sparse, split_list)
    if not (labels / "all_train.csv").is_file():
        command(
            "pae.data_cli", "convert", "colmap", str(sparse), str(bench), str(labels),
            "--split-list", str(split_list),
        )  # fmt: skip
    camera = PinholeCamera(DEFAULT_SIZE)
    f, c = camera.focal_px, camera.principal_point
    shared = ["experiment=demo"]
    runs = {
        "benchmark": [f"data.root={bench}", "data.scenes=1"],
        "colmap": [
            "data=converted",
            f"data.root={bench}",
            f"data.train_labels={labels / 'all_train.csv'}",
            f"data.test_labels={labels / 'all_test.csv'}",
            f"data.camera={{fx: {f}, fy: {f}, cx: {c}, cy: {c}, "
            f"width: {DEFAULT_SIZE}, height: {DEFAULT_SIZE}}}",
            # the demo's data settings (pae.synthetic.settings), which data=converted
            # leaves at a real dataset's
            f"data.shorter_edge={DEFAULT_SIZE}",
            "data.crop=56",
            "data.color_jitter=[0.3,0.3,0.3,0.0]",
            "data.eval_batch_size=256",
            "data.num_workers=0",
            "data.cache_images=true",
            "data.pose_loss_init={s_x: 0.0, s_q: -3.0}",
        ],
    }
    for name, overrides in runs.items():
        run = out / f"run_{name}"
        if (
            not (run / "metrics.json").is_file()
            or "test/render_compare/pos_median_m" not in (run / "metrics.json").read_text()
        ):
            command("pae.train", *shared, *overrides, f"hydra.run.dir={run}")
    results = {name: figures(out / f"run_{name}") for name in runs}
    print("\ntest median m / deg   " + "   ".join(f"{name:>18s}" for name in runs))
    for method in METHODS:
        cells = [results[name].get(method) for name in runs]
        text = [f"{c[0]:.3f} / {c[1]:.2f}" if c else "" for c in cells]
        print(f"{method:22s}" + "   ".join(t.rjust(18) for t in text))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
