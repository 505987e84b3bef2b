"""PoseDataModule's settings with their defaults (their one home: ``conf/data`` overrides
them). Imports neither numpy nor torch, so that the config schema
(:mod:`pae.config.schemas`) reads it in a launching process."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

from pae.core.ranges import check_boolean, check_integer, is_int, is_number


def _names(value: Any) -> bool:
    """A list of strings (a config's list too)."""
    return (
        isinstance(value, Sequence)
        and not isinstance(value, str)
        and all(isinstance(name, str) for name in value)
    )


@dataclass
class PoseDataSettings:
    """Every setting of :class:`pae.data.datamodule.PoseDataModule` but the three without a
    default (``root``, the images' folder, and the ``train_labels`` and ``test_labels``
    files), with its default: those of real images of 640 × 480 px."""

    val_labels: str | None = None
    """A label file whose rows are the validation split (the train labels then stay whole);
    None: ``val_sequences`` of the train labels."""
    shorter_edge: int = 256
    """The images' shorter edge (px) after loading."""
    crop: int = 224
    """The side (px) of the square crop the models see."""
    color_jitter: list[float] = field(default_factory=lambda: [0.5, 0.5, 0.5, 0.2])
    """Brightness, contrast, saturation and hue jitter of train batches."""
    channel_gain: float = 0.0
    """White-balance jitter: each colour channel times a factor from [1 - g, 1 + g] (0: off)."""
    crop_shift_px: int | None = None
    """How far (px) the train-time random crop's corner may move from the centre crop's, each
    axis (None: anywhere in the image; 0: the centre crop). A shift looks like a turned camera
    whose label did not turn (s px: about s / focal length in px radians)."""
    crop_turns_camera: bool = False
    """Each random crop is the view of the camera turned towards the crop's centre (the image
    warped by the homography of that pure rotation, exact for any scene) and its label is
    turned with it: the crop's turn becomes a labelled one (needs ``camera``, one camera for
    every train row)."""
    augment: bool = True
    """Random crop and colour jitter for train batches."""
    batch_size: int = 32
    eval_batch_size: int = 128
    num_workers: int = 0
    """Loader processes (pae.core.threads caps them at the cores pae may use)."""
    cache_images: bool = False
    """Decode the val/test images at setup (a bad image fails the run before training) and
    each train image once."""
    image_store: str | None = None
    """A folder where each image, once decoded and resized, is kept for every later epoch,
    step and run to read back (:mod:`pae.data.image_store`; about 262 kB per image at the
    default size), and, where ``root`` is read-only, the cache of each train image file's
    BLAKE2b for the data fingerprint (:class:`pae.data.fingerprint.DigestCache`); None:
    decoded each time."""
    balance_scenes: bool = False
    """Sample scenes equally often in multi-scene training."""
    pose_loss_init: dict[str, float] | None = None
    """The initial ``s_x``, ``s_q`` of the learned pose loss that suit the dataset's error
    scale."""
    scenes: list[str] | None = None
    """The scenes of the label files kept (None: all)."""
    camera: Any = None
    """The intrinsics of the images as stored: ``fx, fy, cx, cy`` (px), ``width``,
    ``height``; a ``focal`` column in the label files (per image, px at this size) overrides
    ``fx, fy``. None where unknown (render-and-compare then cannot run)."""
    val_sequences: Any = 1
    """The validation split (every val/ figure): whole train sequences held out of the train
    labels, neither trained on nor stored for retrieval. An integer n: the last n of each
    scene in numeric order, or names: ``[seq-06]`` (every scene that has it),
    ``[scene00/seq-06]``. Scenes with one train sequence hold out the last ``val_fraction``
    of their rows instead. None: validation reads the test split, with a warning (for
    comparisons with runs that had no validation split only: settings chosen on val then see
    the test labels)."""
    val_fraction: float | None = 0.1
    order_seed: int = 0
    """Each epoch's order is drawn from (``order_seed``, epoch) alone (the run's seed)."""

    def __post_init__(self) -> None:
        check_integer("shorter_edge", self.shorter_edge, 1, optional=True)
        check_integer("crop", self.crop, 1)
        for name, low in (("batch_size", 1), ("eval_batch_size", 1), ("num_workers", 0)):
            check_integer(name, getattr(self, name), low)
        for name in ("augment", "cache_images", "balance_scenes", "crop_turns_camera"):
            check_boolean(name, getattr(self, name))
        if self.scenes is not None and not (_names(self.scenes) and len(self.scenes) > 0):
            raise ValueError(f"scenes must be null or a list of scene names, got {self.scenes!r}")
        held = self.val_sequences
        if not (held is None or (is_int(held) and held >= 1) or (_names(held) and len(held))):
            raise ValueError(
                "val_sequences must be null, an integer >= 1 (the last n train sequences of "
                f"each scene) or a list of sequence names, got {held!r}"
            )
        fraction = self.val_fraction
        if fraction is not None and not (is_number(fraction) and 0 < fraction < 1):
            raise ValueError(f"val_fraction must be null or a number in (0, 1), got {fraction!r}")

    @classmethod
    def names(cls) -> tuple[str, ...]:
        """The settings' names, in order."""
        return tuple(f.name for f in dataclasses.fields(cls))

    @classmethod
    def given(cls, settings: dict[str, Any]) -> PoseDataSettings:
        """The settings of ``settings`` (a mapping of their names) with the defaults for the
        rest; a name that is none of them is a TypeError naming it."""
        unknown = sorted(set(settings) - set(cls.names()))
        if unknown:
            raise TypeError(f"{cls.__name__}: unknown setting {unknown[0]!r}")
        return cls(**settings)
