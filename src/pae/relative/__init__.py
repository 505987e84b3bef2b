"""Refinement methods that read the query image: virtual relative pose regression, the
image RPR and the iterative APR, behind ``ImageRefiner``."""

from pae.relative.refiners import (
    ImageRefiner,
    ImageRPR,
    IterativeAPRRefiner,
    RefinedPoses,
    TrainImages,
    VirtualRPR,
)

__all__ = [
    "ImageRPR",
    "ImageRefiner",
    "IterativeAPRRefiner",
    "RefinedPoses",
    "TrainImages",
    "VirtualRPR",
]
