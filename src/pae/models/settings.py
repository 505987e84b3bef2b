"""The configurable models' settings with their defaults (their one home: ``conf/<group>``
overrides them). Imports neither numpy nor torch, so that the config schema
(:mod:`pae.config.schemas`) reads it in a launching process."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

from pae.core.ranges import check_integer, is_int


@dataclass
class PoseAutoEncoderSettings:
    """:class:`pae.models.pae.PoseAutoEncoder`'s settings: the paper's PAE, Fourier features
    of ``L`` bands and a 4-layer MLP per branch."""

    latent_dim: int = 256
    """The latent's size: the teacher's."""
    hidden: list[int] = field(default_factory=lambda: [64, 128, 256])
    """Each branch's hidden layer sizes."""
    L: int = 6
    """Fourier bands of the position and orientation (0: the raw pose)."""
    scene_L: int = 6  # noqa: N815 (the paper's L)
    """Fourier bands of the scene index (multi-scene PAEs)."""

    def __post_init__(self) -> None:
        check_integer("latent_dim", self.latent_dim, 1)
        if not isinstance(self.hidden, Sequence) or not all(
            is_int(width) and width >= 1 for width in self.hidden
        ):
            raise ValueError(f"hidden must be a list of layer widths >= 1, got {self.hidden!r}")
        check_integer("L", self.L, 0)
        check_integer("scene_L", self.scene_L, 0)


PAE_DEFAULTS = PoseAutoEncoderSettings()
"""The defaults, read by the constructor's signature."""
