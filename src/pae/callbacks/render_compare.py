"""Render-and-compare as a Lightning callback for scene-model runs: an adapter that calls
:func:`pae.render_compare.calibrate` on validation and ``refine`` at test, and logs."""

from __future__ import annotations

import functools
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import lightning as L
import torch
from torch import Tensor

from pae.lit.eval_outputs import (
    EVAL,
    HONEST,
    ORACLE,
    MatchInputs,
    SceneModelEvaluation,
    check_held_out,
    collect_outputs,
    query_sequences,
    scene_models,
)
from pae.render_compare.api import Queries, Refinement, Validation, calibrate, refine
from pae.render_compare.calibration import Calibration, CalibrationOptions, teacher_features
from pae.render_compare.queries import refinement_figures, write_queries
from pae.render_compare.refiner import ACCEPT_ALL, RenderCompareRefiner, refiner_defaults
from pae.render_compare.sequences import SequenceOptions
from pae.scene_model.base import SceneModel


class RenderCompareCallback(L.Callback):
    """Refines every query a ``SceneModelEvaluation`` evaluates from the teacher's estimate
    after every ``every_n_val_epochs``-th validation (``calibrate`` under
    :class:`CalibrationOptions`) and every test (``refine``); logs (:func:`refinement_figures`,
    ``bench/<method>/ms_per_query``) and writes the queries' CSVs. ``refiner``: the partial
    of ``render_compare.refiner`` or a mapping; ``feature_layers``: the backbone's modules
    behind ``refiner.score=features``; ``init*``: another APR's starts; ``sequence_*``:
    :class:`SequenceOptions`; ``match_*``: :class:`pae.lit.eval_outputs.MatchInputs`."""

    def __init__(
        self,
        refiner: functools.partial[RenderCompareRefiner] | Mapping[str, Any] | None = None,
        oracle: bool = True,
        every_n_val_epochs: int = 1,
        feature_layers: int = 2,
        accept_margin: float | str = "auto",
        accept_score: float | str = ACCEPT_ALL,
        step_from_val: dict[str, float] | None = None,
        scene_check_below: float | str = "auto",
        filters_from_val: list[dict[str, float]] | None = None,
        init: str | None = None,
        init_axes: str = "pae",
        init_format: str | None = None,
        sequence_passes: int = 0,
        sequence_window: int = 0,
        sequence_scene_vote: bool = False,
        sequence_fit: str = "median",
        gate_objective: str = "mean",
        matches_from_val: list[dict[str, Any]] | None = None,
        match_descriptor: str = "teacher",
        match_shares_from_val: list[float] | None = None,
    ) -> None:
        super().__init__()
        settings = refiner.keywords if isinstance(refiner, functools.partial) else refiner
        self.settings = refiner_defaults() | dict(settings or {})
        self.oracle, self.every_n_val_epochs = oracle, max(1, every_n_val_epochs)
        self.feature_layers, self.init = feature_layers, init
        self.init_axes, self.init_format = init_axes, init_format
        on_val = (accept_margin, accept_score, step_from_val, scene_check_below, filters_from_val)
        matches = (matches_from_val, match_shares_from_val)
        self.options = CalibrationOptions(*on_val, gate_objective, *matches)
        self.match_inputs = MatchInputs(matches_from_val, match_descriptor)
        sequence = (sequence_passes, sequence_window, sequence_scene_vote, sequence_fit)
        self.sequence = SequenceOptions(*sequence)
        self.calibrations: dict[str, Calibration] = {}  # method -> the last chosen on val
        self.refined: dict[str, dict[str, Tensor]] = {}  # split -> method -> poses kept
        self.refinements: dict[str, dict[str, Refinement]] = {}  # split -> method -> the last
        self._val_runs = 0
        RenderCompareRefiner(SceneModel(), features=lambda x: x, **self.settings)  # checks
        self.query_width = int(self.settings["resolution"])  # the compare width evaluation keeps

    def calibration(self, name: str) -> Calibration:
        """Method ``name``'s calibration: the last chosen on val, else the fixed options."""
        return self.calibrations.get(name) or self.options.uncalibrated()

    def features(self, teacher: torch.nn.Module | None) -> Any:
        """The teacher's features where the refiner scores features, else None."""
        scored = self.settings["score"] == "features"
        return teacher_features(teacher, self.feature_layers) if scored else None

    def setup(self, trainer: L.Trainer, pl_module: L.LightningModule, stage: str) -> None:
        check_held_out(trainer.datamodule, stage)  # before any work: val is not the test split

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: SceneModelEvaluation) -> None:
        self._val_runs += 1
        if (self._val_runs - 1) % self.every_n_val_epochs == 0:
            self.refine(trainer, pl_module, "val")

    def on_test_epoch_end(self, trainer: L.Trainer, pl_module: SceneModelEvaluation) -> None:
        self.refine(trainer, pl_module, "test")

    def refine(self, trainer: L.Trainer, pl_module: SceneModelEvaluation, split: str) -> None:
        """Refine all queries of the finished evaluation epoch and log the figures."""
        outputs = collect_outputs(trainer, pl_module)
        if outputs is None:
            return
        models = scene_models(pl_module.scene_model, trainer.datamodule, self.oracle)
        truth, estimate = outputs[EVAL.pose].float(), outputs[EVAL.estimate].float()
        scene, predicted = outputs[EVAL.scene], outputs[EVAL.scene_estimate]
        decided = predicted if EVAL.scene_poses in outputs or self.sequence.vote_scene else None
        rows, data = outputs[EVAL.index], trainer.datamodule
        queries = Queries(
            outputs[EVAL.image], outputs[EVAL.intrinsics], predicted,
            outputs.get(EVAL.scene_poses), outputs.get(EVAL.scene_logits),
            self.match_inputs.queries(data, pl_module.teacher, split, rows),
        )  # fmt: skip
        sequences = query_sequences(self.sequence, data, split, rows)
        settings = self.settings | {"features": self.features(pl_module.teacher)}
        figures: dict[str, Tensor] = {}
        self.refined[split], self.refinements[split] = {"teacher": estimate}, {}
        for name, model in models.items():
            start = time.perf_counter()
            if split == "val":
                val = Validation(queries, estimate, truth, scene)
                self.calibrations[name], refinement = calibrate(
                    model, val, self.options, sequences, settings
                )
            else:
                calibration = self.calibration(name)
                refinement = refine(model, queries, estimate, calibration, sequences, settings)
            seconds = time.perf_counter() - start
            self.refined[split][name], self.refinements[split][name] = refinement.poses, refinement
            found, starts, refined = refinement_figures(
                f"{split}/{name}", refinement, self.calibration(name), estimate, truth, scene,
                pl_module.scene_names, decided,
            )  # fmt: skip
            figures |= found
            if getattr(trainer, "log_dir", None) is not None:
                path = Path(trainer.log_dir) / f"queries_{split}_{name}.csv"
                names = [pl_module.scene_names[s] for s in scene.tolist()]
                write_queries(path, outputs[EVAL.index], names, starts, refined, refinement)
            if split == "test":
                figures[f"bench/{name}/ms_per_query"] = torch.tensor(1000 * seconds / len(truth))
        steps = self.calibration(HONEST if HONEST in models else ORACLE).steps
        figures |= {f"{split}/{HONEST}/{key}": torch.tensor(v) for key, v in steps.items()}
        pl_module.log_dict(figures)
