"""Render-and-compare's per-query record (a CSV per split and method) and its gate's
figures."""

from __future__ import annotations

import csv
import dataclasses
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from pae.core.atomic import atomic_write
from pae.core.geometry import pose_errors
from pae.core.metrics import summarise_errors
from pae.render_compare.keypoints import DETECTORS, MatchSettings

QUERY_COLUMNS = (
    "index",
    "scene",
    "start_pos_m",
    "start_rot_deg",
    "refined_pos_m",
    "refined_rot_deg",
    "start_score",
    "refined_score",
    "accepted",
)


def write_queries(
    path: Path,
    index: Tensor,
    scenes: list[str],
    start: tuple[Tensor, Tensor],
    refined: tuple[Tensor, Tensor],
    refinement: Any,
) -> None:
    """One row per query [N] (``QUERY_COLUMNS``, in split order): its row ``index`` in the
    split's label file, scene name, the position (m) and orientation (deg) errors of the
    start and of the refined pose (before the gate), both scores and the gate's verdict
    (:class:`pae.render_compare.Refinement`); written atomically."""
    order = index.argsort()
    columns = [
        index,
        *start,
        *refined,
        refinement.result.initial_score,
        refinement.result.score,
        refinement.accepted.int(),
    ]
    values = [c[order].tolist() for c in columns]
    with atomic_write(path, newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(QUERY_COLUMNS)
        for i, row in enumerate(zip(*values, strict=True)):
            name = scenes[int(order[i])]
            numbers = [f"{v:.5f}" for v in row[1:-1]]
            writer.writerow([int(row[0]), name, *numbers, int(row[-1])])


def gate_figures(
    prefix: str,
    setting: tuple[float, float],
    accepted: Tensor,
    pos: Tensor,
    refined_pos: Tensor,
) -> dict[str, Tensor]:
    """The acceptance gate's figures under ``prefix``: its margin and score floor
    (``setting``), the share accepted, the median position error (m) of accepted and of
    rejected queries (where there are any) after the gate [N], and of every refinement
    accepted (``ungated``)."""
    figures = {
        f"{prefix}/accept_margin": torch.tensor(setting[0]),
        f"{prefix}/accept_score": torch.tensor(setting[1]),
        f"{prefix}/accepted_share": accepted.float().mean(),
        f"{prefix}/ungated_pos_median_m": refined_pos.quantile(0.5),
    }
    for kind, rows in (("accepted", accepted), ("rejected", ~accepted)):
        if rows.any():
            figures[f"{prefix}/{kind}_pos_median_m"] = pos[rows].quantile(0.5)
    return figures


def refinement_figures(
    prefix: str,
    refinement: Any,
    calibration: Any,
    starts: Tensor,
    truth: Tensor,
    scenes: Tensor,
    scene_names: list[str],
    predicted: Tensor | None = None,
) -> tuple[dict[str, Tensor], tuple[Tensor, Tensor], tuple[Tensor, Tensor]]:
    """Figures under ``prefix`` of a :class:`pae.render_compare.Refinement` of ``starts``
    [N, 7] under ``calibration`` against the true poses [N, 7] and scenes [N]: the error
    summary after the gate, the gate's figures (:func:`gate_figures`),
    ``worse_than_start_share`` and, where scenes were decided from the teacher's
    ``predicted`` scenes [N] (None: not), ``scene_accuracy``, the scene rule's settings
    (:class:`pae.render_compare.scene_decision.SceneRule`), ``scene_checked_share`` and
    ``scene_moved_share``; where a correspondence stage ran (``calibration.match``), its
    settings (``match_<setting>``: :func:`match_figures`), ``match_found_share`` (queries
    whose keypoints gave a pose) and ``match_kept_share`` (those whose kept refinement started
    from another start than the APR's) -> the figures and the position (m)
    and orientation (deg) errors [N] of the starts and of the refined poses before the gate."""
    start_errors = pose_errors(starts.float(), truth.float())
    refined_errors = pose_errors(refinement.result.poses.float(), truth.float())
    pos, rot = pose_errors(refinement.poses.float(), truth.float())
    summary = summarise_errors(pos, rot, scenes, scene_names)
    figures = {f"{prefix}/{key}": value for key, value in summary.items()}
    setting = (calibration.accept_margin, calibration.accept_score)
    figures |= gate_figures(prefix, setting, refinement.accepted, pos, refined_errors[0])
    figures[f"{prefix}/worse_than_start_share"] = (pos > start_errors[0]).float().mean()
    if predicted is not None:
        rule = calibration.scene
        figures[f"{prefix}/scene_accuracy"] = (refinement.scenes == scenes).float().mean()
        figures[f"{prefix}/scene_check_below"] = torch.tensor(rule.check_below)
        figures[f"{prefix}/scene_probe_scale"] = torch.tensor(rule.probe_scale)
        figures[f"{prefix}/scene_prior_weight"] = torch.tensor(rule.prior_weight)
        figures[f"{prefix}/scene_move_margin"] = torch.tensor(rule.margin)
        figures[f"{prefix}/scene_checked_share"] = refinement.checked.float().mean()
        figures[f"{prefix}/scene_moved_share"] = (refinement.scenes != predicted).float().mean()
    match = getattr(calibration, "match", None)
    if match is not None and getattr(refinement, "matched", None) is not None:
        figures |= {f"{prefix}/{k}": torch.tensor(v) for k, v in match_figures(match).items()}
        figures[f"{prefix}/match_found_share"] = refinement.matched.float().mean()
        figures[f"{prefix}/match_kept_share"] = refinement.from_match.float().mean()
    return figures, start_errors, refined_errors


def match_figures(match: MatchSettings) -> dict[str, float]:
    """A correspondence stage's settings as numbers, ``match_<setting>`` (the detector as its
    index in ``DETECTORS``): what a run records of the stage val chose."""
    values = dataclasses.asdict(match) | {"detector": DETECTORS.index(match.detector)}
    return {f"match_{key}": float(value) for key, value in values.items()}


def recorded_match(figures: Mapping[str, Any], prefix: str) -> MatchSettings | None:
    """The stage :func:`match_figures` recorded under ``prefix`` in ``figures`` (None: none;
    a setting a record predates takes its default)."""
    values = {
        field.name: figures.get(f"{prefix}/match_{field.name}")
        for field in dataclasses.fields(MatchSettings)
    }
    if values["width"] is None:
        return None
    default = MatchSettings()
    if values["detector"] is not None:
        values["detector"] = DETECTORS[int(values["detector"])]
    return MatchSettings(
        **{
            k: getattr(default, k) if v is None else type(getattr(default, k))(v)
            for k, v in values.items()
        }
    )


def method_from(path: str | Path) -> str:
    """The method name of render-and-compare from the starts in ``path``:
    ``render_compare_from_<its stem>`` (characters other than letters, digits and ``_``
    replaced by ``_``)."""
    stem = "".join(c if c.isalnum() or c == "_" else "_" for c in Path(path).stem)
    return f"render_compare_from_{stem}"
