"""Render-and-compare's per-query record (a CSV per split and method) and its gate's
figures."""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from pae.core.atomic import atomic_write
from pae.render_compare.gate import RenderCompareResult

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
    result: RenderCompareResult,
    gated: Any,
) -> None:
    """One row per query [N] (``QUERY_COLUMNS``, in split order): its row ``index`` in the
    split's label file, scene name, the position (m) and orientation (deg) errors of the
    start and of the refined pose (before the gate), both scores and the gate's verdict;
    written atomically."""
    order = index.argsort()
    columns = [
        index,
        *start,
        *refined,
        result.initial_score,
        result.score,
        gated.accepted.int(),
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
