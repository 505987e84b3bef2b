"""The paper's test-time refinement's settings with their defaults (their one home:
``conf/refine`` overrides them). Imports neither numpy nor torch, so that the config schema
(:mod:`pae.config.schemas`) reads it in a launching process."""

from __future__ import annotations

from dataclasses import dataclass

from pae.core.ranges import check_integer, check_number


@dataclass
class RefinementSettings:
    """The paper's refinement (§3.3) and the retrieval store it reads (the public code's
    defaults)."""

    k: int = 3
    """Train poses retrieved around the teacher's estimate."""
    iterations: int = 3
    """AdamW steps on the affine weights."""
    lr: float = 1e-3
    weight_model: str = "mlp"
    """How the affine weights are made: mlp (public code), softmax_logits or closed_form
    (exact, may be negative)."""
    activation: str = "relu"
    """The mlp's hidden activation: relu (public code), tanh or gelu."""
    orientation: str = "teacher"
    """The refined orientation: teacher (paper), affine or markley."""
    distance: str = "normalized"
    """The store's distance: normalized (public code) or fixed."""
    rot_weight: float = 0.01
    """Metres per degree in the fixed distance."""
    guess_sigma_m: float | None = 0.5
    """The random-guess check's Gaussian position noise (m); None: no check."""
    seed: int = 0
    """The refinement's random draws (weight regressors, random guesses)."""
    audit: bool = True
    """Also retrieve among the evaluated split's own poses (``*_test_store``, as the authors'
    public scripts do: an audit that reads the test labels)."""

    def __post_init__(self) -> None:
        check_integer("k", self.k, 1)
        check_integer("iterations", self.iterations, 0)
        check_number("lr", self.lr, 0, strict=True)
        check_number("rot_weight", self.rot_weight, 0)
        check_number("guess_sigma_m", self.guess_sigma_m, 0, optional=True)
