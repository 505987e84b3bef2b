"""Render-and-compare's figures: a gallery of queries beside the scene model's renderings,
their captions, and the per-query errors of each method read back from the query files
(``pae.render_compare.queries``)."""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor, nn

FONT = cv2.FONT_HERSHEY_SIMPLEX
LABEL_PX = 30
"""Height (px) of the two text lines above each panel."""


def gallery_figure(
    title: str, panels: Tensor, labels: list[list[str]], panel_px: int
) -> np.ndarray:
    """Rows of RGB panels [R, C, 3, h, w] in [0, 1], each scaled to ``panel_px`` px wide and
    captioned with its two lines of ``labels`` [R][C] ('first line|second line'), under a
    ``title`` -> uint8 image [H, W, 3]."""
    rows, columns, _, h, w = panels.shape
    height = round(panel_px * h / w)
    scaled = nn.functional.interpolate(
        panels.flatten(0, 1), size=(height, panel_px), mode="nearest"
    )
    cells = (scaled.clamp(0, 1) * 255).byte().permute(0, 2, 3, 1).cpu().numpy()
    cell_h, cell_w = height + LABEL_PX, panel_px + 6
    image = np.full((24 + rows * cell_h, columns * cell_w, 3), 255, np.uint8)
    cv2.putText(image, title, (4, 16), FONT, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    for r in range(rows):
        for c in range(columns):
            top, left = 24 + r * cell_h, c * cell_w + 3
            image[top + LABEL_PX : top + cell_h, left : left + panel_px] = cells[r * columns + c]
            for line, text in enumerate(labels[r][c].split("|")):
                at = (left, top + 11 + 12 * line)
                cv2.putText(image, text, at, FONT, 0.36, (0, 0, 0), 1, cv2.LINE_AA)
    return image


def gallery_labels(
    index: Tensor, errors: list[tuple[Tensor, Tensor]], accepted: Tensor
) -> list[list[str]]:
    """Each picked query's captions: its row, the teacher's errors, the refined pose's."""
    (start_pos, start_rot), (pos, rot) = errors
    verdict = ["kept", "rejected"]
    return [
        [
            f"query|row {int(i)}",
            f"teacher|{float(sp):.2f} m {float(sr):.1f} deg",
            f"refined: {verdict[0 if a else 1]}|{float(p):.2f} m {float(r):.1f} deg",
        ]
        for i, sp, sr, p, r, a in zip(
            index.tolist(), start_pos, start_rot, pos, rot, accepted.tolist(), strict=True
        )
    ]


def read_query_errors(
    folder: Path, split: str, methods: tuple[str, ...]
) -> tuple[dict[str, Tensor], dict[str, Tensor], list[str]]:
    """Per-query position (m) and orientation (deg) errors [N] of the start (``teacher``)
    and of each of ``methods`` after its gate, read from ``queries_{split}_{method}.csv`` in
    ``folder`` (missing files skipped) -> position and orientation errors by method, and
    each query's scene name."""
    position: dict[str, Tensor] = {}
    orientation: dict[str, Tensor] = {}
    scenes: list[str] = []
    for name in methods:
        path = folder / f"queries_{split}_{name}.csv"
        if not path.is_file():
            continue
        with path.open(newline="") as handle:
            rows = list(csv.DictReader(handle))
        if not rows:
            continue

        def column(key: str, rows: list[dict[str, str]] = rows) -> Tensor:
            return torch.tensor([float(row[key]) for row in rows])

        scenes = [row["scene"] for row in rows]
        accepted = column("accepted") > 0
        position.setdefault("teacher", column("start_pos_m"))
        orientation.setdefault("teacher", column("start_rot_deg"))
        position[name] = torch.where(accepted, column("refined_pos_m"), position["teacher"])
        orientation[name] = torch.where(accepted, column("refined_rot_deg"), orientation["teacher"])
    return position, orientation, scenes
