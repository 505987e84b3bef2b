"""Test-time position refinement (paper §3.3) evaluated in both retrieval protocols on a
split's queries, without a Trainer: the paper's refinement and the plain mean of the same
neighbours, from the train poses and (``audit``) from the split's own poses, the
random-guess check and the alternatives, and how far the queries lie from the train poses."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping

import torch
from torch import Tensor

from pae.core.pose_sampling import perturb_positions
from pae.models.base import Latents
from pae.refine.index import PoseIndex
from pae.refine.refiner import ORIENTATION_MODES, PositionRefiner, RefinementResult
from pae.refine.regressor import ACTIVATIONS
from pae.refine.settings import RefinementSettings
from pae.refine.weights import WEIGHT_MODELS

Refiner = Callable[[Latents, Tensor, Tensor | None], RefinementResult]
"""``(query_latents, initial_poses [B, 7], scenes [B]) -> RefinementResult``."""
RefinerFactory = Callable[..., Refiner]
"""Builds a refiner from keywords ``index`` (the train-pose store) and ``pae``."""
RESERVED_METHODS = (
    "teacher",
    "student",
    "student_gt",
    "mean_pose",
    "refined",
    "knn_mean",
    "refined_test_store",
    "knn_mean_test_store",
    "guess_initial",
    "guess_refined",
    "guess_refined_test_store",
    "diagnostics",
)


@dataclasses.dataclass
class RefinementProtocols(RefinementSettings):
    """The paper's refinement's settings (:class:`RefinementSettings`: ``k`` neighbours,
    ``iterations``, ``lr``, ``weight_model``, ``activation``, ``orientation``, the store's
    ``distance`` and ``rot_weight``, the random-guess check's ``guess_sigma_m``, ``seed``,
    ``audit``) and named ``alternatives`` (train store only)."""

    alternatives: Mapping[str, RefinerFactory] = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        super().__post_init__()
        for key, choices in (
            ("weight_model", WEIGHT_MODELS),
            ("activation", tuple(ACTIVATIONS)),
            ("orientation", ORIENTATION_MODES),
            ("distance", ("normalized", "fixed")),
        ):
            if getattr(self, key) not in choices:
                raise ValueError(f"unknown refine.{key} {getattr(self, key)!r}; choose {choices}")
        clashes = sorted(set(self.alternatives) & set(RESERVED_METHODS))
        if clashes:
            raise ValueError(f"refine.alternatives may not reuse the method names {clashes}")

    def store(self, poses: Tensor, scenes: Tensor) -> PoseIndex:
        """The retrieval store of poses [N, 7] with scene ids [N], searched with the
        configured distance."""
        return PoseIndex(poses, scenes, distance=self.distance, rot_weight=self.rot_weight)

    def refiner(self, pae: torch.nn.Module, index: PoseIndex) -> PositionRefiner:
        """The paper's refinement (``refined``; ``knn_mean`` from its neighbours) with ``pae``
        over the store ``index``."""
        keys = ("k", "iterations", "lr", "weight_model", "activation", "orientation")
        return PositionRefiner(index, pae, seed=self.seed, **{k: getattr(self, k) for k in keys})

    def predict(
        self,
        pae: torch.nn.Module,
        train: PoseIndex,
        query: Latents,
        estimate: Tensor,
        estimate_scene: Tensor,
        truth: Tensor,
        scene: Tensor,
    ) -> tuple[dict[str, Tensor], float]:
        """Every method's poses [N, 7] for queries with PAE latents ``query``, the teacher's
        estimates [N, 7] in its scenes [N], their true poses [N, 7] and scenes [N] (read only
        by the ``*_test_store`` audit and the random-guess check) -> method -> poses, and the
        paper's refinement's seconds from the train store."""
        stores = {"": train}
        if self.audit:
            stores["_test_store"] = self.store(truth, scene).to(train.device)
        predictions: dict[str, Tensor] = {}
        seconds = 0.0
        for suffix, store in stores.items():
            start = time.perf_counter()
            refiner = self.refiner(pae, store)
            result = refiner(query, estimate, estimate_scene)
            knn_mean = refiner.neighbour_mean(result.neighbour_indices, estimate)
            seconds = seconds or time.perf_counter() - start
            predictions[f"refined{suffix}"], predictions[f"knn_mean{suffix}"] = (
                result.poses,
                knn_mean,
            )
        for name, factory in self.alternatives.items():
            predictions[name] = factory(index=train, pae=pae)(query, estimate, estimate_scene).poses
        if self.guess_sigma_m:
            generator = torch.Generator().manual_seed(self.seed)
            guess = perturb_positions(truth.cpu(), self.guess_sigma_m, generator).to(truth.device)
            with torch.no_grad():
                guess_latents = pae(guess, scene)
            predictions["guess_initial"] = guess
            for suffix, store in stores.items():
                refined = self.refiner(pae, store)(guess_latents, guess, scene).poses
                predictions[f"guess_refined{suffix}"] = refined
        return predictions, seconds


def store_distances(
    positions: PoseIndex,
    prefix: str,
    estimate: Tensor,
    estimate_scene: Tensor,
    truth: Tensor,
    scene: Tensor,
    teacher_error_m: Tensor,
) -> dict[str, Tensor]:
    """Median distance (m) from the teacher's estimates [N, 7] and from the true positions
    [N, 7] to the nearest train position of their scene (``positions``, a position-only
    store), and their ratios to the teacher's median position error: retrieval from the
    train poses can only pull an estimate towards them."""
    _, to_estimate = positions.query(estimate, estimate_scene, 1)
    _, to_truth = positions.query(truth, scene, 1)
    estimate_m, truth_m = to_estimate.quantile(0.5), to_truth.quantile(0.5)
    error = teacher_error_m.clamp(min=1e-12)
    return {
        f"{prefix}/estimate_to_train_m": estimate_m,
        f"{prefix}/gt_to_train_m": truth_m,
        f"{prefix}/estimate_to_train_per_error": estimate_m / error,
        f"{prefix}/gt_to_train_per_error": truth_m / error,
    }
