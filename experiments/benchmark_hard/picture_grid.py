"""A picture grid of the easy and the hard synthetic benchmark, frame beside frame.

    python experiments/benchmark_hard/picture_grid.py [--experiment demo_hard] [--frames 4]
        [--out outputs/benchmark_hard/grid.png]

Renders a few frames of the first train sequence of each scene, spread along it, twice: with
the data settings of `experiment=demo` (the easy benchmark) and with those of the given
experiment (by default `demo_hard`), the way `pae-data synth` renders them (only the sensor
noise is drawn afresh). Each row is one frame; the columns: the easy frame, the hard frame as
stored (render_scale times the size) and the hard frame as the loaders see it (downsampled to
data.shorter_edge with OpenCV's area filter), all shown 256 px wide. Writes one PNG.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np

from pae import synthetic
from pae.config.schemas import compose_config

SHOWN_PX = 256
"""Width and height (px) each frame is shown at."""
LABEL_PX = 22
"""Height (px) of the band holding the column titles."""


def data_settings(experiment: str) -> tuple[synthetic.SyntheticSettings, int]:
    """The synthetic benchmark's settings in ``data`` of ``experiment`` (a name under
    conf/experiment) and the size (px) its loaders downsample the images to."""
    cfg = compose_config("train", [f"experiment={experiment}"])
    given = {name: cfg.data[name] for name in synthetic.SyntheticSettings.names() if name != "seed"}
    return synthetic.SyntheticSettings(**given, seed=cfg.data.render_seed), cfg.data.shorter_edge


def render_frames(settings: synthetic.SyntheticSettings, frames: int) -> list[np.ndarray]:
    """``frames`` images ``[S, S, 3]`` uint8 RGB (``S``: size × render_scale) of the first
    train sequence of each scene, spread evenly along it, rendered with ``settings``."""
    size, seed, capture = settings.size, settings.seed, settings.capture
    camera = synthetic.PinholeCamera(size)
    stored = synthetic.PinholeCamera(size * capture.render_scale)
    images = []
    for index in range(settings.scenes):
        scene = synthetic.make_scene(index, seed, settings.test_offset_m, settings.train_lane_m)
        scene = synthetic.dress_surfaces(
            scene, settings.surfaces, synthetic.surface_seed(seed, index)
        )
        sequence = synthetic.make_sequences(index, scene, settings)[0]
        appearance, conditions = synthetic.sequence_conditions(
            scene, sequence, camera, settings.nuisances, capture
        )
        conditions = synthetic.scaled_blur(conditions, capture.render_scale)
        step = len(sequence.poses) // frames
        chosen = slice(0, step * frames, step)
        images += list(
            synthetic.render_batch(
                scene,
                sequence.poses[chosen],
                stored,
                appearance,
                np.random.default_rng(list(sequence.noise_seed)),
                conditions=None if conditions is None else conditions[chosen],
            )
        )
    return images


def shown(image: np.ndarray, side: int | None = None) -> np.ndarray:
    """``image`` downsampled (area) to ``side`` px if given, then shown at :data:`SHOWN_PX`
    (nearest neighbour, so pixels stay visible)."""
    if side is not None and side != image.shape[0]:
        image = cv2.resize(image, (side, side), interpolation=cv2.INTER_AREA)
    return cv2.resize(image, (SHOWN_PX, SHOWN_PX), interpolation=cv2.INTER_NEAREST)


def titled(columns: list[np.ndarray], titles: list[str]) -> np.ndarray:
    """The ``columns`` (each ``[H, SHOWN_PX, 3]``) side by side under a band of ``titles``,
    4 px apart."""
    gap = np.full((columns[0].shape[0], 4, 3), 255, np.uint8)
    body = np.concatenate([part for column in columns for part in (column, gap)][:-1], axis=1)
    band = np.full((LABEL_PX, body.shape[1], 3), 255, np.uint8)
    for number, title in enumerate(titles):
        origin = (number * (SHOWN_PX + 4) + 4, LABEL_PX - 7)
        cv2.putText(band, title, origin, cv2.FONT_HERSHEY_SIMPLEX, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([band, body], axis=0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--experiment", default="demo_hard", help="the hard benchmark's config")
    parser.add_argument("--frames", type=int, default=4, help="frames per scene (default: 4)")
    parser.add_argument(
        "--out", type=Path, default=Path("outputs/benchmark_hard/grid.png"), help="PNG to write"
    )
    args = parser.parse_args()
    easy_settings, _ = data_settings("demo")
    hard_settings, seen = data_settings(args.experiment)
    easy = render_frames(easy_settings, args.frames)
    hard = render_frames(hard_settings, args.frames)
    columns = [
        np.concatenate([shown(image) for image in easy], axis=0),
        np.concatenate([shown(image) for image in hard], axis=0),
        np.concatenate([shown(image, seen) for image in hard], axis=0),
    ]
    side = hard[0].shape[0]
    titles = [
        f"easy ({easy[0].shape[0]} px)",
        f"{args.experiment} ({side} px, as stored)",
        f"{args.experiment} (as loaded, {seen} px)",
    ]
    grid = titled(columns, titles)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(args.out), cv2.cvtColor(grid, cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write {args.out}")
    print(
        f"wrote {args.out}: {len(easy)} frames of {easy_settings.scenes} scenes, "
        f"{grid.shape[1]}x{grid.shape[0]} px"
    )


if __name__ == "__main__":
    main()
