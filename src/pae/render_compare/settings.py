"""RenderCompareRefiner's settings: their defaults (``RenderCompareSettings``, their one home
in code; ``conf/render_compare/default.yaml`` overrides them) and their ranges (checked when a
refiner is made)."""

from __future__ import annotations

import dataclasses
from typing import Any

from pae.core.compiled import ENGINES

SCORES = ("zncc", "features")
"""``engine`` (:data:`pae.core.compiled.ENGINES`): auto, the compiled loops
(:mod:`pae.render_compare.kernels`) for CPU tensors and the
ZNCC score, tensor operations otherwise; numba: always (ZNCC only); torch: always tensor
operations (any device)."""

BUILD_KEYS = ("_target_", "_partial_")


@dataclasses.dataclass(frozen=True)
class RenderCompareSettings:
    """Every setting of :class:`pae.render_compare.refiner.RenderCompareRefiner` with its
    default (chosen on the demo's validation split: experiments/render_compare)."""

    rounds: int = 4
    """The search, at the coarsest pyramid level: a first round of ``hypotheses`` ×
    ``candidates`` draws around the start seeds ``hypotheses`` chains; each then draws
    ``candidates`` per round, for ``rounds`` rounds."""
    candidates: int = 12
    hypotheses: int = 4
    position_sigma_m: float = 0.25
    """The first draws' spread in position (m) and orientation (deg)."""
    orientation_sigma_deg: float = 4.0
    shrink: float = 0.6
    """The spread's factor from one round to the next."""
    resolution: int = 64
    """The pyramid: ``levels`` compare widths, the finest ``resolution`` px (or the query's
    width), each level half the next."""
    levels: int = 3
    blur_sigma_px: float = 0.3
    """The compared images' blur (px of each level)."""
    highpass_sigma_px: float = 0.0
    """Subtract the compared images' blur at this sigma (px at ``resolution``; a difference
    of Gaussians) so that smooth shading and light fall-off do not steer the score; 0: off."""
    contrast_sigma_px: float = 0.0
    """Divide the compared images' (band-passed) values by their local contrast within this
    sigma (px at ``resolution``, :func:`pae.render_compare.images.band_pass`) so that dim and
    bright regions weigh alike; 0: off."""
    highlight_quantile: float = 0.0
    """Clip each compared grey image (the query's at every level, the scene model's
    renderings) at this quantile of its values before the band-pass, so that highlights and
    saturated patches, which move with the light and the view, carry no texture to match;
    0: off."""
    highpass_levels: int = 0
    """The high-pass at the finest this many levels only (the coarser, where the search
    starts, compared whole: its reach); 0: at every level."""
    reference_size: int = 16
    """The scene model's rendering at the start (px), with ``reference_fov_scale`` × the
    query's field of view."""
    reference_fov_scale: float = 1.3
    final_reference_size: int = 32
    """Rendered again at the best hypothesis before the finest level (px; 0: not), with a
    field of view ``final_fov_scale`` × the query's. About half of ``resolution`` serves
    best: at 128 px, 64 took chess's floor on val from 1.42 to 0.93 cm (32: fewer surface
    points than the compared pixels; 96: 0.87 cm at twice the time;
    experiments/render_compare_real_starts/floor.py)."""
    final_fov_scale: float = 1.05
    surface_share: float = 0.0
    """The references' surface points: where each ray of a volumetric scene model has
    gathered this share of its opacity (0: the light's mean depth), so that faint fog in
    front of a surface does not pull its points towards the camera
    (:meth:`pae.scene_model.base.SceneModel.render`)."""
    polish_steps: int = 5
    """Levenberg–Marquardt steps on each hypothesis's image residual at every level, damped
    by ``polish_damping``."""
    polish_damping: float = 1.0e-3
    min_overlap: float = 0.2
    """The share of the reference's surface points a candidate must see."""
    trim_sigma: float = 0.0
    """Robust score: pixels whose residual after a gain-and-bias fit exceeds ``trim_sigma``
    residual standard deviations (occluders, what the scene model cannot explain) are dropped
    and the ZNCC recomputed, ``trim_passes`` times (each pass refits on the points kept); 0:
    the plain ZNCC."""
    trim_passes: int = 2
    score: str = "zncc"
    """zncc, or features (the teacher backbone's; search only: ``polish_steps=0``)."""
    seed: int = 0
    chunk: int = 64
    """Queries refined at once on the CPU."""
    gpu_chunk: int = 1024
    """Queries refined at once on another device, where the tensor engine's time goes to
    launching small kernels: on an H200, 64 took 2.19 ms per query, 1,024 0.29 ms
    (experiments/bench/README.md, "On a GPU")."""
    engine: str = "auto"


