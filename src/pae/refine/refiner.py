"""The test-time position refiner: retrieval, PAE encoding, affine weights, orientation.

``PositionRefiner`` runs the paper's refinement (§3.3) for a batch of APR estimates;
``combine_orientations`` gives the refined orientation (the random-guess check's queries
come from ``pae.core.pose_sampling.perturb_positions``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any, Literal, NamedTuple

import torch
from torch import Tensor

from pae.core.geometry import average_quaternions, canonicalize_quaternion, normalize_quaternion
from pae.models.base import Latents
from pae.refine.index import PoseIndex
from pae.refine.weights import WEIGHT_MODELS, Objective, WeightModel, refine_affine

OrientationMode = Literal["teacher", "affine", "markley"]
ORIENTATION_MODES: tuple[str, ...] = ("teacher", "affine", "markley")
PoseEncoder = Callable[[Tensor, Tensor | None], Latents]
"""A PAE: poses [B, 7] and scenes [B] (or None) -> Latents."""


class RefinementResult(NamedTuple):
    """poses [B, 7] refined; weights [B, k]; neighbour_indices [B, k] into the pose index."""

    poses: Tensor
    weights: Tensor
    neighbour_indices: Tensor


def combine_orientations(
    neighbour_q: Tensor, weights: Tensor, initial_q: Tensor, mode: OrientationMode = "teacher"
) -> Tensor:
    """Orientation [B, 4] (unit, qw >= 0) of the refined pose.

    neighbour_q [B, k, 4]; weights [B, k]; initial_q [B, 4] (the teacher's estimate).
    ``"teacher"``: the initial estimate (the paper). ``"affine"``: normalised Σ aᵢ qᵢ after
    flipping each neighbour onto the hemisphere of the first (the weighted average the
    supplementary evaluates). ``"markley"``: the weighted quaternion average of Markley et al.;
    negative weights (possible with ``closed_form``) are clamped to 0 since the average needs
    non-negative weights — Σ a = 1 guarantees at least one positive weight.
    """
    if mode not in ORIENTATION_MODES:
        raise ValueError(f"orientation mode must be one of {ORIENTATION_MODES}, got {mode!r}")
    if mode == "teacher":
        return canonicalize_quaternion(initial_q)
    neighbour_q = normalize_quaternion(neighbour_q)
    weights = weights.to(neighbour_q.dtype)
    if mode == "affine":
        alignment = (neighbour_q * neighbour_q[:, :1]).sum(dim=-1, keepdim=True)
        aligned = torch.where(alignment < 0, -neighbour_q, neighbour_q)
        return canonicalize_quaternion((weights.unsqueeze(-1) * aligned).sum(dim=1))
    return average_quaternions(neighbour_q, weights.clamp(min=0.0))


def refine_with_neighbours(
    query_latent: Tensor,
    neighbour_latents: Tensor,
    neighbour_poses: Tensor,
    initial_poses: Tensor,
    orientation: OrientationMode,
    **options: Any,
) -> tuple[Tensor, Tensor]:
    """Refined poses [B, 7] (``initial_poses``' dtype) and weights [B, k] from retrieved
    neighbours: affine weights fitted by ``refine_affine(**options)``, position Σ aᵢ xᵢ, the
    orientation chosen by ``orientation`` (``combine_orientations``). query_latent [B, D];
    neighbour_latents [B, k, D]; neighbour_poses [B, k, 7]; initial_poses [B, 7]."""
    fit = refine_affine(query_latent, neighbour_latents, neighbour_poses, **options)
    rotation = combine_orientations(
        neighbour_poses[..., 3:], fit.weights, initial_poses[:, 3:], orientation
    )
    dtype = initial_poses.dtype
    return torch.cat([fit.positions.to(dtype), rotation.to(dtype)], dim=1), fit.weights


class PositionRefiner:
    """Test-time position refinement of APR estimates with a PAE and a store of train poses.

        For each query: retrieve the k nearest train poses of the initial estimate in its scene,
        encode them with the PAE (one batched call, no gradients), fit affine weights so that the
        combined encodings match the query's latent, and return Σ aᵢ xᵢ with the orientation
        chosen by ``orientation``. Defaults follow the paper and its public code: k=3, 3 AdamW
        iterations, the MLP weight regressor, the teacher's orientation; the paper's L2 objective
        and lr 1e-3 (the public script uses the mean squared error and lr 1e-2:
        ``objective="mse", lr=1e-2``). ``hidden`` and ``activation`` shape the MLP weight model
    (``pae.refine.regressor``). ``seed`` seeds the generator that draws the regressors.

        A plain class (not an ``nn.Module``) so the PAE it uses is not registered twice in a
        LightningModule that owns both.
    """

    def __init__(
        self,
        index: PoseIndex,
        pae: PoseEncoder,
        *,
        k: int = 3,
        iterations: int = 3,
        lr: float = 1e-3,
        weight_decay: float = 0.01,
        weight_model: WeightModel = "mlp",
        orientation: OrientationMode = "teacher",
        objective: Objective = "l2",
        hidden: Sequence[int] | None = None,
        activation: str = "relu",
        chunk_size: int = 64,
        seed: int = 0,
    ) -> None:
        if weight_model not in WEIGHT_MODELS:
            raise ValueError(f"weight_model must be one of {WEIGHT_MODELS}, got {weight_model!r}")
        if orientation not in ORIENTATION_MODES:
            raise ValueError(f"orientation must be one of {ORIENTATION_MODES}, got {orientation!r}")
        if k < 1:
            raise ValueError(f"k must be >= 1, got {k}")
        self.index = index
        self.pae = pae
        self.k = k
        self.iterations = iterations
        self.lr = lr
        self.weight_decay = weight_decay
        self.weight_model: WeightModel = weight_model
        self.orientation: OrientationMode = orientation
        self.objective: Objective = objective
        self.hidden = hidden
        self.activation = activation
        self.chunk_size = chunk_size
        self.generator = torch.Generator().manual_seed(seed)

    def neighbour_mean(self, neighbour_indices: Tensor, initial_poses: Tensor) -> Tensor:
        """[B, 7]: the plain mean position of the retrieved neighbours ``[B, k]`` (indices into
        the index), with the orientation of ``self.orientation`` under equal weights. The
        PAE-free baseline of the same retrieval: what the affine weights add is the
        difference to it."""
        neighbours = self.index.poses[neighbour_indices.to(self.index.device)].to(initial_poses)
        weights = torch.full(neighbours.shape[:2], 1.0 / neighbours.shape[1]).to(neighbours)
        orientation = combine_orientations(
            neighbours[..., 3:], weights, initial_poses[:, 3:], self.orientation
        )
        return torch.cat([neighbours[..., :3].mean(dim=1), orientation], dim=1)

    def __call__(
        self, query_latents: Latents, initial_poses: Tensor, scenes: Tensor | None = None
    ) -> RefinementResult:
        """query_latents: the APR's latents (x, q of [B, d]); initial_poses [B, 7]: its
        estimates; scenes [B] long: the scene of each query (``PoseRegressor.estimate``
        assigns them), None only for a single-scene index.
        """
        with torch.inference_mode(False):
            device = initial_poses.device
            initial = initial_poses.detach().clone()
            indices, _ = self.index.query(initial, scenes, self.k)
            batch = initial.shape[0]
            stored = self.index.poses[indices.to(self.index.device)]
            neighbour_poses = stored.to(device)  # [B, k, 7]
            neighbour_scenes = (
                None if scenes is None else scenes.detach().clone().repeat_interleave(self.k)
            )
            with torch.no_grad():
                encoded = self.pae(neighbour_poses.reshape(batch * self.k, 7), neighbour_scenes)
            query = query_latents.joint().detach().clone()
            neighbour_latents = encoded.joint().detach().clone().reshape(batch, self.k, -1)
            poses, weights = refine_with_neighbours(
                query,
                neighbour_latents,
                neighbour_poses,
                initial,
                self.orientation,
                weight_model=self.weight_model,
                iterations=self.iterations,
                lr=self.lr,
                weight_decay=self.weight_decay,
                objective=self.objective,
                hidden=self.hidden,
                activation=self.activation,
                generator=self.generator,
                chunk_size=self.chunk_size,
            )
        return RefinementResult(poses, weights, indices)
