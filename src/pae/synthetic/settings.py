"""The synthetic benchmark's settings in one record, with their defaults and ranges: what
:func:`~pae.synthetic.writer.write_synthetic_dataset` renders, the ``data.*`` keys of
``data=synthetic`` and ``pae-data synth``'s options. Imports neither numpy nor torch, so that
the config schema (:mod:`pae.config.schemas`) reads it in a launching process."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from pae.core.ranges import check_integer, is_int

NUISANCE_BOUNDS = {
    "lighting_change": 1.0,
    "occluder_fraction": 1.0,
    "sensor_noise_std": 0.5,
    "motion_blur_px": 64.0,
}
"""Upper bound of each nuisance setting (all >= 0; 0 turns it off)."""
SURFACE_BOUNDS = {
    "plain_surface_share": 1.0,
    "repeated_surface_share": 1.0,
    "glossy_surface_share": 1.0,
}
"""Upper bound of each surface setting (all >= 0; 0 turns it off)."""
JPEG_QUALITY_RANGE = (1, 100)
"""Qualities ``jpeg_quality`` takes when on."""
RENDER_SCALE_MAX = 8
"""Largest ``render_scale``."""


@dataclass(frozen=True)
class Nuisances:
    """The benchmark's nuisance settings (see the module doc); all 0: none, the plain render.

    Out-of-range values raise a one-line ValueError naming the setting.
    """

    lighting_change: float = 0.0
    occluder_fraction: float = 0.0
    sensor_noise_std: float = 0.0
    motion_blur_px: float = 0.0

    def __post_init__(self) -> None:
        _check_bounds(self, NUISANCE_BOUNDS)

    @property
    def active(self) -> bool:
        """Whether any nuisance is on."""
        return any(getattr(self, name) for name in NUISANCE_BOUNDS)

    def folder_suffix(self) -> str:
        """``_light1_occl0.3_noise0.02_blur3``-like suffix naming the settings that are on
        (empty when none is)."""
        tags = zip(("light", "occl", "noise", "blur"), NUISANCE_BOUNDS, strict=True)
        return "".join(
            f"_{tag}{getattr(self, name):g}" for tag, name in tags if getattr(self, name)
        )


@dataclass(frozen=True)
class SurfaceOptions:
    """The benchmark's surface settings (see the module doc); all 0: the plain benchmark's
    textured, matte surfaces. Out-of-range values raise a one-line ValueError naming the
    setting."""

    plain_surface_share: float = 0.0
    repeated_surface_share: float = 0.0
    glossy_surface_share: float = 0.0

    def __post_init__(self) -> None:
        _check_bounds(self, SURFACE_BOUNDS)
        if self.plain_surface_share + self.repeated_surface_share > 1:
            raise ValueError(
                f"plain_surface_share + repeated_surface_share must be <= 1, got "
                f"{self.plain_surface_share:g} + {self.repeated_surface_share:g}"
            )

    @property
    def active(self) -> bool:
        """Whether any surface setting is on."""
        return any(getattr(self, name) for name in SURFACE_BOUNDS)

    def folder_suffix(self) -> str:
        """``_plain0.3_repeat0.2_gloss0.3``-like suffix naming the settings that are on (empty
        when none is)."""
        tags = zip(("plain", "repeat", "gloss"), SURFACE_BOUNDS, strict=True)
        return "".join(
            f"_{tag}{getattr(self, name):g}" for tag, name in tags if getattr(self, name)
        )


@dataclass(frozen=True)
class CaptureOptions:
    """The benchmark's capture settings (see the module doc); the defaults: the plain
    benchmark's. Out-of-range values raise a one-line ValueError naming the setting."""

    camera_pipeline: float = 0.0
    jpeg_quality: int = 0
    render_scale: int = 1

    def __post_init__(self) -> None:
        value = self.camera_pipeline
        number = isinstance(value, int | float) and not isinstance(value, bool)
        if not (number and math.isfinite(value) and 0 <= value <= 1):
            raise ValueError(f"camera_pipeline must be a number in [0, 1], got {value!r}")
        low, high = JPEG_QUALITY_RANGE
        if not is_int(self.jpeg_quality) or not (
            self.jpeg_quality == 0 or low <= self.jpeg_quality <= high
        ):
            raise ValueError(
                f"jpeg_quality must be 0 (off) or an integer in [{low}, {high}], "
                f"got {self.jpeg_quality!r}"
            )
        if not is_int(self.render_scale) or not 1 <= self.render_scale <= RENDER_SCALE_MAX:
            raise ValueError(
                f"render_scale must be an integer in [1, {RENDER_SCALE_MAX}], "
                f"got {self.render_scale!r}"
            )

    @property
    def active(self) -> bool:
        """Whether any capture setting is on."""
        return bool(self.camera_pipeline or self.jpeg_quality or self.render_scale > 1)

    def folder_suffix(self) -> str:
        """``_pipe1_jpeg75_x4``-like suffix naming the settings that are on (empty when none
        is)."""
        return (
            (f"_pipe{self.camera_pipeline:g}" if self.camera_pipeline else "")
            + (f"_jpeg{self.jpeg_quality}" if self.jpeg_quality else "")
            + (f"_x{self.render_scale}" if self.render_scale > 1 else "")
        )