def refiner_defaults() -> dict[str, Any]:
    """RenderCompareRefiner's default settings (``RenderCompareSettings``) as a mapping."""
    return dataclasses.asdict(RenderCompareSettings())


def check_settings(
    *,
    score: str,
    engine: str,
    features: Any,
    rounds: int,
    candidates: int,
    hypotheses: int,
    levels: int,
    polish_steps: int,
    resolution: int,
    reference_size: int,
    final_reference_size: int,
    reference_fov_scale: float,
    final_fov_scale: float,
    surface_share: float,
    highlight_quantile: float,
    blur_sigma_px: float,
    highpass_sigma_px: float,
    contrast_sigma_px: float,
    highpass_levels: int,
    polish_damping: float,
    trim_sigma: float,
    trim_passes: int,
    chunk: int,
    gpu_chunk: int,
    **_: Any,
) -> None:
    """The ranges and combinations of the refiner's settings (``features``: the feature
    extractor given, or None); a ValueError naming the setting otherwise."""
    if score not in SCORES:
        raise ValueError(f"unknown render_compare.score {score!r}; choose one of {SCORES}")
    if engine not in ENGINES:
        raise ValueError(f"unknown render_compare.engine {engine!r}; choose one of {ENGINES}")
    if engine == "numba" and score != "zncc":
        raise ValueError("render_compare.engine=numba scores zncc only; use auto or torch")
    if score == "features" and polish_steps:
        raise ValueError(
            "render_compare.polish_steps align the zncc score only; set "
            "render_compare.refiner.polish_steps=0 with score=features"
        )
    if score == "features" and features is None:
        raise ValueError("render_compare.score=features needs a feature extractor")
    if min(chunk, gpu_chunk) < 1:
        raise ValueError(
            f"render_compare needs chunk and gpu_chunk >= 1, not {chunk} and {gpu_chunk}"
        )
    if (
        min(rounds, polish_steps, final_reference_size) < 0
        or min(candidates, hypotheses, levels) < 1
    ):
        raise ValueError(
            "render_compare needs rounds, polish_steps, final_reference_size >= 0 and "
            "candidates, hypotheses, levels >= 1"
        )
    if min(resolution, reference_size) < 8 or 0 < final_reference_size < 8:
        raise ValueError(
            "render_compare needs resolution, reference_size and final_reference_size "
            "(unless 0) >= 8 px"
        )
    if min(reference_fov_scale, final_fov_scale) <= 0:
        raise ValueError(
            "render_compare needs reference_fov_scale and final_fov_scale > 0, not "
            f"{reference_fov_scale:g} and {final_fov_scale:g}"
        )
    if not 0 <= surface_share < 1:
        raise ValueError(f"render_compare needs 0 <= surface_share < 1, not {surface_share:g}")
    if not 0 <= highlight_quantile < 1:
        raise ValueError(
            f"render_compare needs 0 <= highlight_quantile < 1, not {highlight_quantile:g}"
        )
    if min(highpass_sigma_px, blur_sigma_px, contrast_sigma_px) < 0 or polish_damping <= 0:
        raise ValueError(
            "render_compare needs blur_sigma_px, highpass_sigma_px and contrast_sigma_px >= 0 "
            f"and polish_damping > 0, not {blur_sigma_px:g}, {highpass_sigma_px:g}, "
            f"{contrast_sigma_px:g}, {polish_damping:g}"
        )
    if highpass_levels < 0:
        raise ValueError(f"render_compare needs highpass_levels >= 0, not {highpass_levels}")
    if trim_sigma < 0 or trim_passes < 0:
        raise ValueError(
            f"render_compare needs trim_sigma >= 0 and trim_passes >= 0, not {trim_sigma} "
            f"and {trim_passes}"
        )
