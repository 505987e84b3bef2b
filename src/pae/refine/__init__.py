"""Test-time refinement: a per-scene pose index (kNN), affine weights over PAE encodings
(``weights``, the MLP weight regressor in ``regressor``), the position refiner (``refiner``)
and refiners that search latent space (``latent``). The methods that read the query image
(virtual RPR, image RPR, iterative APR, behind ``ImageRefiner``) are ``pae.relative``.
``reference`` holds per-query test oracles and benchmark baselines; it is not exported here.
Each name is imported from its module on first use (``settings`` loads without torch)."""

from pae.core.lazy import lazy_attributes

_MODULES = {
    "perturb_positions": "pae.core.pose_sampling",
    "PoseIndex": "pae.refine.index",
    "LatentRetrievalRefiner": "pae.refine.latent",
    "PoseDescentRefiner": "pae.refine.latent",
    "ORIENTATION_MODES": "pae.refine.refiner",
    "PositionRefiner": "pae.refine.refiner",
    "RefinementResult": "pae.refine.refiner",
    "combine_orientations": "pae.refine.refiner",
    "ACTIVATIONS": "pae.refine.regressor",
    "init_weight_regressor": "pae.refine.regressor",
    "regressor_hidden_sizes": "pae.refine.regressor",
    "AffineFit": "pae.refine.weights",
    "WEIGHT_MODELS": "pae.refine.weights",
    "closed_form_weights": "pae.refine.weights",
    "refine_affine": "pae.refine.weights",
}
"""Each public name -> the module that defines it."""

__all__ = sorted(_MODULES)
__getattr__ = lazy_attributes(__name__, _MODULES)
