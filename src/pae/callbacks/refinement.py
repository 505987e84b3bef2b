"""Test-time position refinement (paper §3.3) as a Lightning callback for student runs: an
adapter that runs :class:`pae.refine.protocols.RefinementProtocols` on every evaluated
split and logs its figures."""

from __future__ import annotations

import dataclasses
from typing import Any

import lightning as L
import torch
from lightning.pytorch.loggers import TensorBoardLogger
from torch import Tensor

from pae.callbacks.error_curves import log_error_curves
from pae.callbacks.settings import TestTimeRefinementSettings
from pae.callbacks.trajectory import log_trajectories
from pae.core.geometry import pose_errors
from pae.core.metrics import summarise_errors
from pae.lit.eval_outputs import EVAL, collect_outputs
from pae.models.base import Latents
from pae.refine import PoseIndex, PositionRefiner
from pae.refine.protocols import (
    RESERVED_METHODS,
    RefinementProtocols,
    RefinerFactory,
    store_distances,
)
from pae.refine.settings import RefinementSettings

PROTOCOLS_TEXT = (
    "**Retrieval protocols.** `refined`, `knn_mean`, `guess_refined` and the alternatives "
    "retrieve among the train poses (the protocol the paper describes). Scalars named "
    "`*_test_store` retrieve among the evaluated split's own ground-truth poses, as the "
    "authors' public scripts do: they read the test labels and can retrieve a query's own "
    "pose. They are an audit, not a result. `knn_mean*` is the plain mean of the same "
    "neighbours, with no PAE: what refinement adds is the difference to it."
)


class TestTimeRefinement(L.Callback):
    """Refines every evaluated query of a StudentEvaluator (or StudentModule) after every
    ``every_n_val_epochs``-th validation and every test, in one batched call per method
    (:meth:`RefinementProtocols.predict`), and logs ``{split}/<method>/...`` for each:
    ``refined`` (the paper's refinement, train poses), ``knn_mean`` (the plain mean of the
    same neighbours, no PAE), with ``audit`` the same from the split's own poses
    (``*_test_store``: the authors' scripts' protocol, an audit), with ``guess_sigma_m`` the
    random-guess check (``guess_initial``, ``guess_refined``), every alternative, and
    ``{split}/diagnostics/...`` (:func:`store_distances`). Under DDP every process gathers
    all queries (dataset order, each once). The settings: :class:`TestTimeRefinementSettings`
    (the refinement's, :class:`RefinementProtocols`, and how often it runs and what it
    draws); ``alternatives``: named factories of other refiners (train store only)."""

    settings_types = (TestTimeRefinementSettings,)
    """The settings it takes by name besides ``alternatives``."""

    def __init__(
        self, alternatives: dict[str, RefinerFactory] | None = None, **settings: Any
    ) -> None:
        super().__init__()
        given = TestTimeRefinementSettings(**settings)
        method = {f.name: getattr(given, f.name) for f in dataclasses.fields(RefinementSettings)}
        self.protocols = RefinementProtocols(**method, alternatives=dict(alternatives or {}))
        self.every_n_val_epochs = given.every_n_val_epochs
        self.trajectory_plot = given.trajectory_plot
        self.trajectory_methods = tuple(given.trajectory_methods)
        self.index: PoseIndex | None = None
        self.position_index: PoseIndex | None = None
        self._val_runs = 0
        drawable = ["refined", "knn_mean", *self.protocols.alternatives]
        unknown = [m for m in self.trajectory_methods if m not in drawable]
        if unknown:
            raise ValueError(f"unknown refine.trajectory_methods {unknown}; choose from {drawable}")

    @property
    def alternatives(self) -> dict[str, RefinerFactory]:
        return dict(self.protocols.alternatives)

    def store(self, poses: Tensor, scenes: Tensor) -> PoseIndex:
        return self.protocols.store(poses, scenes)

    def refiner(self, pae: torch.nn.Module, index: PoseIndex) -> PositionRefiner:
        return self.protocols.refiner(pae, index)

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        poses, scenes = trainer.datamodule.store_poses()
        self.index = self.store(poses, scenes)
        self.position_index = PoseIndex(poses, scenes, distance="fixed", rot_weight=0.0)

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._val_runs += 1
        if (self._val_runs - 1) % self.every_n_val_epochs == 0:
            self.refine(trainer, pl_module, "val")

    def on_test_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.refine(trainer, pl_module, "test")

    def refine(self, trainer: L.Trainer, pl_module: L.LightningModule, split: str) -> None:
        """Refine all queries of the finished evaluation epoch and log the figures."""
        outputs = collect_outputs(trainer, pl_module)  # every rank refines all queries
        if outputs is None:
            return
        assert self.index is not None and self.position_index is not None
        d = outputs["z"].shape[-1] // 2
        query = Latents(outputs["z"][:, :d], outputs["z"][:, d:])
        estimate, estimate_scene = outputs[EVAL.estimate], outputs[EVAL.scene_estimate]
        gt, scene = outputs[EVAL.pose], outputs[EVAL.scene]
        predictions, seconds = self.protocols.predict(
            pl_module.pae, self.index, query, estimate, estimate_scene, gt, scene
        )
        names = pl_module.scene_names
        figures: dict[str, Tensor] = {}
        for method, poses in predictions.items():
            summary = summarise_errors(*pose_errors(poses.float(), gt.float()), scene, names)
            figures |= {f"{split}/{method}/{key}": value for key, value in summary.items()}
        errors = pose_errors(estimate.float(), gt.float())
        teacher_m = summarise_errors(*errors, scene, names)["pos_median_m"]
        figures |= store_distances(
            self.position_index, f"{split}/diagnostics", estimate, estimate_scene, gt, scene,
            teacher_m,
        )  # fmt: skip
        if split == "test":
            figures["bench/refine/callback_ms_per_query"] = torch.tensor(1000 * seconds / len(gt))
        pl_module.log_dict(figures)
        if self.protocols.audit:
            for logger in trainer.loggers:
                if isinstance(logger, TensorBoardLogger):
                    logger.experiment.add_text("refinement/protocols", PROTOCOLS_TEXT, 0)
        if self.trajectory_plot:
            shown = {"teacher": estimate} | {m: predictions[m] for m in self.trajectory_methods}
            log_trajectories(trainer, split, gt, shown, scene, names)
        honest = {m: p for m, p in predictions.items() if m not in RESERVED_METHODS}
        methods = {"teacher": estimate, "refined": predictions["refined"]}
        methods |= {"knn_mean": predictions["knn_mean"]} | honest
        log_error_curves(trainer, split, methods, gt, scene, names)
