"""Test-time refinement: a per-scene pose index (kNN), affine weights over PAE encodings
(``weights``, the MLP weight regressor in ``regressor``), the position refiner (``refiner``)
and refiners that search latent space (``latent``), and the methods that read the query
image (``relative``: virtual RPR, image RPR, iterative APR, behind ``ImageRefiner``).
``reference`` holds per-query test oracles and benchmark baselines; it is not exported here."""

from pae.pose_sampling import perturb_positions
from pae.refine.index import PoseIndex
from pae.refine.latent import LatentRetrievalRefiner, PoseDescentRefiner
from pae.refine.refiner import (
    ORIENTATION_MODES,
    PositionRefiner,
    RefinementResult,
    combine_orientations,
)
from pae.refine.regressor import ACTIVATIONS, init_weight_regressor, regressor_hidden_sizes
from pae.refine.relative import (
    ImageRefiner,
    ImageRPR,
    IterativeAPRRefiner,
    RefinedPoses,
    TrainImages,
    VirtualRPR,
)
from pae.refine.weights import WEIGHT_MODELS, AffineFit, closed_form_weights, refine_affine

__all__ = [
    "ACTIVATIONS",
    "ORIENTATION_MODES",
    "WEIGHT_MODELS",
    "AffineFit",
    "ImageRPR",
    "ImageRefiner",
    "IterativeAPRRefiner",
    "LatentRetrievalRefiner",
    "PoseDescentRefiner",
    "PoseIndex",
    "PositionRefiner",
    "RefinedPoses",
    "RefinementResult",
    "TrainImages",
    "VirtualRPR",
    "closed_form_weights",
    "combine_orientations",
    "init_weight_regressor",
    "perturb_positions",
    "refine_affine",
    "regressor_hidden_sizes",
]
