"""Top-down trajectory figure of one scene: ground-truth positions and each method's
estimates, with axes in metres, a legend and the scene's name (drawn with OpenCV)."""

from __future__ import annotations

import math
from collections.abc import Mapping

import cv2
import lightning as L
import numpy as np
from torch import Tensor

from pae.callbacks.tensorboard import log_figure, tensorboard_loggers

GROUND_TRUTH_RGB = (0, 160, 0)
METHOD_RGB = (
    (220, 0, 0),
    (0, 0, 220),
    (230, 140, 0),
    (150, 0, 180),
    (0, 160, 200),
    (120, 80, 40),
    (220, 0, 160),
)
"""Colours of the methods in the order given (the teacher first: red, then blue, ...)."""
AXIS_NAMES = ("x", "y", "z")
FONT = cv2.FONT_HERSHEY_SIMPLEX
MARGIN = {"left": 70, "right": 230, "top": 36, "bottom": 52}
"""Pixels around the plot: tick labels left and below, the title above, the legend right."""


def nice_step(span: float, ticks: int = 5) -> float:
    """A tick spacing of 1, 2 or 5 × 10^k metres giving about `ticks` ticks over `span`."""
    raw = max(span, 1e-9) / ticks
    power = 10 ** math.floor(math.log10(raw))
    return min((m * power for m in (1, 2, 5, 10)), key=lambda s: abs(s - raw))


def draw_text(image: np.ndarray, text: str, at: tuple[int, int], scale: float = 0.45) -> None:
    """Black text on ``image`` [H, W, 3] with its baseline's left end at ``at`` (u, v px)."""
    cv2.putText(image, text, at, FONT, scale, (0, 0, 0), 1, cv2.LINE_AA)


def _stamp(image: np.ndarray, pixels: np.ndarray, colour: tuple[int, int, int]) -> None:
    """Dots of radius 2 px at `pixels` [N, 2] (u, v), all at once."""
    offsets = np.stack(np.meshgrid(np.arange(-2, 3), np.arange(-2, 3)), -1).reshape(-1, 2)
    offsets = offsets[(offsets**2).sum(1) <= 5]
    dots = pixels[:, None, :] + offsets  # [N, D, 2]
    h, w = image.shape[:2]
    dots = dots.reshape(-1, 2)
    inside = (dots[:, 0] >= 0) & (dots[:, 0] < w) & (dots[:, 1] >= 0) & (dots[:, 1] < h)
    dots = dots[inside]
    image[dots[:, 1], dots[:, 0]] = colour


def trajectory_figure(
    title: str,
    ground_truth: Tensor,
    estimates: Mapping[str, Tensor],
    width: int = 720,
    height: int = 540,
) -> np.ndarray:
    """Ground-truth positions and each method's estimates (poses [N, 7], in metres) of one
    scene, seen from above along the two position axes of largest spread, on one metre scale
    for both axes -> RGB uint8 [height, width, 3]. The legend names each method with its
    median position error; ground truth is green, the methods take METHOD_RGB in order."""
    gt = ground_truth[:, :3].detach().cpu().double().numpy()
    tracks = {
        name: poses[:, :3].detach().cpu().double().numpy() for name, poses in estimates.items()
    }
    axes = np.argsort(-gt.var(0), kind="stable")[:2]
    every = np.concatenate([gt, *tracks.values()])[:, axes]
    low, high = every.min(0), every.max(0)
    span = np.maximum(high - low, 1e-6)
    plot_w = width - MARGIN["left"] - MARGIN["right"]
    plot_h = height - MARGIN["top"] - MARGIN["bottom"]
    pad = 12  # pixels between the outermost points and the frame
    scale = min((plot_w - 2 * pad) / span[0], (plot_h - 2 * pad) / span[1])  # px per metre
    centre = (low + high) / 2
    origin = np.array([MARGIN["left"] + plot_w / 2, MARGIN["top"] + plot_h / 2])

    def to_pixels(points: np.ndarray) -> np.ndarray:
        uv = (points[:, axes] - centre) * scale
        return np.round(origin + uv * np.array([1.0, -1.0])).astype(np.int64)

    image = np.full((height, width, 3), 255, np.uint8)
    left, top = MARGIN["left"], MARGIN["top"]
    right, bottom = width - MARGIN["right"], height - MARGIN["bottom"]
    cv2.rectangle(image, (left, top), (right, bottom), (0, 0, 0), 1)
    visible_low = centre - np.array([plot_w, plot_h]) / 2 / scale
    visible_high = centre + np.array([plot_w, plot_h]) / 2 / scale
    for dim in (0, 1):
        step = nice_step(visible_high[dim] - visible_low[dim])
        decimals = max(0, -math.floor(math.log10(step)))
        first = math.ceil(visible_low[dim] / step)
        for index in range(first, math.floor(visible_high[dim] / step) + 1):
            value = index * step
            point = np.zeros((1, 3))
            point[0, axes[dim]] = value
            point[0, axes[1 - dim]] = centre[1 - dim]
            u, v = to_pixels(point)[0]
            label = f"{value:.{decimals}f}"
            if dim == 0:
                cv2.line(image, (int(u), bottom), (int(u), bottom + 5), (0, 0, 0), 1)
                draw_text(image, label, (int(u) - 4 * len(label), bottom + 20))
            else:
                cv2.line(image, (left - 5, int(v)), (left, int(v)), (0, 0, 0), 1)
                draw_text(image, label, (left - 10 - 8 * len(label), int(v) + 4))
    draw_text(image, f"{AXIS_NAMES[axes[0]]} [m]", ((left + right) // 2 - 15, height - 12), 0.5)
    draw_text(image, f"{AXIS_NAMES[axes[1]]} [m]", (8, top - 12), 0.5)
    draw_text(image, title, (left, 22), 0.55)

    legend = [("ground truth", GROUND_TRUTH_RGB, gt)]
    legend += [
        (name, METHOD_RGB[i % len(METHOD_RGB)], points)
        for i, (name, points) in enumerate(tracks.items())
    ]
    for row, (name, colour, points) in enumerate(legend):
        _stamp(image, to_pixels(points), colour)
        y = top + 14 + 22 * row
        _stamp(image, np.array([[right + 18, y - 4]]), colour)
        error = np.median(np.linalg.norm(points - gt, axis=1)) if row else None
        label = name if error is None else f"{name} (median {error:.2f} m)"
        draw_text(image, label, (right + 28, y))
    return image


def log_trajectories(
    trainer: L.Trainer,
    split: str,
    truth: Tensor,
    estimates: Mapping[str, Tensor],
    scene: Tensor,
    names: list[str],
) -> None:
    """A trajectory figure per scene of scene ids [N] (TensorBoard image
    ``{split}/trajectory/<scene>``): the true poses [N, 7] and each method's (method -> poses
    [N, 7]), in the order given."""
    loggers = tensorboard_loggers(trainer)
    if not loggers:
        return
    for index in scene.unique().tolist():
        mask = scene == index
        title = f"{names[index]}: {split} positions from above ({int(mask.sum())} frames)"
        image = trajectory_figure(
            title, truth[mask], {m: poses[mask] for m, poses in estimates.items()}
        )
        log_figure(loggers, f"{split}/trajectory/{names[index]}", image, trainer.global_step)
