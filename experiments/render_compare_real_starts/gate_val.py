"""Which gate family val prefers for another APR's starts: today's, a score that vouches
alone, or evidence per distance moved (README, "The gate from good starts").

For each run of ``run.py``: its val queries refined from the any-start calibration's own
ladder starts under the run's calibration (``RUN/render_compare_any_start.json``), every
refinement kept; each query's score gain, refined score, distance moved and position errors
go to ``RUN/gate_val.pt`` (made once, read back after). Then each gate family is fitted by
the calibration's objective (``log_ratio``) in a two-fold cross-validation over alternating
blocks of ``len(LADDER)`` queries, and its held-out objective printed and written to
``RUN/gate_val.json``. ``--audit-test APR``: an audit that reads the test labels
(:func:`audit_test`). ``--mixed``: also a ladder of compensated starts
(:func:`compensated_starts`, ``RUN/gate_val_compensated.pt``) and what today's gate fitted
on both ladders changes against it fitted on the random ladder alone, on each kind's
held-out queries (:func:`mixed_against_random`). Without ``--audit-test`` only validation
labels are read.

    python experiments/render_compare_real_starts/gate_val.py outputs/rsh_grow/fire \\
        outputs/rsh_grow/pumpkin --mixed
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import NamedTuple

import torch

from pae.apps import localization as loc
from pae.apps.match_inputs import run_train_images
from pae.core.atomic import atomic_write
from pae.core.checkpoints import load_scene_model, load_teacher
from pae.core.geometry import pose_errors, quaternion_to_matrix
from pae.core.pose_sampling import perturb
from pae.data.labels import read_labels
from pae.render_compare import ACCEPT_ALL, Calibration, Queries, refine
from pae.render_compare.calibration import (
    KEEP_ALL,
    LADDER,
    MARGIN_QUANTILES,
    RATIO_EPS_M,
    AnyStartOptions,
    ladder_starts,
    scene_size,
)
from pae.render_compare.correspondences import MatchQueries, TrainImages

LOOK_AT_SHARE = 0.5
"""A compensated start keeps on its optical axis the point this share of the scene's size
ahead of the true camera."""
MOVE_UNIT_SHARE = 0.01
"""Family C's unit distance: this share of the scene's size asks the margin m itself."""
NEVER = float("inf")
DISTANCE_BINS_M = ((0.02, 0.04), (0.04, 0.07), (0.07, 0.12))
"""The start distances (m) at which :func:`by_distance` compares kinds of starts."""


def compensated_starts(
    truth: torch.Tensor, size_m: float, generator: torch.Generator
) -> torch.Tensor:
    """Starts [N, 7] that leave the view nearly as it was, as an APR that regresses the pose
    from what the image shows errs: query i's camera moved by a distance uniform in [0, 2 x
    ``LADDER[i % K]`` x ``size_m``] (m) in a random direction, then turned (the least turn)
    so that the point ``LOOK_AT_SHARE`` x ``size_m`` ahead of the true camera stays on its
    optical axis."""
    count = len(truth)
    scale = torch.tensor(LADDER, dtype=torch.float64)[torch.arange(count) % len(LADDER)]
    direction = torch.randn(count, 3, generator=generator, dtype=torch.float64)
    direction = direction / direction.norm(dim=-1, keepdim=True)
    moved = direction * (2 * scale * size_m * torch.rand(count, generator=generator))[:, None]
    poses = truth.double()
    rotation = quaternion_to_matrix(poses[:, 3:])
    ahead = torch.tensor([0.0, 0.0, LOOK_AT_SHARE * size_m], dtype=torch.float64)
    axis_to = ahead - torch.einsum("nji,nj->ni", rotation, moved)  # in the camera's frame
    axis_to = axis_to / axis_to.norm(dim=-1, keepdim=True)
    cross = torch.stack(
        [-axis_to[:, 1], axis_to[:, 0], torch.zeros(count, dtype=torch.float64)], -1
    )
    sine = cross.norm(dim=-1, keepdim=True)
    turn = cross / sine.clamp_min(1e-12) * torch.atan2(sine, axis_to[:, 2:])
    return perturb(poses, torch.cat([moved, turn], -1)).to(truth)


class Loaded(NamedTuple):
    """A run's refiner settings, scene model, any-start calibration, train views (None:
    none read), data (set up) and scene size (m)."""

    settings: dict
    model: torch.nn.Module
    calibration: Calibration
    train: TrainImages | None
    data: object
    size_m: float


def loaded(folder: Path) -> Loaded:
    """The run in ``folder`` as its any-start refinement reads it (the calibration from
    ``RUN/render_compare_any_start.json``; chosen on val and written there first, as
    ``pae-localize`` does, where none was kept for the run's settings)."""
    run = loc.read_run(folder)
    settings, _ = loc.render_compare_settings(run)
    model = load_scene_model(loc.scene_model_path(run), "scene_model_ckpt").model.eval()
    teacher_path = loc.teacher_checkpoint(run, loc.RENDER_COMPARE)
    teacher = None if teacher_path is None else load_teacher(teacher_path)
    device = torch.device("cpu")
    calibration, train = loc.any_start_calibration(run, model, settings, None, device, teacher)
    data = loc.data_module(run, cache_images=False)
    data.setup()
    if calibration.match.active and train is None:
        train = run_train_images((run.folder, run.config), data, calibration.match.width, teacher)
    positions, _ = data.train_poses()
    return Loaded(settings, model, calibration, train, data, scene_size(positions[:, :3].double()))


def split_queries(run: Loaded, split: str) -> dict[str, torch.Tensor]:
    """The run's ``split`` as its refiner compares it (:func:`loc.split_queries`)."""
    return loc.split_queries(run.data, split, loc.compare_width(run.settings))


def every_kept(
    run: Loaded, split: str, queries: dict, rows: torch.Tensor, starts: torch.Tensor
) -> dict:
    """The ``split``'s ``queries`` (:func:`split_queries`) ``rows`` refined from starts
    [R, 7] under the run's calibration with every refinement kept: per query [R] the score
    gain, refined score, start's score, distance moved (m), start and refined position
    errors (m)."""
    matching = None
    if run.calibration.match.active:
        images, intrinsics = run.data.images_at(split, run.calibration.match.width)
        matching = MatchQueries(images[rows].float() / 255, intrinsics[rows], run.train)
    every = dataclasses.replace(run.calibration, accept_margin=ACCEPT_ALL, accept_score=ACCEPT_ALL)
    chosen = Queries(
        queries["image"][rows],
        queries["intrinsics"][rows],
        queries["scene"][rows],
        matching=matching,
    )
    begin = time.perf_counter()
    result = refine(run.model, chosen, starts, every, settings=run.settings).result
    print(f"{len(rows)} {split} queries refined in {time.perf_counter() - begin:.0f} s")
    truth = queries["pose"][rows]
    return {
        "gain": result.score - result.initial_score,
        "score": result.score,
        "initial": result.initial_score,
        "moved_m": pose_errors(result.poses.float(), starts.float())[0],
        "start_m": pose_errors(starts.float(), truth.float())[0],
        "refined_m": pose_errors(result.poses.float(), truth.float())[0],
    }


def refined_on_val(folder: Path, kind: str) -> dict[str, torch.Tensor | float]:
    """The run's val queries refined from the ladder starts (``kind``: ``random``, as the
    calibration draws them, or ``compensated``, :func:`compensated_starts`), every
    refinement kept (:func:`every_kept`), with each query's rung and the scene's size (m)."""
    run = loaded(folder)
    queries = split_queries(run, "val")
    truth = queries["pose"]
    generator = torch.Generator().manual_seed(AnyStartOptions().seed)
    draw = compensated_starts if kind == "compensated" else ladder_starts
    starts = draw(truth, run.size_m, generator)
    record = every_kept(run, "val", queries, torch.arange(len(truth)), starts)
    return record | {"rung": torch.arange(len(truth)) % len(LADDER), "size_m": run.size_m}


def audit_test(folder: Path, apr: str) -> dict[str, float]:
    """An audit (it reads the test labels): the test images ``run.py`` refined from
    ``RUN/starts_<apr>.csv``, from those starts with every refinement kept
    (``RUN/gate_test_audit_<apr>.pt``), and what the run's gate does with them."""
    stored = folder / f"gate_test_audit_{apr}.pt"
    run = loaded(folder)
    if stored.is_file():
        record = torch.load(stored, weights_only=True)
    else:
        path = folder / f"starts_{apr}.csv"
        starts = read_labels(path)
        row_of = {name: row for row, name in enumerate(run.data.tables["test"].img_path)}
        missing = [name for name in starts.img_path if name not in row_of]
        if missing:
            raise SystemExit(f"{path}: {missing[0]!r} is not a test image of the run")
        rows = torch.tensor([row_of[name] for name in starts.img_path])
        poses = torch.as_tensor(starts.poses).float()
        record = every_kept(run, "test", split_queries(run, "test"), rows, poses)
        with atomic_write(stored, "wb") as handle:
            torch.save(record, handle)
    margin, floor = run.calibration.accept_margin, run.calibration.accept_score
    passes_margin, passes_floor = record["gain"] > margin, record["score"] > floor
    kept = passes_margin & passes_floor
    gated = torch.where(kept, record["refined_m"], record["start_m"])
    turned = {"margin": ~passes_margin, "floor_alone": passes_margin & ~passes_floor}
    figures = {
        "accepted": float(kept.float().mean()),
        "gated_pos_median_m": float(gated.median()),
        "every_kept_pos_median_m": float(record["refined_m"].median()),
        "start_pos_median_m": float(record["start_m"].median()),
    }
    for name, rows in turned.items():
        figures[f"turned_by_{name}"] = float(rows.float().mean())
        if not rows.any():  # no medians of none
            continue
        figures[f"turned_by_{name}_start_median_m"] = float(record["start_m"][rows].median())
        figures[f"turned_by_{name}_refined_median_m"] = float(record["refined_m"][rows].median())
        nearer = record["refined_m"][rows] < record["start_m"][rows]
        figures[f"turned_by_{name}_nearer"] = float(nearer.float().mean())
    figures["by_distance"] = by_distance(record)
    with atomic_write(folder / f"gate_test_audit_{apr}.json") as handle:
        json.dump(figures, handle, indent=1)
    return figures


def by_distance(record: dict) -> list[dict[str, float]]:
    """Per bin of ``DISTANCE_BINS_M`` (the start's distance from the truth): how many
    queries, the medians of the start's score, the score gain and the refined pose's
    distance (m), and the share refined nearer than the start."""
    start_score = record["score"] - record["gain"]
    rows = []
    for low, high in DISTANCE_BINS_M:
        inside = (record["start_m"] > low) & (record["start_m"] < high)
        if not inside.any():  # no medians of none
            rows.append({"start_m": [low, high], "queries": 0})
            continue
        refined, start = record["refined_m"][inside], record["start_m"][inside]
        rows.append({
            "start_m": [low, high],
            "queries": int(inside.sum()),
            "start_score_median": float(start_score[inside].median()),
            "gain_median": float(record["gain"][inside].median()),
            "refined_median_m": float(refined.median()),
            "nearer": float((refined < start).float().mean()),
        })  # fmt: skip
    return rows


def distances_line(name: str, rows: list[dict[str, float]]) -> str:
    """:func:`by_distance`'s rows as one printed line."""
    return f"{name} by start distance: " + "; ".join(
        f"{100 * r['start_m'][0]:.0f}-{100 * r['start_m'][1]:.0f} cm: start score "
        f"{r['start_score_median']:.3f} gain {r['gain_median']:.3f} refined "
        f"{100 * r['refined_median_m']:.1f} cm, nearer {r['nearer']:.2f}"
        for r in rows
        if r["queries"]
    )


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


def joined(first: dict, second: dict) -> dict:
    """Two records of the same val queries as one of twice the queries."""
    return {
        key: torch.cat([value, second[key]]) if isinstance(value, torch.Tensor) else value
        for key, value in first.items()
        if key in second
    }


def mixed_against_random(random: dict, compensated: dict) -> dict[str, float]:
    """Today's family fitted on the random ladder alone and on both ladders together, each
    fold's fit scored on the other fold: how much the mixed gate changes the held-out
    objective of the random starts (``random_change``) and of the compensated ones
    (``compensated_change``), the mean over the two folds (negative: lower, better)."""
    count = len(random["gain"])
    block = (torch.arange(count) // len(LADDER)) % 2
    folds = [torch.nonzero(block == k).flatten() for k in (0, 1)]
    both = joined(random, compensated)
    changes = {"random_change": 0.0, "compensated_change": 0.0}
    for k in (0, 1):
        fit, held = folds[k], folds[1 - k]
        alone = fitted("A", random, fit)
        mixed = fitted("A", both, torch.cat([fit, fit + count]))
        for name, record in (("random_change", random), ("compensated_change", compensated)):
            value = {
                gate: objective(record, held, accepted("A", record, held, gate))
                for gate in (alone, mixed)
            }
            changes[name] += (value[mixed] - value[alone]) / 2
    return changes


def stored_record(folder: Path, kind: str) -> dict:
    """The val record of ``kind`` starts, made once and read back after."""
    stored = folder / ("gate_val.pt" if kind == "random" else f"gate_val_{kind}.pt")
    if stored.is_file():
        return torch.load(stored, weights_only=True)
    record = refined_on_val(folder, kind)
    with atomic_write(stored, "wb") as handle:
        torch.save(record, handle)
    return record


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", type=Path, nargs="+")
    parser.add_argument(
        "--mixed",
        action="store_true",
        help="also the compensated ladder (compensated_starts) and the gate fitted on both "
        "ladders against the gate fitted on the random one (mixed_against_random)",
    )
    parser.add_argument(
        "--audit-test",
        metavar="APR",
        help="an audit that reads the test labels: the run's test rows refined from "
        "RUN/starts_<APR>.csv with every refinement kept, and what the gate does with them",
    )
    args = parser.parse_args(argv)
    if args.audit_test and args.mixed:
        parser.error("--audit-test and --mixed are separate runs: give one")
    for folder in args.runs:
        if args.audit_test:
            figures = audit_test(folder, args.audit_test)
            rows = figures.pop("by_distance")
            print(f"{folder.name} {args.audit_test} (audit): {figures}")
            print(distances_line(f"{folder.name} test, {args.audit_test}'s starts", rows))
            continue
        out = folder / "gate_val.json"
        families = json.loads(out.read_text()) if out.is_file() else {}  # earlier --mixed kept
        record = stored_record(folder, "random")
        families |= cross_validated(record)
        families["by_distance"] = by_distance(record)
        print(distances_line(f"{folder.name} val, random ladder", families["by_distance"]))
        if args.mixed:
            compensated = stored_record(folder, "compensated")
            families["mixed"] = mixed_against_random(record, compensated)
            families["compensated_by_distance"] = by_distance(compensated)
            rows = families["compensated_by_distance"]
            print(distances_line(f"{folder.name} val, compensated ladder", rows))
            print(f"{folder.name} mixed ladder: {families['mixed']}")
        with atomic_write(out) as handle:
            json.dump(families, handle, indent=1)
        for family in ("A", "B", "C"):
            row = families[family]
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
