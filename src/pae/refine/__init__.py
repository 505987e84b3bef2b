"""Test-time refinement: a per-scene pose index (kNN), affine weights over PAE encodings
(``weights``, the MLP weight regressor in ``regressor``), the position refiner (``refiner``)
and refiners that search latent space (``latent``). The methods that read the query image
(virtual RPR, image RPR, iterative APR, behind ``ImageRefiner``) are ``pae.relative``.
``reference`` holds per-query test oracles and benchmark baselines; it is not exported here."""

from pae.core.pose_sampling import perturb_positions
from pae.refine.index import PoseIndex
from pae.refine.latent import LatentRetrievalRefiner, PoseDescentRefiner
from pae.refine.refiner import (
    ORIENTATION_MODES,
    PositionRefiner,
    RefinementResult,
    combine_orientations,
)
from pae.refine.regressor import ACTIVATIONS, init_weight_regressor, regressor_hidden_sizes
from pae.refine.weights import WEIGHT_MODELS, AffineFit, closed_form_weights, refine_affine

__all__ = [
    "ACTIVATIONS",
    "ORIENTATION_MODES",
    "WEIGHT_MODELS",
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
    "regressor_hidden_sizes",
]
