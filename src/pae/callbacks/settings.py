"""The settings of pae's callbacks that configs set, with their defaults (their one home:
``conf/<group>`` overrides them). Imports neither Lightning nor torch, so that the config
schema (:mod:`pae.config.schemas`) reads it in a launching process."""

from __future__ import annotations

from dataclasses import dataclass, field

from pae.core.ranges import check_integer
from pae.refine.settings import RefinementSettings


@dataclass
class TestTimeRefinementSettings(RefinementSettings):
    """:class:`pae.callbacks.refinement.TestTimeRefinement`'s settings: the refinement's, how
    often it runs and what it draws."""

    every_n_val_epochs: int = 1
    """Refine after every n-th validation (and every test)."""
    trajectory_plot: bool = True
    """TensorBoard IMAGES ``{split}/trajectory/<scene>``: ground truth, the teacher and
    ``trajectory_methods``."""
    trajectory_methods: list[str] = field(default_factory=lambda: ["refined"])
    """Methods drawn: refined, knn_mean or an alternative's name."""

    def __post_init__(self) -> None:
        super().__post_init__()
        check_integer("every_n_val_epochs", self.every_n_val_epochs, 1)
