"""How a real camera captures the benchmark's frames, all off by default
(``CaptureOptions``): what lies between the light reaching the lens and the file on disk.

- ``camera_pipeline`` (strength in ``[0, 1]``): per sequence vignetting (``1 − v·r²``, ``v``
  up to 0.25–0.45 at the corners), a gamma encoding (the exponent divided by 1.3–1.8) and an
  auto-exposure that meters each frame (its gain times ``(target / level)^m``, ``m`` 0.6–0.9);
  per frame an exposure and a white balance (red and blue against green) that drift within
  the sequence (× e^±0.3 and × e^±0.12). Every factor is the strength times these.
- ``jpeg_quality`` (0: off, else 1–100): each image compressed as JPEG at that quality and
  decoded again (OpenCV, 4:2:0 chroma); the decoded pixels are stored as PNG, so the files,
  their names and the label files stay those of the plain benchmark, and every loader reads
  exactly the decoder's pixels.
- ``render_scale`` (1: off, else 2–8): images rendered and stored at ``render_scale`` times
  the size (a 64 px benchmark at 4: 256 px, like a real camera's images far larger than the
  compare width), with the same field of view; the loaders and the scene model downsample
  them. Motion blur lengths stay in pixels of the nominal size.

:func:`sequence_capture` draws one sequence's, from a stream of its nuisance seed of its
own, so turning it on leaves the nuisances' draws unchanged.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from pae.synthetic.raycast import Appearance, FrameConditions
from pae.synthetic.settings import CaptureOptions
from pae.synthetic.trajectories import smooth_wave


def _drift(rng: np.random.Generator, frames: int) -> np.ndarray:
    """Slow drift ``[frames]`` within ``[-1, 1]``: two sines, 0.3–1 and 2–3 cycles per
    sequence."""
    return smooth_wave(rng, np.arange(frames) / max(frames, 1), (0.3, 1.0), (0.8, 0.2))


def sequence_capture(
    options: CaptureOptions,
    appearance: Appearance,
    conditions: FrameConditions | None,
    seed: tuple[int, ...],
) -> tuple[Appearance, FrameConditions | None]:
    """One sequence's capture: its ``appearance`` with the pipeline's vignetting, gamma and
    auto-exposure and the JPEG quality, and its frames' ``conditions`` with the exposure and
    white balance drifts on top (the same ``seed``, the same draws). The pipeline needs the
    frames' ``conditions`` (ValueError without); off, they stay as they are (None too)."""
    strength = options.camera_pipeline
    if options.jpeg_quality:
        appearance = dataclasses.replace(appearance, jpeg_quality=options.jpeg_quality)
    if not strength:
        return appearance, conditions
    if conditions is None:
        raise ValueError("camera_pipeline needs the frames' conditions (FrameConditions.plain)")
    rng = np.random.default_rng([*seed, 4])
    frames = len(conditions)
    appearance = dataclasses.replace(
        appearance,
        vignetting=strength * rng.uniform(0.25, 0.45),
        metering=strength * rng.uniform(0.6, 0.9),
        gamma=appearance.gamma / (1 + strength * rng.uniform(0.3, 0.8)),
    )
    exposure = conditions.exposure * np.exp(strength * 0.3 * _drift(rng, frames))
    white_balance = np.ones((frames, 3))
    for channel in (0, 2):
        offset = rng.uniform(-0.5, 0.5)
        white_balance[:, channel] = np.exp(strength * 0.12 * (offset + _drift(rng, frames)) / 1.5)
    conditions = dataclasses.replace(
        conditions,
        exposure=exposure,
        white_balance=conditions.white_balance * white_balance,
    )
    return appearance, conditions
