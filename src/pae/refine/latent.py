"""Refinements that search the PAE's latent space instead of pose space (train poses only).

Both share :class:`~pae.refine.refiner.PositionRefiner`'s call signature
``(query_latents, initial_poses, scenes) -> RefinementResult`` and its factory signature
``(index, pae, **options)``, so the refinement callback runs them side by side:

- :class:`LatentRetrievalRefiner` retrieves the k train poses whose PAE encodings lie
  nearest the query's latent (instead of the poses nearest the teacher's estimate), then fits
  affine weights as the paper does;
- :class:`PoseDescentRefiner` moves the teacher's estimate by gradient descent until the PAE
  encodes it as close as possible to the query's latent (no store at all).
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor

from pae.models.base import Latents
from pae.refine.index import PoseIndex
from pae.refine.refiner import (
    OrientationMode,
    PoseEncoder,
    RefinementResult,
    refine_with_neighbours,
)
from pae.refine.weights import WeightModel


def _query_scenes(
    index: PoseIndex, scenes: Tensor | None, batch: int, device: torch.device
) -> Tensor:
    """[B] scene of each query: as given (``PoseRegressor.estimate`` assigns them), or the
    index's only scene."""
    if scenes is not None:
        return scenes.to(device, torch.long)
    if len(index.scene_ids) != 1:
        raise ValueError(f"the index holds {len(index.scene_ids)} scenes: pass the queries' scenes")
    return torch.full((batch,), index.scene_ids[0], dtype=torch.long, device=device)


class LatentRetrievalRefiner:
    """k nearest train poses in latent space, combined with affine weights.

    Every train pose of the index is encoded once per call (one batched PAE pass); each query
    retrieves, within its scene, the k encodings nearest its latent ``[z_x, z_q]`` (L2), and
    the refined position is ``Σ aᵢ xᵢ`` with weights fitted as in
    :func:`~pae.refine.weights.refine_affine` (default: the exact closed form).
    """

    def __init__(
        self,
        index: PoseIndex,
        pae: PoseEncoder,
        *,
        k: int = 3,
        weight_model: WeightModel = "closed_form",
        orientation: OrientationMode = "teacher",
        iterations: int = 3,
        lr: float = 1e-3,
        seed: int = 0,
    ) -> None:
        if k < 1:
            raise ValueError(f"k must be >= 1, got {k}")
        self.index = index
        self.pae = pae
        self.k = k
        self.weight_model: WeightModel = weight_model
        self.orientation: OrientationMode = orientation
        self.iterations = iterations
        self.lr = lr
        self.generator = torch.Generator().manual_seed(seed)

    def __call__(
        self, query_latents: Latents, initial_poses: Tensor, scenes: Tensor | None = None
    ) -> RefinementResult:
        """query_latents x, q [B, d]; initial_poses [B, 7]; scenes [B] long or None."""
        device = initial_poses.device
        batch = initial_poses.shape[0]
        scenes = _query_scenes(self.index, scenes, batch, device)
        store_poses = self.index.poses.to(device)
        store_scenes = self.index.scenes.to(device)
        with torch.no_grad():
            encoded = self.pae(store_poses, store_scenes).joint()  # [N, D]
            query = query_latents.joint().detach()
            indices = torch.empty(batch, self.k, dtype=torch.long, device=device)
            for scene in torch.unique(scenes).tolist():
                rows = torch.nonzero(scenes == scene).squeeze(1)
                members = torch.nonzero(store_scenes == scene).squeeze(1)
                if len(members) < self.k:
                    raise ValueError(
                        f"scene {scene} holds {len(members)} stored poses, fewer than k={self.k}"
                    )
                distances = torch.cdist(query[rows], encoded[members])
                nearest = distances.topk(self.k, dim=1, largest=False).indices
                indices[rows] = members[nearest]
        poses, weights = refine_with_neighbours(
            query,
            encoded[indices],
            store_poses[indices],
            initial_poses,
            self.orientation,
            weight_model=self.weight_model,
            iterations=self.iterations,
            lr=self.lr,
            generator=self.generator,
        )
        return RefinementResult(poses, weights, indices)


class PoseDescentRefiner:
    """The pose whose PAE encoding best matches the query's latent, by gradient descent.

    Starts at the teacher's estimate and runs ``iterations`` Adam steps (``lr`` in metres per
    step for the position) on ``Σ_queries ‖PAE(p) − z‖₂``, all queries at once. ``refine``
    picks what moves: ``"position"`` (the orientation stays the teacher's) or ``"pose"``
    (the quaternion too, renormalised after each step). ``index`` is accepted for the common
    factory signature; the descent needs no store. Gradients reach only the pose, never the
    PAE's parameters.
    """

    def __init__(
        self,
        index: PoseIndex | None,
        pae: PoseEncoder,
        *,
        iterations: int = 100,
        lr: float = 0.01,
        refine: Literal["position", "pose"] = "position",
    ) -> None:
        if iterations < 0:
            raise ValueError(f"iterations must be >= 0, got {iterations}")
        if not lr > 0:
            raise ValueError(f"lr must be > 0, got {lr}")
        if refine not in ("position", "pose"):
            raise ValueError(f"refine must be 'position' or 'pose', got {refine!r}")
        self.pae = pae
        self.iterations = iterations
        self.lr = lr
        self.refine = refine

    def __call__(
        self, query_latents: Latents, initial_poses: Tensor, scenes: Tensor | None = None
    ) -> RefinementResult:
        """query_latents x, q [B, d]; initial_poses [B, 7]; scenes [B] long (a multi-scene
        PAE needs them), or None."""
        batch = initial_poses.shape[0]
        with torch.inference_mode(False), torch.enable_grad():
            target = query_latents.joint().detach().clone()
            pose = initial_poses.detach().clone().float()
            variable = pose[:, :3] if self.refine == "position" else pose
            variable = variable.clone().requires_grad_(True)
            optimiser = torch.optim.Adam([variable], lr=self.lr)
            for _ in range(self.iterations):
                current = self._pose(variable, pose)
                residual = self.pae(current, scenes).joint() - target
                loss = torch.linalg.vector_norm(residual, dim=-1).sum()
                (gradient,) = torch.autograd.grad(loss, variable)
                variable.grad = gradient
                optimiser.step()
                if self.refine == "pose":
                    with torch.no_grad():
                        variable[:, 3:] = torch.nn.functional.normalize(variable[:, 3:], dim=-1)
            refined = self._pose(variable.detach(), pose)
        empty = torch.empty(batch, 0, device=initial_poses.device)
        return RefinementResult(refined.to(initial_poses.dtype), empty, empty.long())

    def _pose(self, variable: Tensor, initial: Tensor) -> Tensor:
        """[B, 7] pose from the optimised variable (position [B, 3] or pose [B, 7])."""
        if self.refine == "position":
            return torch.cat([variable, initial[:, 3:]], dim=1)
        return variable
