"""The checks of the novel-view settings before any work (``teacher.novel_views.*``,
``student.novel_views``, ``student.store_novel_views``), and which steps they make read
``scene_model_ckpt``. Imports no torch: ``pae.config.validation`` calls it before a run loads it."""

from __future__ import annotations

from omegaconf import DictConfig, ListConfig

from pae.core.checks import boolean, integer, number, setting
from pae.core.errors import ConfigError

NOVEL_VIEW_KEYS = ("enabled", "ratio", "views", "between", "between_radius_m")
NOVEL_VIEW_KEYS += ("between_max_turn_deg", "between_share", "between_orientation")
NOVEL_VIEW_KEYS += ("position_jitter_m",)
NOVEL_VIEW_KEYS += ("orientation_jitter_deg", "min_distance_m", "size", "cache")
"""The settings of ``teacher.novel_views`` (pae.scene_model.novel_views.NovelViewSettings's fields
and ``enabled``)."""
BETWEEN_ORIENTATIONS = ("interpolated", "either")
"""A view's orientation between two cameras: interpolated like its position, or either's."""
STUDENT_VIEW_KEYS = ("student.novel_views", "student.store_novel_views")
"""The student's switches that read the views of ``teacher.novel_views``."""


def _teacher_views_on(cfg: DictConfig) -> bool:
    """``teacher.novel_views.*``: its keys and ranges -> whether novel views are on."""
    views = setting(cfg, "teacher.novel_views")
    if views is None:
        return False
    for name in views:
        if name not in NOVEL_VIEW_KEYS:
            raise ConfigError(
                f"teacher.novel_views.{name}: not a setting of teacher.novel_views (it has "
                f"{', '.join(NOVEL_VIEW_KEYS)})"
            )
    for name in ("enabled", "between", "cache"):
        boolean(cfg, f"teacher.novel_views.{name}")
    for name in ("ratio", "views"):
        number(cfg, f"teacher.novel_views.{name}", 0, strict=True)
    for name in ("position_jitter_m", "orientation_jitter_deg", "min_distance_m"):
        number(cfg, f"teacher.novel_views.{name}", 0, strict=False)
    number(cfg, "teacher.novel_views.between_max_turn_deg", 0, strict=True)
    share = setting(cfg, "teacher.novel_views.between_share")
    if share is not None and not (
        isinstance(share, ListConfig | list)
        and len(share) == 2
        and all(isinstance(value, int | float) and not isinstance(value, bool) for value in share)
        and 0 <= share[0] <= share[1] <= 1
    ):
        raise ConfigError(
            "teacher.novel_views.between_share must be [lo, hi] with 0 <= lo <= hi <= 1, got "
            f"{share!r}"
        )
    orientation = setting(cfg, "teacher.novel_views.between_orientation")
    if orientation is not None and orientation not in BETWEEN_ORIENTATIONS:
        raise ConfigError(
            f"teacher.novel_views.between_orientation must be one of "
            f"{', '.join(BETWEEN_ORIENTATIONS)}, got {orientation!r}"
        )
    if setting(cfg, "teacher.novel_views.between_radius_m") is not None:
        number(cfg, "teacher.novel_views.between_radius_m", 0, strict=True)
    if setting(cfg, "teacher.novel_views.size") is not None:
        integer(cfg, "teacher.novel_views.size", 4)
    return bool(views.enabled)


def _student_views_on(cfg: DictConfig) -> bool:
    """The student's switches (booleans; they need cached teacher latents) -> whether one is
    on."""
    for key in STUDENT_VIEW_KEYS:
        boolean(cfg, key)
    on = any(setting(cfg, key) for key in STUDENT_VIEW_KEYS)
    if on and not setting(cfg, "student.cache_latents"):
        raise ConfigError(
            "student.novel_views and student.store_novel_views need student.cache_latents=true"
        )
    return on


def novel_view_needs(cfg: DictConfig, steps: list[str]) -> dict[str, tuple[str, ...]]:
    """Check the novel-view settings -> step name -> the checkpoint keys they make it read
    (``scene_model_ckpt`` for a teacher or student that renders views)."""
    needs: dict[str, tuple[str, ...]] = {}
    if _teacher_views_on(cfg) and "teacher" in steps:
        needs["teacher"] = ("scene_model_ckpt",)
    if _student_views_on(cfg) and "student" in steps:
        needs["student"] = ("scene_model_ckpt",)
    return needs
