"""Which gate family val prefers for another APR's starts: today's, a score that vouches
alone, or evidence per distance moved (README, "The gate from good starts").

For each run of ``run.py``: its val queries refined from the any-start calibration's own
ladder starts under the run's calibration (``RUN/render_compare_any_start.json``), every
refinement kept; each query's score gain, refined score, distance moved and position errors
go to ``RUN/gate_val.pt`` (made once, read back after). Then each gate family is fitted by
the calibration's objective (``log_ratio``) in a two-fold cross-validation over alternating
blocks of ``len(LADDER)`` queries, and its held-out objective printed and written to
``RUN/gate_val.json``. Only validation labels are read.

    python experiments/render_compare_real_starts/gate_val.py outputs/rsh_grow/fire \\
        outputs/rsh_grow/pumpkin
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import torch

from pae.apps import localization as loc
from pae.apps.match_inputs import run_train_images
from pae.core.atomic import atomic_write
from pae.core.checkpoints import load_scene_model, load_teacher
from pae.core.geometry import pose_errors
from pae.render_compare import ACCEPT_ALL, Queries, refine
from pae.render_compare.calibration import (
    KEEP_ALL,
    LADDER,
    MARGIN_QUANTILES,
    RATIO_EPS_M,
    AnyStartOptions,
    ladder_starts,
    scene_size,
)
from pae.render_compare.correspondences import MatchQueries

MOVE_UNIT_SHARE = 0.01
"""Family C's unit distance: this share of the scene's size asks the margin m itself."""
NEVER = float("inf")


def refined_on_val(folder: Path) -> dict[str, torch.Tensor | float]:
    """The run's val queries refined from the ladder starts under its any-start calibration,
    every refinement kept: per query [N] the score gain, refined score, distance moved (m),
    start and refined position errors (m) and rung; the scene's size (m)."""
    run = loc.read_run(folder)
    settings, _ = loc.render_compare_settings(run)
    model = load_scene_model(loc.scene_model_path(run), "scene_model_ckpt").model.eval()
    teacher_path = loc.teacher_checkpoint(run, loc.RENDER_COMPARE)
    teacher = None if teacher_path is None else load_teacher(teacher_path)
    device = torch.device("cpu")
    calibration, train = loc.any_start_calibration(run, model, settings, None, device, teacher)
    data = loc.data_module(run, cache_images=False)
    data.setup()
    val = loc.split_queries(data, "val", loc.compare_width(settings))
    positions, _ = data.train_poses()
    size = scene_size(positions[:, :3].double())
    matching = None
    if calibration.match.active:
        width = calibration.match.width
        views = train or run_train_images((run.folder, run.config), data, width, teacher)
        images, intrinsics = data.images_at("val", width)
        matching = MatchQueries(images.float() / 255, intrinsics, views)
    truth = val["pose"]
    starts = ladder_starts(truth, size, torch.Generator().manual_seed(AnyStartOptions().seed))
    every = dataclasses.replace(calibration, accept_margin=ACCEPT_ALL, accept_score=ACCEPT_ALL)
    queries = Queries(val["image"], val["intrinsics"], val["scene"], matching=matching)
    begin = time.perf_counter()
    result = refine(model, queries, starts, every, settings=settings).result
    print(f"{folder.name}: {len(truth)} val queries refined in {time.perf_counter() - begin:.0f} s")
    return {
        "gain": result.score - result.initial_score,
        "score": result.score,
        "moved_m": pose_errors(result.poses.float(), starts.float())[0],
        "start_m": pose_errors(starts.float(), truth.float())[0],
        "refined_m": pose_errors(result.poses.float(), truth.float())[0],
        "rung": torch.arange(len(truth)) % len(LADDER),
        "size_m": size,
    }


def quantiles(values: torch.Tensor, base: list[float]) -> torch.Tensor:
    """Candidate thresholds: ``base`` and ``MARGIN_QUANTILES`` of values [N], sorted."""
    levels = torch.tensor(MARGIN_QUANTILES)
    return torch.cat([torch.tensor(base), values.float().quantile(levels)]).sort().values


