"""The render-and-compare calibration for another APR's starts (``pae-localize --init FILE
--init-gate any``): chosen once on the run's validation split and kept in the run folder, so
that every later call with the same settings and scene model applies the same gate and steps
without choosing them again."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch

from pae.core.atomic import atomic_write
from pae.core.geometry import pose_errors
from pae.render_compare import AnyStartOptions, Calibration, Queries, calibrate_any_start
from pae.render_compare.correspondences import MatchQueries, MatchSettings
from pae.scene_model.base import SceneModel

CALIBRATION_FILE = "render_compare_any_start.json"
"""The run folder's record of the calibration for any start (:func:`any_start_calibration`)."""


def calibration_key(
    settings: dict[str, Any],
    scene_model: Path,
    features: bool,
    matches: Sequence[Mapping[str, Any]] = (),
    filters: Sequence[Mapping[str, float]] = (),
    shares: Sequence[float] = (),
) -> str:
    """What the calibration depends on: the refiner's settings, the scene model's checkpoint
    (its path, size and a SHA-256 of its first MiB), whether features are compared, the
    correspondence stages, the further filters and the stage's shares of the queries tried
    (none tried: the key of a calibration that tried none)."""
    with scene_model.open("rb") as handle:
        head = hashlib.sha256(handle.read(1 << 20)).hexdigest()
    stated = {
        "settings": settings,
        "scene_model": [str(scene_model.resolve()), scene_model.stat().st_size, head],
        "features": features,
    }
    if matches:
        stated["matches"] = [dict(m) for m in matches]
    if filters:
        stated["filters"] = [dict(f) for f in filters]
    if matches and shares:
        stated["stage_shares"] = [float(share) for share in shares]
    return hashlib.sha256(json.dumps(stated, sort_keys=True).encode()).hexdigest()


def calibration_record(calibration: Calibration) -> dict[str, Any]:
    """The gate, steps and correspondence stage of ``calibration`` as JSON values (``match``
    only where a stage runs)."""
    record: dict[str, Any] = {
        "accept_margin": calibration.accept_margin,
        "accept_score": calibration.accept_score,
        "steps": dict(calibration.steps),
    }
    if calibration.match.active:
        record["match"] = dataclasses.asdict(calibration.match)
    return record


def read_calibration(path: Path, key: str) -> Calibration | None:
    """The calibration recorded in ``path`` under ``key``; None where the file is absent,
    unreadable or was chosen for other settings or another scene model."""
    try:
        record = json.loads(path.read_text())
        if record.get("key") != key:
            return None
        chosen = record["calibration"]
        steps = {name: float(value) for name, value in chosen["steps"].items()}
        match = MatchSettings(**chosen.get("match", {}))
        return Calibration(
            float(chosen["accept_margin"]), float(chosen["accept_score"]), steps, match=match
        )
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        return None


def val_figures(poses: torch.Tensor, truth: torch.Tensor) -> dict[str, float]:
    """Median position (m) and orientation (deg) errors of ``poses`` [N, 7] against ``truth``
    [N, 7], and the share within 5 cm and 5 deg."""
    position, orientation = pose_errors(poses.float(), truth.float())
    within = ((position < 0.05) & (orientation < 5.0)).float().mean()
    return {
        "pos_median_m": float(position.median()),
        "rot_median_deg": float(orientation.median()),
        "within_5cm_5deg": float(within),
    }


def any_start_calibration(
    folder: Path,
    scene_model: tuple[SceneModel, Path],
    val: dict[str, torch.Tensor],
    size_m: float,
    settings: dict[str, Any],
    features: Any,
    stages: tuple[Sequence[Mapping[str, Any]], Callable[[], MatchQueries] | None] = ((), None),
    filters: Sequence[Mapping[str, float]] = (),
    shares: Sequence[float] = (),
) -> Calibration:
    """The gate, first steps and correspondence stage for starts from another APR, chosen on
    the validation queries ``val`` (``image``, ``intrinsics``, ``scene``, true ``pose``, as
    :func:`pae.apps.localization.split_queries` gives them, on the scene model's device) with
    :func:`pae.render_compare.calibrate_any_start` (starts at every error scale of the scene's
    size ``size_m``, m; ``stages``: the correspondence stages to try, mappings of
    ``MatchSettings``, and what reads the val queries at their match width, called only
    where the stages are tried; None: no stage tried; ``filters``: filters to try besides
    the built-in ones, the run's ``render_compare.filters_from_val``; ``shares``: the shares
    of the val queries the kept stage may go to, ``render_compare.match_shares_from_val``), read
    from ``FOLDER/render_compare_any_start.json`` where an earlier call chose them under the
    same settings, stages and scene model (its checkpoint's path in ``scene_model``), else
    chosen and written there with the val figures (a read-only folder only warns)."""
    model, checkpoint = scene_model
    matches, read_matching = stages if stages[1] is not None else ((), None)
    path = folder / CALIBRATION_FILE
    key = calibration_key(settings, checkpoint, features is not None, matches, filters, shares)
    recorded = read_calibration(path, key)
    if recorded is not None:
        print(f"pae-localize: the calibration for any start from {path}", file=sys.stderr)
        return recorded
    truth = val["pose"]
    matching = None if read_matching is None else read_matching()
    queries = Queries(val["image"], val["intrinsics"], val["scene"], matching=matching)
    calibration, refined, starts = calibrate_any_start(
        model, queries, truth, size_m, settings | {"features": features},
        AnyStartOptions(matches=matches, filters=filters, stage_shares=shares),
    )  # fmt: skip
    record = {
        "key": key,
        "calibration": calibration_record(calibration),
        "val_queries": len(truth),
        "scene_size_m": size_m,
        "val": {
            "start": val_figures(starts, truth),
            "render_compare": val_figures(refined.poses, truth),
        },
    }
    if refined.matched is not None:
        record["val"]["keypoints_found_share"] = float(refined.matched.float().mean())
        record["val"]["other_start_kept_share"] = float(refined.from_match.float().mean())
    try:
        with atomic_write(path) as handle:
            json.dump(record, handle, indent=1)
        print(
            f"pae-localize: the calibration for any start, chosen on val: {path}", file=sys.stderr
        )
    except OSError as err:
        print(f"pae-localize: warning: the calibration is not kept ({err})", file=sys.stderr)
    return calibration
