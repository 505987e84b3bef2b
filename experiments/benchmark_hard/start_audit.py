"""Where render-and-compare loses the hard benchmark's queries: the score or the starts.

For a finished ``pae-train experiment=demo_hard`` run (RUN, its teacher and scene model):

1. **Coverage** (``coverage``): how far each query's true pose lies from the nearest train
   camera of its scene (median position, m / orientation, deg; the nearest by
   ``metres + degrees / 10``): a bound on any start that retrieves train poses (by the
   teacher's latent or by appearance). The test row reads the test labels: an audit, named
   ``coverage_test_audit``; nothing is chosen on it.
2. **Basin** (``basin``): the validation queries refined under the run's settings (the filter
   and steps its val calibration chose, every refinement accepted) and each ``--variant``
   (``key=value,key=value`` over the refiner's settings), with the run's scene model and with
   the benchmark's own renderer (``oracle``, a bound), from two starts: the true poses (where
   the score's best match lies near the truth) and the teacher's estimates. Each cell: median
   position (m) / orientation (deg) and the share within 0.25 m and 3 deg.

3. **Renderings** (``RUN/start_audit.png``): ``--pictures`` val queries (one column each,
   spread over the split), top to bottom: the query as compared, the scene model's and the
   oracle's renderings at its true pose.

Only validation labels are read for the basin and the renderings. Prints markdown tables and
writes them to ``RUN/start_audit.json``.

    python experiments/benchmark_hard/start_audit.py outputs/demo_hard \\
        --variant highlight_quantile=0.7 --variant candidates=48
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from torch import Tensor

from pae.apps.localization import (
    Run,
    data_module,
    read_run,
    render_compare_settings,
    scene_model_path,
    split_queries,
)
from pae.core.atomic import atomic_write
from pae.core.checkpoints import load_scene_model, load_teacher
from pae.core.geometry import pose_errors
from pae.data.datamodule import PoseDataModule
from pae.lit.eval_outputs import oracle_scenes
from pae.render_compare import Queries, refine
from pae.render_compare.settings import refiner_defaults
from pae.scene_model.oracle import OracleSceneModel

NEAR_M, NEAR_DEG = 0.25, 3.0
"""The basin's cells count the queries within this position (m) and orientation (deg)."""
DEG_PER_M = 10.0
"""The nearest train camera: the least ``metres + degrees / DEG_PER_M``."""


def nearest_train(
    poses: Tensor, scenes: Tensor, train_poses: Tensor, train_scenes: Tensor
) -> tuple[Tensor, Tensor]:
    """Position (m) and orientation (deg) errors [N] of the nearest train pose of the same
    scene to each pose [N, 7] (scenes [N]; train poses [M, 7], scenes [M])."""
    n, m = len(poses), len(train_poses)
    pairs = pose_errors(
        poses[:, None].expand(n, m, 7).reshape(-1, 7).double(),
        train_poses[None].expand(n, m, 7).reshape(-1, 7).double(),
    )
    position, orientation = (e.view(n, m) for e in pairs)
    other = scenes[:, None] != train_scenes[None]
    cost = (position + orientation / DEG_PER_M).masked_fill(other, float("inf"))
    pick = cost.argmin(1, keepdim=True)
    return position.gather(1, pick)[:, 0], orientation.gather(1, pick)[:, 0]


@torch.no_grad()
def teacher_estimates(run: Run, data: PoseDataModule, split: str) -> Tensor:
    """The run's teacher's (its ``teacher_ckpt`` where it trained none) poses [N, 7] of
    ``split``'s queries, in the split's order."""
    path = run.config.get("teacher_ckpt") or run.checkpoint("teacher", "the audit")
    teacher = load_teacher(path, "teacher_ckpt").model.eval()
    loader = data.val_dataloader() if split == "val" else data.test_dataloader()
    return torch.cat(
        [teacher(data.preprocess(b["image"], False), b["scene"])[0].float() for b in loader]
    )