def evidence(family: str, record: dict) -> torch.Tensor:
    """What family's margin is compared with, per query [N]: the score gain, or (C) the gain
    per unit distance moved."""
    if family != "C":
        return record["gain"].float()
    unit = MOVE_UNIT_SHARE * record["size_m"]
    return record["gain"].float() * unit / record["moved_m"].float().clamp_min(1e-9)


def accepted(family: str, record: dict, rows: torch.Tensor, gate: tuple) -> torch.Tensor:
    """Which of ``rows`` the family's gate (m, f, g) accepts [R] (bool)."""
    margin, floor, alone = gate
    score = record["score"].float()[rows]
    kept = (evidence(family, record)[rows] > margin) & (score > floor)
    return kept | (score > alone)


def objective(record: dict, rows: torch.Tensor, kept: torch.Tensor) -> float:
    """The mean log of each query's error over its start's where ``kept`` [R] (bool)."""
    ratio = (record["refined_m"][rows] + RATIO_EPS_M) / (record["start_m"][rows] + RATIO_EPS_M)
    return float(torch.where(kept, ratio.log(), torch.zeros_like(ratio)).mean())


def fitted(family: str, record: dict, rows: torch.Tensor) -> tuple[float, float, float]:
    """The family's gate (margin, floor, score alone) minimising the objective over ``rows``;
    the smallest margin, then floor, wins ties, then no score alone."""
    margins = quantiles(evidence(family, record)[rows], [ACCEPT_ALL, 0.0, KEEP_ALL])
    floors = quantiles(record["score"][rows], [ACCEPT_ALL])
    alones = [NEVER]
    if family == "B":
        alones += quantiles(record["score"][rows], []).flip(0).tolist()
    best, chosen = float("inf"), (0.0, ACCEPT_ALL, NEVER)
    for alone in alones:
        for margin in margins.tolist():
            for floor in floors.tolist():
                gate = (margin, floor, alone)
                value = objective(record, rows, accepted(family, record, rows, gate))
                if value < best - 1e-12:
                    best, chosen = value, gate
    return chosen


def cross_validated(record: dict) -> dict[str, dict]:
    """Per family: the held-out objective of each fold's fit, their mean, and the gate fitted
    on every query with what it does on each rung."""
    count = len(record["gain"])
    block = (torch.arange(count) // len(LADDER)) % 2
    folds = [torch.nonzero(block == k).flatten() for k in (0, 1)]
    out = {}
    for family in ("A", "B", "C"):
        held = [
            objective(record, folds[1 - k], accepted(family, record, folds[1 - k], gate))
            for k, gate in ((k, fitted(family, record, folds[k])) for k in (0, 1))
        ]
        every = torch.arange(count)
        gate = fitted(family, record, every)
        kept = accepted(family, record, every, gate)
        final = torch.where(kept, record["refined_m"], record["start_m"])
        rungs = [
            {
                "share": share,
                "accepted": float(kept[record["rung"] == k].float().mean()),
                "pos_median_m": float(final[record["rung"] == k].median()),
            }
            for k, share in enumerate(LADDER)
        ]
        out[family] = {
            "held_out": held,
            "cross_validated": sum(held) / 2,
            "gate_on_all": list(gate),
            "rungs": rungs,
        }
    return out


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, nargs="+")
    args = parser.parse_args(argv)
    for folder in args.runs:
        stored = folder / "gate_val.pt"
        if stored.is_file():
            record = torch.load(stored, weights_only=True)
        else:
            record = refined_on_val(folder)
            with atomic_write(stored, "wb") as handle:
                torch.save(record, handle)
        families = cross_validated(record)
        with atomic_write(folder / "gate_val.json") as handle:
            json.dump(families, handle, indent=1)
        for family, row in families.items():
            rungs = " ".join(
                f"{100 * r['pos_median_m']:.1f}/{r['accepted']:.2f}" for r in row["rungs"]
            )
            print(
                f"{folder.name} {family}: held out {row['held_out'][0]:.4f} "
                f"{row['held_out'][1]:.4f} mean {row['cross_validated']:.4f}; gate on all "
                f"{[round(v, 3) for v in row['gate_on_all']]}; per rung cm/accepted {rungs}"
            )
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
