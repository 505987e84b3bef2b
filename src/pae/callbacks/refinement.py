"""Test-time position refinement (paper §3.3) as a Lightning callback for student runs."""

from __future__ import annotations

import time
from collections.abc import Callable

import lightning as L
import torch
from lightning.pytorch.loggers import TensorBoardLogger
from torch import Tensor

from pae.callbacks.error_curves import error_curves_figure
from pae.callbacks.tensorboard import log_figure, tensorboard_loggers
from pae.callbacks.trajectory import log_trajectories
from pae.core.geometry import pose_errors
from pae.core.metrics import summarise_errors
from pae.lit.eval_outputs import EVAL, collect_outputs
from pae.models.base import Latents
from pae.refine import (
    ACTIVATIONS,
    ORIENTATION_MODES,
    WEIGHT_MODELS,
    PoseIndex,
    PositionRefiner,
    RefinementResult,
    perturb_positions,
)

Refiner = Callable[[Latents, Tensor, Tensor | None], RefinementResult]
"""``(query_latents, initial_poses [B, 7], scenes [B]) -> RefinementResult``."""
PROTOCOLS_TEXT = (
    "**Retrieval protocols.** `refined`, `knn_mean`, `guess_refined` and the alternatives "
    "retrieve among the train poses (the protocol the paper describes). Scalars named "
    "`*_test_store` retrieve among the evaluated split's own ground-truth poses, as the "
    "authors' public scripts do: they read the test labels and can retrieve a query's own "
    "pose. They are an audit, not a result. `knn_mean*` is the plain mean of the same "
    "neighbours, with no PAE: what refinement adds is the difference to it."
)
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


RefinerFactory = Callable[..., Refiner]
"""Builds a refiner from keywords ``index`` (the train-pose store) and ``pae``."""


