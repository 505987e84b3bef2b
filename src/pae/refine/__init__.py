"""Test-time refinement: a per-scene pose index (kNN) and affine combinations of PAE encodings."""

from pae.refine.affine import (
    AffineFit,
    PositionRefiner,
    RefinementResult,
    closed_form_weights,
    combine_orientations,
    init_weight_regressor,
    perturb_positions,
    refine_affine,
    refine_affine_per_query,
    regressor_hidden_sizes,
)
from pae.refine.index import PoseIndex
from pae.refine.latent import LatentRetrievalRefiner, PoseDescentRefiner

__all__ = [
    "AffineFit",
    "LatentRetrievalRefiner",
    "PoseDescentRefiner",
    "PoseIndex",
    "PositionRefiner",
    "RefinementResult",
    "closed_form_weights",
    "combine_orientations",
    "init_weight_regressor",
    "perturb_positions",
    "refine_affine",
    "refine_affine_per_query",
    "regressor_hidden_sizes",
]
