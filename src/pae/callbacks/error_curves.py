"""Cumulative error curves, the standard localisation plot: per method the share of queries
whose position (orientation) error lies within each threshold (drawn with OpenCV)."""

from __future__ import annotations

import math
from collections.abc import Mapping

import cv2
import lightning as L
import numpy as np
from torch import Tensor

from pae.callbacks.tensorboard import log_figure, tensorboard_loggers
from pae.callbacks.trajectory import METHOD_RGB, draw_text, nice_step
from pae.core.geometry import pose_errors
from pae.core.metrics import summarise_errors

MARGIN = {"left": 56, "right": 240, "top": 36, "bottom": 46}
"""Pixels around each plot: tick labels left and below, the title above, the legend right."""


def error_curve(
    title: str,
    unit: str,
    errors: Mapping[str, Tensor],
    medians: Mapping[str, float] | None = None,
    width: int = 610,
    height: int = 360,
) -> np.ndarray:
    """One plot of the cumulative share of queries (0-1) within each error (x, in ``unit``)
    for each method of ``errors`` (name -> errors [N]), up to the 95th percentile of the
    first method's errors -> RGB uint8 [height, width, 3]. The legend names each method
    with its median (``medians``, e.g. the results table's average of per-scene medians;
    default: over all queries); methods take METHOD_RGB in order."""
    values = {name: np.sort(e.detach().cpu().double().numpy()) for name, e in errors.items()}
    first = next(iter(values.values()))
    limit = float(np.quantile(first, 0.95)) if len(first) else 1.0
    limit = max(limit, 1e-6)
    left, top = MARGIN["left"], MARGIN["top"]
    right, bottom = width - MARGIN["right"], height - MARGIN["bottom"]
    image = np.full((height, width, 3), 255, np.uint8)
    cv2.rectangle(image, (left, top), (right, bottom), (0, 0, 0), 1)

    def to_pixels(x: np.ndarray, share: np.ndarray) -> np.ndarray:
        u = left + np.clip(x / limit, 0, 1) * (right - left)
        v = bottom - share * (bottom - top)
        return np.round(np.stack([u, v], -1)).astype(np.int32)

    step = nice_step(limit)
    decimals = max(0, -math.floor(math.log10(step)))
    for index in range(math.floor(limit / step) + 1):
        u = int(to_pixels(np.array([index * step]), np.array([0.0]))[0, 0])
        cv2.line(image, (u, bottom), (u, bottom + 5), (0, 0, 0), 1)
        label = f"{index * step:.{decimals}f}"
        draw_text(image, label, (u - 4 * len(label), bottom + 20))
    for share in (0.0, 0.25, 0.5, 0.75, 1.0):
        v = int(to_pixels(np.array([0.0]), np.array([share]))[0, 1])
        cv2.line(image, (left - 5, v), (left, v), (0, 0, 0), 1)
        draw_text(image, f"{share:.2f}", (left - 44, v + 4))
    label_at = ((left + right) // 2 - 80, height - 10)
    draw_text(image, f"error [{unit}]; legend: median", label_at, 0.5)
    draw_text(image, title, (left, 22), 0.55)
    for row, (name, sorted_errors) in enumerate(values.items()):
        colour = METHOD_RGB[row % len(METHOD_RGB)]
        n = len(sorted_errors)
        share = np.arange(1, n + 1) / max(n, 1)
        steps = np.concatenate([[0.0], np.repeat(sorted_errors, 2)])  # up at each error
        heights = np.concatenate([[0.0, 0.0], np.repeat(share, 2)[:-1]])
        points = to_pixels(steps, heights)
        cv2.polylines(image, [points.reshape(-1, 1, 2)], False, colour, 2, cv2.LINE_AA)
        y = top + 14 + 22 * row
        cv2.line(image, (right + 10, y - 4), (right + 26, y - 4), colour, 2)
        median = float(np.median(sorted_errors)) if n else float("nan")
        median = (medians or {}).get(name, median)
        digits = 3 if unit == "m" else 2  # as the results tables
        draw_text(image, f"{name} ({median:.{digits}f})", (right + 32, y))
    return image


def error_curves_figure(
    title: str,
    position: Mapping[str, Tensor],
    orientation: Mapping[str, Tensor],
    scene: Tensor,
    scene_names: list[str],
) -> np.ndarray:
    """The position (m) and orientation (deg) curves of the same methods (name -> errors
    [N] of queries of scene ids ``scene`` [N]), one above the other, under ``title``, the
    legend's medians as the results table's (per scene, averaged over scenes) -> RGB
    uint8 [H, W, 3]."""
    summaries = {
        name: summarise_errors(position[name], orientation[name], scene, scene_names)
        for name in position
    }
    return np.concatenate(
        [
            error_curve(
                f"{title}: position",
                "m",
                position,
                {name: float(s["pos_median_m"]) for name, s in summaries.items()},
            ),
            error_curve(
                f"{title}: orientation",
                "deg",
                orientation,
                {name: float(s["rot_median_deg"]) for name, s in summaries.items()},
            ),
        ]
    )


def log_error_curves(
    trainer: L.Trainer,
    split: str,
    methods: Mapping[str, Tensor],
    truth: Tensor,
    scene: Tensor,
    names: list[str],
) -> None:
    """Cumulative error curves of ``methods`` (name -> poses [N, 7]) against the true poses
    [N, 7] of scenes ``scene`` [N]: TensorBoard image ``{split}/cumulative_errors``."""
    loggers = tensorboard_loggers(trainer)
    if not loggers:
        return
    errors = {m: pose_errors(p.float(), truth.float()) for m, p in methods.items()}
    image = error_curves_figure(
        f"{split} split, {len(truth)} queries",
        {m: e[0] for m, e in errors.items()},
        {m: e[1] for m, e in errors.items()},
        scene,
        names,
    )
    log_figure(loggers, f"{split}/cumulative_errors", image, trainer.global_step)
