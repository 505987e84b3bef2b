"""Render-and-compare refinement as a Lightning callback for scene-model runs."""

from __future__ import annotations

import functools
import logging
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import lightning as L
import torch
from torch import Tensor

from pae.core.geometry import pose_errors
from pae.core.metrics import summarise_errors
from pae.lit.eval_outputs import EVAL, SceneModelEvaluation, collect_outputs
from pae.render_compare.calibration import (
    choose_gate,
    steps_from_errors,
    teacher_features,
)
from pae.render_compare.queries import gate_figures, write_queries
from pae.render_compare.refiner import (
    ACCEPT_ALL,
    RenderCompareRefiner,
    RenderCompareResult,
    gate,
    refiner_defaults,
)
from pae.render_compare.scene_decision import (
    ALWAYS,
    NEVER,
    Refine,
    choose_scene_check,
    decide_scenes,
    narrow,
)
from pae.scene_model.base import SceneModel
from pae.scene_model.oracle import OracleSceneModel

HONEST = "render_compare"
ORACLE = "render_compare_oracle"
log = logging.getLogger(__name__)


class RenderCompareCallback(L.Callback):
    """Refines every evaluated query of a module with a scene model
    (:class:`pae.lit.eval_outputs.SceneModelEvaluation`, e.g. SceneModelModule) by
    render-and-compare, from the teacher's estimate, in one batched call per
    method, after every ``every_n_val_epochs``-th validation and every test:

    - ``{split}/render_compare/...``: against the module's scene model, learned from the
      train images only (``render_compare_oracle`` instead when that model is the oracle);
    - with ``oracle`` on data that knows its true scenes (the synthetic benchmark),
      ``{split}/render_compare_oracle/...``: the same search against the benchmark's own
      renderer, a bound (it knows the scene);
    - ``bench/render_compare/ms_per_query`` (test): the honest search's time per query;
    - ``queries_{split}_{method}.csv`` in the trainer's log folder: each query's start and
      refined errors, scores and whether the gate accepted it (:func:`write_queries`).

    A refined pose replaces the teacher's only where its score beats the start's by more
    than ``accept_margin`` and itself exceeds ``accept_score``
    (:func:`pae.render_compare.refiner.gate`: a low final score marks a query the scene model
    does not explain; ``ACCEPT_ALL``, the default: no floor); ``auto`` chooses each on every
    validation run (:func:`choose_gate`, jointly, from the split's held-out train sequences)
    and applies the last choice at test (margin 0 and no floor where no validation ran).
    Beside each method's figures: ``accept_margin``, ``accept_score``, ``accepted_share``, the
    median position error of the accepted queries (refined) and of the rejected ones (kept at
    the start), ``ungated_pos_median_m`` (every refinement accepted) and
    ``worse_than_start_share`` (queries that end farther from the truth than the teacher's
    estimate: a wrong basin).

    ``step_from_val`` (``{"position": a, "orientation": b}``) sets the search's first steps
    from the teacher's typical error, so that the search covers it at every scene scale: on
    each validation run ``position_sigma_m`` = a × the teacher's median val position error
    (m) and ``orientation_sigma_deg`` = b × its median val orientation error (deg), applied
    at test (the refiner's own settings where no validation ran; None: always those). The
    polish needs no scale: its Levenberg–Marquardt steps are invariant to the units.

    With a teacher that predicts the scene (its poses for every scene in the outputs),
    ``scene_check_below`` (a ZNCC, or ``auto``) moves poorly explained queries to the scene
    that explains them best (:meth:`decide_scenes`), reported as ``scene_accuracy``.

    ``refiner`` builds the refiner from the scene model and ``features=``: the partial that
    Hydra makes of ``render_compare.refiner`` (its ``_target_`` with ``_partial_``), or a
    mapping of settings that replace the defaults (:func:`refiner_defaults`);
    ``feature_layers`` sets how many modules of the teacher backbone make the features of
    ``refiner.score=features``.
    """

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
    ) -> None:
        super().__init__()
        if not isinstance(refiner, functools.partial):
            refiner = functools.partial(
                RenderCompareRefiner, **(refiner_defaults() | dict(refiner or {}))
            )
        self.build_refiner = refiner
        self.oracle = oracle
        self.every_n_val_epochs = max(1, every_n_val_epochs)
        self.feature_layers = feature_layers
        if accept_margin != "auto" and not isinstance(accept_margin, int | float):
            raise ValueError(
                f"render_compare.accept_margin must be a number or auto, not {accept_margin!r}"
            )
        if accept_score != "auto" and not isinstance(accept_score, int | float):
            raise ValueError(
                f"render_compare.accept_score must be a number or auto, not {accept_score!r}"
            )
        self.accept_margin = accept_margin
        self.accept_score = accept_score
        self.gates: dict[str, tuple[float, float]] = {}
        self.step_from_val = dict(step_from_val) if step_from_val is not None else None
        if self.step_from_val is not None and (
            set(self.step_from_val) != {"position", "orientation"}
            or min(self.step_from_val.values()) <= 0
        ):
            raise ValueError(
                "render_compare.step_from_val needs position and orientation fractions > 0, "
                f"got {step_from_val!r}"
            )
        self.steps: dict[str, float] = {}
        if scene_check_below != "auto" and not isinstance(scene_check_below, int | float):
            raise ValueError(
                "render_compare.scene_check_below must be a number or auto, not "
                f"{scene_check_below!r}"
            )
        self.scene_check_below = scene_check_below
        self.scene_checks: dict[str, float] = {}
        self.refined: dict[str, dict[str, Tensor]] = {}
        """split -> method -> the poses [N, 7] the last run kept (after the gate), with
        ``teacher`` (the starts), in the order of the split's collected outputs."""
        self._val_runs = 0
        refiner(SceneModel(), features=lambda x: x)  # its keys and ranges, before any work

    def setting(self, name: str) -> Any:
        """The refiner's setting ``name`` as configured."""
        return self.build_refiner.keywords[name]

    @property
    def query_width(self) -> int:
        """The width (px) at which the refiner compares queries: what evaluation keeps."""
        return int(self.setting("resolution"))

    def gate_setting(
        self, name: str, split: str, result: RenderCompareResult, errors: Any
    ) -> tuple[float, float]:
        """The acceptance margin and score floor of method ``name`` on ``split`` (each chosen
        here on val where ``auto``; errors: the refined and start position errors [N], m)."""
        fixed_margin = None if self.accept_margin == "auto" else float(self.accept_margin)
        fixed_floor = None if self.accept_score == "auto" else float(self.accept_score)
        if fixed_margin is not None and fixed_floor is not None:
            return fixed_margin, fixed_floor
        if split == "val":
            gains = result.score - result.initial_score
            self.gates[name] = choose_gate(
                gains, result.score, *errors, margin=fixed_margin, floor=fixed_floor
            )
        elif name not in self.gates:
            log.warning(
                "render_compare: no validation ran to choose the gate; margin 0, no floor on %s",
                split,
            )
        default = (
            0.0 if fixed_margin is None else fixed_margin,
            ACCEPT_ALL if fixed_floor is None else fixed_floor,
        )
        return self.gates.get(name, default)

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: SceneModelEvaluation) -> None:
        self._val_runs += 1
        if (self._val_runs - 1) % self.every_n_val_epochs == 0:
            self.refine(trainer, pl_module, "val")

    def on_test_epoch_end(self, trainer: L.Trainer, pl_module: SceneModelEvaluation) -> None:
        self.refine(trainer, pl_module, "test")

    def refiner(self, scene_model: SceneModel, teacher: torch.nn.Module) -> RenderCompareRefiner:
        """The configured refiner against ``scene_model`` (features from ``teacher``), with the
        steps chosen on the last validation run (``step_from_val``)."""
        features = None
        if self.setting("score") == "features":
            features = teacher_features(teacher, self.feature_layers)
        return self.build_refiner(scene_model, features=features, **self.steps)

    def choose_steps(self, estimate: Tensor, truth: Tensor) -> None:
        """``step_from_val``: the search's first steps from the teacher's median errors of
        the validation estimates [N, 7] against their true poses [N, 7]."""
        if self.step_from_val is None:
            return
        self.steps = steps_from_errors(estimate, truth, self.step_from_val)

    def decide_scenes(
        self,
        name: str,
        split: str,
        refine: Refine,
        outputs: dict[str, Tensor],
        first: RenderCompareResult,
    ) -> tuple[RenderCompareResult, dict[str, Tensor]]:
        """For a teacher that predicts the scene: the queries scoring below
        ``scene_check_below`` in their predicted scene are refined in the others too and
        moved to the best-scoring one (:func:`decide_scenes`; ``auto``: the floor is chosen
        on each validation run for scene accuracy and applied at test) -> the refinement in
        the decided scenes and the figures ``scene_accuracy``, ``scene_check_below`` and
        ``scene_checked_share``."""
        predicted, truth = outputs[EVAL.scene_estimate], outputs[EVAL.scene]
        arguments = (outputs[EVAL.image], outputs[EVAL.intrinsics], outputs[EVAL.scene_poses])
        below = self.scene_check_below
        if below == "auto" and split == "val":
            every = decide_scenes(refine, *arguments, predicted, first, ALWAYS)
            self.scene_checks[name] = choose_scene_check(first.score, predicted, every.scene, truth)
            floor = self.scene_checks[name]
            decision = narrow(every, first, predicted, first.score < floor)
        else:
            floor = float(self.scene_checks.get(name, NEVER) if below == "auto" else below)
            decision = decide_scenes(refine, *arguments, predicted, first, floor)
        figures = {
            "scene_accuracy": (decision.scene == truth).float().mean(),
            "scene_check_below": torch.tensor(floor),
            "scene_checked_share": decision.checked.float().mean(),
        }
        return decision.result, figures

    def refine(self, trainer: L.Trainer, pl_module: SceneModelEvaluation, split: str) -> None:
        """Refine all queries of the finished evaluation epoch and log the figures."""
        outputs = collect_outputs(trainer, pl_module)
        if outputs is None:
            return
        data = trainer.datamodule
        intrinsics = outputs[EVAL.intrinsics]
        models = {HONEST: pl_module.scene_model}
        if isinstance(pl_module.scene_model, OracleSceneModel):
            models = {ORACLE: pl_module.scene_model}
        elif self.oracle:
            scenes = oracle_scenes(data)
            if scenes is not None:
                models[ORACLE] = OracleSceneModel(scenes)
        if split == "val":
            self.choose_steps(outputs[EVAL.estimate], outputs[EVAL.pose])
        figures: dict[str, Tensor] = {
            f"{split}/{HONEST}/{key}": torch.tensor(value) for key, value in self.steps.items()
        }
        self.refined[split] = {"teacher": outputs[EVAL.estimate].float()}
        for name, model in models.items():
            start = time.perf_counter()
            refine = self.refiner(model, pl_module.teacher)
            result = refine(
                outputs[EVAL.image],
                intrinsics,
                outputs[EVAL.estimate],
                outputs[EVAL.scene_estimate],
            )
            if EVAL.scene_poses in outputs:
                result, decided = self.decide_scenes(name, split, refine, outputs, result)
                figures |= {f"{split}/{name}/{key}": value for key, value in decided.items()}
            seconds = time.perf_counter() - start
            truth, estimate = outputs[EVAL.pose].float(), outputs[EVAL.estimate].float()
            refined_pos, refined_rot = pose_errors(result.poses.float(), truth)
            start_pos, start_rot = pose_errors(estimate, truth)
            margin, floor = self.gate_setting(name, split, result, (refined_pos, start_pos))
            gated = gate(result, estimate, margin, floor)
            self.refined[split][name] = gated.poses.float()
            pos, rot = pose_errors(gated.poses.float(), truth)
            summary = summarise_errors(pos, rot, outputs[EVAL.scene], pl_module.scene_names)
            figures |= {f"{split}/{name}/{key}": value for key, value in summary.items()}
            figures |= gate_figures(
                f"{split}/{name}", (margin, floor), gated.accepted, pos, refined_pos
            )
            figures[f"{split}/{name}/worse_than_start_share"] = (pos > start_pos).float().mean()
            if getattr(trainer, "log_dir", None) is not None:
                path = Path(trainer.log_dir) / f"queries_{split}_{name}.csv"
                names = [pl_module.scene_names[s] for s in outputs[EVAL.scene].tolist()]
                starts, refined = (start_pos, start_rot), (refined_pos, refined_rot)
                write_queries(path, outputs[EVAL.index], names, starts, refined, result, gated)
            if split == "test":
                ms = torch.tensor(1000 * seconds / len(pos))
                figures[f"bench/{name}/ms_per_query"] = ms
        pl_module.log_dict(figures)


def oracle_scenes(data: Any) -> list[Any] | None:
    """The true scenes of a data module that knows them (the synthetic benchmark), else None."""
    source = getattr(data, "images", data)
    scenes = getattr(source, "oracle_scenes", None)
    return scenes() if callable(scenes) else None
