"""Render-and-compare from another APR's starts in a scene-model evaluation
(``render_compare.init=FILE``): an adapter that calibrates on validation for starts of any
error scale (:func:`pae.render_compare.calibrate_any_start`) and refines the file's starts of
the test images (:func:`pae.render_compare.refine`), beside the teacher's own; the
correspondence stages of ``render_compare.matches_from_val`` are tried in that calibration
too."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import lightning as L
import torch

from pae.callbacks.render_compare import HONEST, RenderCompareCallback
from pae.core.errors import ConfigError
from pae.core.metrics import summarise_errors
from pae.data.starts import AXES, FORMATS, Starts, placed_starts, read_starts
from pae.lit.eval_outputs import EVAL, SceneModelEvaluation, collect_outputs
from pae.render_compare import AnyStartOptions, Calibration, Queries, calibrate_any_start, refine
from pae.render_compare.calibration import scene_size
from pae.render_compare.correspondences import MatchQueries
from pae.render_compare.queries import match_figures, method_from, refinement_figures


class RenderCompareFromFile(L.Callback):
    """With ``refinement.init`` (a starts file in the format ``refinement.init_format``,
    :data:`pae.data.starts.FORMATS`, read here, before any work; camera axes
    ``refinement.init_axes``; every test image needs one, matched by path), logs
    ``test/<method>/...`` for ``<method>`` = ``render_compare_from_<file stem>`` (the gate's
    figures and ``worse_than_start_share`` too) and the starts' own figures under
    ``test/start_from_<file stem>/...``, with the gate and first steps chosen on each
    validation run for starts of any scale (``val/<method>/accept_margin`` ..., the stage as
    ``val/<method>/match_*``); the scene
    model is the evaluated module's, the settings ``refinement``'s."""

    def __init__(self, refinement: RenderCompareCallback) -> None:
        super().__init__()
        self.refinement = refinement
        self.calibration: Calibration | None = None
        self.starts: Starts | None = None
        if refinement.init is not None and not Path(refinement.init).is_file():
            raise ConfigError(f"render_compare.init={refinement.init}: no such starts file")
        if refinement.init_axes not in AXES:
            raise ConfigError(f"render_compare.init_axes={refinement.init_axes}: choose {AXES}")
        if refinement.init_format not in (None, *FORMATS):
            raise ConfigError(
                f"render_compare.init_format={refinement.init_format}: choose {FORMATS}"
            )
        if refinement.init is not None:
            self.starts = read_starts(
                refinement.init,
                refinement.init_axes,
                refinement.init_format,
                "render_compare.init_format={}",
            )

    def settings(self, pl_module: SceneModelEvaluation) -> dict[str, Any]:
        """The refiner's settings, with the teacher's features where it scores them."""
        return self.refinement.settings | {"features": self.refinement.features(pl_module.teacher)}

    def matching(
        self, data: Any, pl_module: SceneModelEvaluation, split: str, rows: torch.Tensor
    ) -> MatchQueries | None:
        """``split``'s queries at ``rows`` at the stages' match width (None: no stage)."""
        return self.refinement.match_inputs.queries(data, pl_module.teacher, split, rows)

    @property
    def method(self) -> str:
        return method_from(self.refinement.init or "")

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: SceneModelEvaluation) -> None:
        outputs = collect_outputs(trainer, pl_module)
        if self.refinement.init is None or outputs is None:
            return
        data = trainer.datamodule
        positions, _ = data.train_poses()
        queries = Queries(
            outputs[EVAL.image], outputs[EVAL.intrinsics], outputs[EVAL.scene_estimate],
            matching=self.matching(data, pl_module, "val", outputs[EVAL.index]),
        )  # fmt: skip
        options = self.refinement.options
        stages = AnyStartOptions(
            matches=options.matches_from_val or (),
            filters=options.filters_from_val or (),
            stage_shares=options.match_shares_from_val or (),
        )
        self.calibration, _, _ = calibrate_any_start(
            pl_module.scene_model, queries, outputs[EVAL.pose].float(),
            scene_size(positions[:, :3].double()), self.settings(pl_module), stages,
        )  # fmt: skip
        gate = (self.calibration.accept_margin, self.calibration.accept_score)
        figures = dict(zip(("accept_margin", "accept_score"), gate, strict=True))
        figures |= dict(self.calibration.steps) | match_figures(self.calibration.match)
        pl_module.log_dict({f"val/{self.method}/{k}": torch.tensor(v) for k, v in figures.items()})

    def on_test_epoch_end(self, trainer: L.Trainer, pl_module: SceneModelEvaluation) -> None:
        outputs = collect_outputs(trainer, pl_module)
        if self.starts is None or outputs is None:
            return
        data, names = trainer.datamodule, pl_module.scene_names
        images = [data.tables["test"].img_path[i] for i in outputs[EVAL.index].tolist()]
        starts, scenes = placed_starts(images, self.starts, str(self.refinement.init), names)
        scenes = outputs[EVAL.scene_estimate] if scenes is None else scenes
        calibration = self.calibration or self.refinement.calibration(HONEST)
        begin = time.perf_counter()
        matching = None
        if calibration.match.active:
            matching = self.matching(data, pl_module, "test", outputs[EVAL.index])
        queries = Queries(
            outputs[EVAL.image], outputs[EVAL.intrinsics], scenes.to(starts.device),
            matching=matching,
        )  # fmt: skip
        refinement = refine(
            pl_module.scene_model, queries, starts, calibration, settings=self.settings(pl_module)
        )
        seconds = time.perf_counter() - begin
        truth, scene = outputs[EVAL.pose].float(), outputs[EVAL.scene]
        figures, start_errors, _ = refinement_figures(
            f"test/{self.method}", refinement, calibration, starts, truth, scene, names
        )
        start = self.method.replace("render_compare_from_", "start_from_")
        summary = summarise_errors(*start_errors, scene, names)
        figures |= {f"test/{start}/{key}": value for key, value in summary.items()}
        figures[f"bench/{self.method}/ms_per_query"] = torch.tensor(1000 * seconds / len(truth))
        pl_module.log_dict(figures)