@torch.no_grad()
def renderings(models: dict[str, Any], val: dict[str, Tensor], count: int) -> np.ndarray:
    """RGB uint8 [3 x h, count x w, 3]: ``count`` val queries (columns) above the renderings
    of each of ``models`` at their true poses."""
    rows = torch.linspace(0, len(val["pose"]) - 1, count).round().long()
    h, w = val["image"].shape[-2:]
    pose, scene, intrinsics = val["pose"][rows], val["scene"][rows], val["intrinsics"][rows]
    images = [val["image"][rows]]
    images += [m.render(pose, scene, intrinsics, w, h).rgb for m in models.values()]
    picture = torch.cat([torch.cat(list(row.clamp(0, 1)), 2) for row in images], 1)
    return (picture.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)


def cell(poses: Tensor, truth: Tensor) -> str:
    position, orientation = pose_errors(poses.double(), truth.double())
    near = ((position <= NEAR_M) & (orientation <= NEAR_DEG)).double().mean()
    return f"{position.median():.3f} / {orientation.median():.2f} ({100 * near:.0f} %)"


def parse_variant(text: str) -> dict[str, Any]:
    """``key=value,key=value`` -> settings (numbers as floats, whole ones as ints); a
    ValueError naming the item that is not a refiner setting set to a number."""
    settings: dict[str, Any] = {}
    known = refiner_defaults()
    for item in filter(None, text.split(",")):
        key, _, value = (part.strip() for part in item.partition("="))
        try:
            number = float(value)
        except ValueError:
            raise ValueError(f"--variant {text!r}: {item!r} is not key=number") from None
        if key not in known:
            raise ValueError(f"--variant {text!r}: {key!r} is not a refiner setting")
        settings[key] = int(number) if number.is_integer() and "." not in value else number
    return settings


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="a finished experiment=demo_hard run folder")
    parser.add_argument("--variant", action="append", default=[], help="key=value,...")
    parser.add_argument("--pictures", type=int, default=12, help="val queries rendered")
    args = parser.parse_args()
    try:
        variants = {"the run's settings": {}} | {v: parse_variant(v) for v in args.variant}
    except ValueError as error:
        parser.error(str(error))
    run = read_run(args.run)
    data = data_module(run, cache_images=False)
    data.setup()
    train_poses, train_scenes = data.train_poses()
    report: dict[str, Any] = {"coverage": {}, "basin": {}}
    print("| split | nearest train pose: position (m) / orientation (deg) |\n|---|---|")
    for split, name in (("val", "coverage_val"), ("test", "coverage_test_audit")):
        dataset = data.datasets[split]
        truth = torch.as_tensor(dataset.poses).float()
        scenes = torch.as_tensor(dataset.scenes)
        position, orientation = nearest_train(truth, scenes, train_poses.float(), train_scenes)
        text = f"{position.median():.3f} / {orientation.median():.2f}"
        report["coverage"][name] = text
        print(f"| {name} | {text} |")
    settings, _ = render_compare_settings(run)
    val = split_queries(data, "val", int(settings["resolution"]))
    starts = {"truth": val["pose"], "teacher": teacher_estimates(run, data, "val")}
    models = {
        "scene model": load_scene_model(scene_model_path(run), "scene_model_ckpt").model,
        "oracle": OracleSceneModel(oracle_scenes(data)),
    }
    columns = [f"{m}, from {s}" for m in models for s in starts]
    print(f"\n| variant | {' | '.join(columns)} |\n|---|{'---|' * len(columns)}")
    for label, variant in variants.items():
        cells = [
            cell(
                refine(
                    model, Queries(val["image"], val["intrinsics"], val["scene"]), start,
                    settings=settings | variant,
                ).result.poses,
                val["pose"],
            )
            for model in models.values()
            for start in starts.values()
        ]  # fmt: skip
        report["basin"][label] = dict(zip(columns, cells, strict=True))
        print(f"| {label} | {' | '.join(cells)} |", flush=True)
    with atomic_write(args.run / "start_audit.json") as handle:
        handle.write(json.dumps(report, indent=2))
    picture = renderings(models, val, args.pictures)
    ok, encoded = cv2.imencode(
        ".png", cv2.resize(picture[..., ::-1], None, fx=3, fy=3, interpolation=cv2.INTER_NEAREST)
    )
    assert ok
    with atomic_write(args.run / "start_audit.png", "wb") as handle:
        handle.write(encoded.tobytes())
    print(f"renderings: {args.run / 'start_audit.png'}")


if __name__ == "__main__":
    main()
