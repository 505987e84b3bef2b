"""RenderCompareRefiner's settings: their defaults (the ``refiner`` node of
``conf/render_compare/default.yaml``, their one home) and their ranges (checked when a refiner
is made)."""

from __future__ import annotations

import functools
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from pae import CONFIG_DIR

SCORES = ("zncc", "features")
ENGINES = ("auto", "compiled", "torch")
"""auto: compiled loops (``pae.refine.render_score``, ``pae.refine.render_polish``) for CPU
tensors and the ZNCC score, tensor operations otherwise; compiled: always (ZNCC only);
torch: always tensor operations (any device)."""

REFINER_CONFIG = Path(CONFIG_DIR) / "render_compare" / "default.yaml"
"""The render_compare group's default: its ``refiner`` node holds every setting's default."""
BUILD_KEYS = ("_target_", "_partial_")


@functools.cache
def _defaults() -> dict[str, Any]:
    node = OmegaConf.merge({"seed": 0}, OmegaConf.load(REFINER_CONFIG))
    settings = OmegaConf.to_container(node.refiner, resolve=True)
    assert isinstance(settings, dict)
    return {key: value for key, value in settings.items() if key not in BUILD_KEYS}


def refiner_defaults() -> dict[str, Any]:
    """RenderCompareRefiner's default settings, read from ``REFINER_CONFIG`` (seed 0)."""
    return dict(_defaults())


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
    blur_sigma_px: float,
    highpass_sigma_px: float,
    polish_damping: float,
    trim_sigma: float,
    trim_passes: int,
    **_: Any,
) -> None:
    """The ranges and combinations of the refiner's settings (``features``: the feature
    extractor given, or None); a ValueError naming the setting otherwise."""
    if score not in SCORES:
        raise ValueError(f"unknown render_compare.score {score!r}; choose one of {SCORES}")
    if engine not in ENGINES:
        raise ValueError(f"unknown render_compare.engine {engine!r}; choose one of {ENGINES}")
    if engine == "compiled" and score != "zncc":
        raise ValueError("render_compare.engine=compiled scores zncc only; use auto or torch")
    if score == "features" and polish_steps:
        raise ValueError(
            "render_compare.polish_steps align the zncc score only; set "
            "render_compare.refiner.polish_steps=0 with score=features"
        )
    if score == "features" and features is None:
        raise ValueError("render_compare.score=features needs a feature extractor")
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
    if highpass_sigma_px < 0 or blur_sigma_px < 0 or polish_damping <= 0:
        raise ValueError(
            "render_compare needs blur_sigma_px >= 0, highpass_sigma_px >= 0 and "
            f"polish_damping > 0, not {blur_sigma_px:g}, {highpass_sigma_px:g}, "
            f"{polish_damping:g}"
        )
    if trim_sigma < 0 or trim_passes < 0:
        raise ValueError(
            f"render_compare needs trim_sigma >= 0 and trim_passes >= 0, not {trim_sigma} "
            f"and {trim_passes}"
        )
