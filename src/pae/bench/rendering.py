"""Rendering speed of the synthetic benchmark (``bench/synthetic/frames_per_s``)."""

from __future__ import annotations

import time

import numpy as np

from pae.synthetic.camera import DEFAULT_SIZE, PinholeCamera
from pae.synthetic.raycast import Appearance, render_batch
from pae.synthetic.scene import make_scene
from pae.synthetic.trajectories import trajectory


def measure_render_speed(frames: int = 200, size: int = DEFAULT_SIZE, seed: int = 0) -> float:
    """Rendering speed (frames/s) for ``frames`` poses along scene 0's route, without file I/O."""
    scene = make_scene(0, seed)
    rng = np.random.default_rng([seed, 0, 3])
    poses = trajectory(scene, frames, 0.0, rng)
    appearance = Appearance.random(rng)
    camera = PinholeCamera(size)
    render_batch(scene, poses[:1], camera, appearance, rng)
    started = time.perf_counter()
    render_batch(scene, poses, camera, appearance, rng)
    return frames / (time.perf_counter() - started)