class TestTimeRefinement(L.Callback):
    """Refines every evaluated query of a StudentEvaluator (or StudentModule), in both
    retrieval protocols.

    Under DDP every process gathers all queries and drops the repeats a distributed sampler
    adds (by dataset index), so each figure counts every sample once, in dataset order.

    Logged for the same queries, after every ``every_n_val_epochs``-th validation and every
    test (``{split}`` is val or test):

    - ``{split}/refined/...``: the paper's refinement, neighbours from the train poses;
    - ``{split}/knn_mean/...``: the plain mean of the same k neighbours, no PAE;
    - with ``audit``, the same two with neighbours from the evaluated split's own poses
      (``refined_test_store``, ``knn_mean_test_store``): the protocol of the authors' public
      scripts, which reads the test labels and can retrieve a query's own pose;
    - with ``guess_sigma_m``, the random-guess check: the ground-truth position plus Gaussian
      noise (σ m), encoded by the PAE, is the query (``guess_initial``, ``guess_refined``
      and, with ``audit``, ``guess_refined_test_store``);
    - ``{split}/<name>/...`` for every refiner of ``alternatives`` (train store only);
    - diagnostics ``{split}/diagnostics/{estimate,gt}_to_train_m`` (median distance from the
      teacher's estimates and from the true positions to the nearest train position of their
      scene) and their ratios to the teacher's median position error,
      ``{split}/diagnostics/{estimate,gt}_to_train_per_error``. Retrieval from the train poses
      can only pull an estimate towards them: it helps when the truth lies nearer the train
      poses than the estimate does.
    """

    def __init__(
        self,
        k: int = 3,
        iterations: int = 3,
        lr: float = 1e-3,
        weight_model: str = "mlp",
        activation: str = "relu",
        orientation: str = "teacher",
        distance: str = "normalized",
        rot_weight: float = 0.01,
        every_n_val_epochs: int = 1,
        guess_sigma_m: float | None = 0.5,
        seed: int = 0,
        trajectory_plot: bool = True,
        trajectory_methods: tuple[str, ...] = ("refined",),
        audit: bool = True,
        alternatives: dict[str, RefinerFactory] | None = None,
    ) -> None:
        super().__init__()
        self.options = {
            "k": k,
            "iterations": iterations,
            "lr": lr,
            "weight_model": weight_model,
            "activation": activation,
            "orientation": orientation,
        }
        self.distance = distance
        self.rot_weight = rot_weight
        self.every_n_val_epochs = max(1, every_n_val_epochs)
        self.guess_sigma_m = guess_sigma_m
        self.seed = seed
        self.trajectory_plot = trajectory_plot
        self.trajectory_methods = tuple(trajectory_methods)
        self.audit = audit
        self.alternatives = dict(alternatives or {})
        self.index: PoseIndex | None = None
        self.position_index: PoseIndex | None = None
        self._val_runs = 0
        if weight_model not in WEIGHT_MODELS:
            raise ValueError(
                f"unknown refine.weight_model {weight_model!r}; choose {WEIGHT_MODELS}"
            )
        if activation not in ACTIVATIONS:
            raise ValueError(
                f"unknown refine.activation {activation!r}; choose {tuple(ACTIVATIONS)}"
            )
        if orientation not in ORIENTATION_MODES:
            raise ValueError(
                f"unknown refine.orientation {orientation!r}; choose {ORIENTATION_MODES}"
            )
        if distance not in ("normalized", "fixed"):
            raise ValueError(f"unknown refine.distance {distance!r}; choose normalized or fixed")
        clashes = sorted(set(self.alternatives) & set(RESERVED_METHODS))
        if clashes:
            raise ValueError(f"refine.alternatives may not reuse the method names {clashes}")
        drawable = ["refined", "knn_mean", *self.alternatives]
        unknown = [m for m in self.trajectory_methods if m not in drawable]
        if unknown:
            raise ValueError(f"unknown refine.trajectory_methods {unknown}; choose from {drawable}")

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        poses, scenes = trainer.datamodule.store_poses()
        self.index = self.store(poses, scenes)
        self.position_index = PoseIndex(poses, scenes, distance="fixed", rot_weight=0.0)

    def store(self, poses: Tensor, scenes: Tensor) -> PoseIndex:
        """The retrieval store of poses [N, 7] with scene ids [N], searched with the
        configured distance."""
        return PoseIndex(poses, scenes, distance=self.distance, rot_weight=self.rot_weight)

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._val_runs += 1
        if (self._val_runs - 1) % self.every_n_val_epochs == 0:
            self.refine(trainer, pl_module, "val")

    def on_test_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.refine(trainer, pl_module, "test")

    def refiner(self, pae: torch.nn.Module, index: PoseIndex) -> PositionRefiner:
        """The configured refinement (``refined``; ``knn_mean`` from its neighbours) with
        ``pae`` over the store ``index``."""
        return PositionRefiner(index, pae, seed=self.seed, **self.options)

    def _refine_both(
        self, refiner: PositionRefiner, query: Latents, initial: Tensor, scene: Tensor
    ) -> tuple[Tensor, Tensor]:
        """(refined poses, mean of the same neighbours) [B, 7] each."""
        result = refiner(query, initial, scene)
        return result.poses, refiner.neighbour_mean(result.neighbour_indices, initial)

    def refine(self, trainer: L.Trainer, pl_module: L.LightningModule, split: str) -> None:
        """Refine all queries of the finished evaluation epoch in one batched call per method."""
        outputs = collect_outputs(trainer, pl_module)  # every rank refines all queries
        if outputs is None:
            return
        assert self.index is not None
        d = outputs["z"].shape[-1] // 2
        query = Latents(outputs["z"][:, :d], outputs["z"][:, d:])
        estimate, estimate_scene = outputs[EVAL.estimate], outputs[EVAL.scene_estimate]
        gt, scene = outputs[EVAL.pose], outputs[EVAL.scene]
        stores = {"": self.index}
        if self.audit:
            stores["_test_store"] = self.store(gt, scene).to(self.index.device)

        predictions: dict[str, Tensor] = {}
        elapsed = {}
        for suffix, store in stores.items():
            start = time.perf_counter()
            refined, knn_mean = self._refine_both(
                self.refiner(pl_module.pae, store), query, estimate, estimate_scene
            )
            elapsed[suffix] = time.perf_counter() - start
            predictions[f"refined{suffix}"], predictions[f"knn_mean{suffix}"] = refined, knn_mean
        for name, factory in self.alternatives.items():
            refiner = factory(index=self.index, pae=pl_module.pae)
            predictions[name] = refiner(query, estimate, estimate_scene).poses
        if self.guess_sigma_m:
            generator = torch.Generator().manual_seed(self.seed)
            guess = perturb_positions(gt.cpu(), self.guess_sigma_m, generator).to(gt.device)
            with torch.no_grad():
                guess_latents = pl_module.pae(guess, scene)
            predictions["guess_initial"] = guess
            for suffix, store in stores.items():
                refiner = self.refiner(pl_module.pae, store)
                predictions[f"guess_refined{suffix}"] = refiner(guess_latents, guess, scene).poses

        names = pl_module.scene_names
        figures: dict[str, Tensor] = {}
        for method, poses in predictions.items():
            figures |= self._figures(split, method, poses, gt, scene, names)
        teacher_error = summarise_errors(*pose_errors(estimate.float(), gt.float()), scene, names)[
            "pos_median_m"
        ]
        figures |= self._store_distances(split, estimate, estimate_scene, gt, scene, teacher_error)
        if split == "test":
            figures["bench/refine/callback_ms_per_query"] = torch.tensor(
                1000 * elapsed[""] / len(gt)
            )
        pl_module.log_dict(figures)
        if self.audit:
            self._describe_protocols(trainer)
        if self.trajectory_plot:
            shown = {"teacher": estimate} | {m: predictions[m] for m in self.trajectory_methods}
            log_trajectories(trainer, split, gt, shown, scene, names)
        honest = {m: p for m, p in predictions.items() if m not in RESERVED_METHODS}
        methods = {"teacher": estimate, "refined": predictions["refined"]}
        methods |= {"knn_mean": predictions["knn_mean"]} | honest
        self._plot_error_curves(trainer, split, methods, gt, scene, names)

    def _store_distances(
        self,
        split: str,
        estimate: Tensor,
        estimate_scene: Tensor,
        gt: Tensor,
        scene: Tensor,
        teacher_error_m: Tensor,
    ) -> dict[str, Tensor]:
        assert self.position_index is not None
        _, to_estimate = self.position_index.query(estimate, estimate_scene, 1)
        _, to_gt = self.position_index.query(gt, scene, 1)
        estimate_m, gt_m = to_estimate.quantile(0.5), to_gt.quantile(0.5)
        error = teacher_error_m.clamp(min=1e-12)
        prefix = f"{split}/diagnostics"
        return {
            f"{prefix}/estimate_to_train_m": estimate_m,
            f"{prefix}/gt_to_train_m": gt_m,
            f"{prefix}/estimate_to_train_per_error": estimate_m / error,
            f"{prefix}/gt_to_train_per_error": gt_m / error,
        }

    @staticmethod
    def _figures(
        split: str, method: str, pred: Tensor, gt: Tensor, scene: Tensor, names: list[str]
    ) -> dict[str, Tensor]:
        pos, rot = pose_errors(pred.float(), gt.float())
        summary = summarise_errors(pos, rot, scene, names)
        return {f"{split}/{method}/{key}": value for key, value in summary.items()}

    @staticmethod
    def _describe_protocols(trainer: L.Trainer) -> None:
        """A TensorBoard text (tab TEXT, tag ``refinement/protocols``) that marks the
        ``*_test_store`` scalars as audits reading the evaluated split's labels."""
        for logger in trainer.loggers:
            if isinstance(logger, TensorBoardLogger):
                logger.experiment.add_text("refinement/protocols", PROTOCOLS_TEXT, 0)

    @staticmethod
    def _plot_error_curves(
        trainer: L.Trainer,
        split: str,
        methods: dict[str, Tensor],
        gt: Tensor,
        scene: Tensor,
        names: list[str],
    ) -> None:
        """Cumulative error curves of ``methods`` (name -> poses [N, 7]) against ``gt`` [N,
        7] of scenes ``scene`` [N] (image tag ``{split}/cumulative_errors``)."""
        loggers = tensorboard_loggers(trainer)
        if not loggers:
            return
        errors = {m: pose_errors(p.float(), gt.float()) for m, p in methods.items()}
        image = error_curves_figure(
            f"{split} split, {len(gt)} queries",
            {m: e[0] for m, e in errors.items()},
            {m: e[1] for m, e in errors.items()},
            scene,
            names,
        )
        log_figure(loggers, f"{split}/cumulative_errors", image, trainer.global_step)