def _check_bounds(record: object, bounds: dict[str, float]) -> None:
    """Each setting of ``record`` named in ``bounds`` a number in [0, its bound]; a one-line
    ValueError naming the first that is not."""
    for name, high in bounds.items():
        value = getattr(record, name)
        number = isinstance(value, int | float) and not isinstance(value, bool)
        if not (number and math.isfinite(value) and 0 <= value <= high):
            raise ValueError(f"{name} must be a number in [0, {high:g}], got {value!r}")


@dataclass(frozen=True)
class SyntheticSettings:
    """Every setting of a synthetic dataset; all nuisances, surfaces and capture options off
    (0) by default, the plain benchmark.

    Layout: ``scenes`` rooms, ``train_frames`` and ``test_frames`` per scene, images of
    ``size`` px (65° horizontal field of view), ``seed`` of every draw. Train sequences walk
    lanes ``train_lane_m`` (m) left and right of each scene's route, test sequences
    ``test_offset_m`` beside it; each camera strays up to ``stray_m`` (m) from its lane and
    its yaw ``yaw_stray_rad`` from the route's heading. ``val_lane_m`` not None: the last
    train sequence walks that far (signed, within ±``train_lane_m``) from the route;
    ``val_walks`` more validation sequences per scene walk where it walks. With the defaults
    the test sequences walk between the train lanes, as test walks do between train walks in
    Cambridge Landmarks: the median test camera lies 0.21 m from the nearest train camera,
    about half the CPU teacher's error (the real datasets: 0.37-1.07 of MS-Transformer's).

    Nuisances (:class:`~pae.synthetic.nuisances.Nuisances`): ``lighting_change`` (0..1),
    ``occluder_fraction`` (share of frames), ``sensor_noise_std`` (std of values in [0, 1]),
    ``motion_blur_px``. Surfaces (:class:`~pae.synthetic.surfaces.SurfaceOptions`): the shares
    of surfaces plain-painted, periodic and glossy. Capture
    (:class:`~pae.synthetic.capture.CaptureOptions`): ``camera_pipeline`` (0..1),
    ``jpeg_quality`` (0: off), ``render_scale`` (images stored at that many times ``size``).

    Out-of-range values raise a one-line ValueError naming the setting.
    """

    scenes: int = 2
    train_frames: int = 1600
    test_frames: int = 250
    size: int = 64
    seed: int = 0
    test_offset_m: float = 0.0
    train_lane_m: float = 0.5
    yaw_stray_rad: float = 0.15
    stray_m: float = 0.1
    val_lane_m: float | None = None
    val_walks: int = 0
    lighting_change: float = 0.0
    occluder_fraction: float = 0.0
    sensor_noise_std: float = 0.0
    motion_blur_px: float = 0.0
    plain_surface_share: float = 0.0
    repeated_surface_share: float = 0.0
    glossy_surface_share: float = 0.0
    camera_pipeline: float = 0.0
    jpeg_quality: int = 0
    render_scale: int = 1

    def __post_init__(self) -> None:
        for name, low in (
            ("scenes", 1),
            ("train_frames", 1),
            ("test_frames", 1),
            ("size", 8),
            ("seed", 0),
            ("val_walks", 0),
        ):
            check_integer(name, getattr(self, name), low)
        for name in ("test_offset_m", "train_lane_m", "stray_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0 <= value <= 1.0):
                raise ValueError(f"{name} must lie in [0, 1] m, got {value!r}")
        lane = self.train_lane_m
        if self.val_lane_m is not None and not (
            math.isfinite(self.val_lane_m) and abs(self.val_lane_m) <= lane
        ):
            raise ValueError(
                f"val_lane_m must lie in [-train_lane_m, train_lane_m] = "
                f"[{-lane:g}, {lane:g}] m, got {self.val_lane_m!r}"
            )
        if not (math.isfinite(self.yaw_stray_rad) and 0 <= self.yaw_stray_rad <= math.pi / 2):
            raise ValueError(f"yaw_stray_rad must lie in [0, pi/2], got {self.yaw_stray_rad!r}")
        for options in ("nuisances", "surfaces", "capture"):
            getattr(self, options)

    @classmethod
    def names(cls) -> tuple[str, ...]:
        """The settings' names, in order."""
        return tuple(field.name for field in dataclasses.fields(cls))

    @property
    def nuisances(self) -> Nuisances:
        """The nuisance settings (checked when made)."""
        return Nuisances(
            self.lighting_change, self.occluder_fraction, self.sensor_noise_std, self.motion_blur_px
        )

    @property
    def surfaces(self) -> SurfaceOptions:
        """The surface settings (checked when made)."""
        return SurfaceOptions(
            self.plain_surface_share, self.repeated_surface_share, self.glossy_surface_share
        )

    @property
    def capture(self) -> CaptureOptions:
        """The capture settings (checked when made)."""
        return CaptureOptions(self.camera_pipeline, self.jpeg_quality, self.render_scale)

    def folder_name(self) -> str:
        """The name of the folder these settings render into: the layout's settings, then a
        suffix for each group of options that is on (``_light1_occl0.3…``,
        ``_plain0.3_repeat0.2_gloss0.3``, ``_pipe1_jpeg75_x4``), a validation lane
        (``_val0``) and validation walks (``_walks3``); off, the name is the one without
        them."""
        return (
            f"scenes{self.scenes}_train{self.train_frames}_test{self.test_frames}"
            f"_px{self.size}_seed{self.seed}_offset{self.test_offset_m:g}"
            f"_lane{self.train_lane_m:g}_yaw{self.yaw_stray_rad:g}_stray{self.stray_m:g}"
            f"{self.nuisances.folder_suffix()}{self.surfaces.folder_suffix()}"
            f"{self.capture.folder_suffix()}"
            f"{'' if self.val_lane_m is None else f'_val{self.val_lane_m:g}'}"
            f"{f'_walks{self.val_walks}' if self.val_walks else ''}"
        )


SYNTHETIC_LOADING = {
    "shorter_edge": None,
    "crop": 56,
    "color_jitter": [0.3, 0.3, 0.3, 0.0],
    "eval_batch_size": 256,
    "cache_images": True,
    "balance_scenes": True,
    "pose_loss_init": {"s_x": 0.0, "s_q": -3.0},
}
"""How the synthetic benchmark is loaded where :class:`pae.data.settings.PoseDataSettings`'
defaults (real images of 640 × 480) do not serve: images loaded at their ``size``
(``shorter_edge`` None) and cropped to 56 px, no hue jitter (wall colours are the scenes' main
cue), all images decoded once, scenes sampled equally often, the learned pose loss started
at the error scale of a room."""
