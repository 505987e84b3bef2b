"""Render-and-compare refinement as a Lightning callback for scene-model runs."""

from __future__ import annotations

import time
from typing import Any

import lightning as L
import torch
from torch import Tensor

from pae.data.transforms import ImageTransform
from pae.geometry import pose_errors
from pae.metrics import first_occurrences, summarise_errors
from pae.models.oracle_scene import OracleSceneModel
from pae.models.scene_model import SceneModel
from pae.refine.render_compare import RenderCompareRefiner

HONEST = "render_compare"
ORACLE = "render_compare_oracle"


def teacher_features(teacher: torch.nn.Module, layers: int) -> Any:
    """The first ``layers`` modules of the teacher backbone's feature extractor, applied to
    RGB images in [0, 1] (normalised as the teacher's inputs are)."""
    features = teacher.backbone.features[:layers]

    def extract(rgb: Tensor) -> Tensor:
        return features(ImageTransform.normalize_batch(rgb))

    return extract


class RenderCompareRefinement(L.Callback):
    """Refines every evaluated query of a SceneModelModule (or an evaluator with a scene
    model) by render-and-compare, from the teacher's estimate, in one batched call per
    method, after every ``every_n_val_epochs``-th validation and every test:

    - ``{split}/render_compare/...``: against the module's scene model, learned from the
      train images only (``render_compare_oracle`` instead when that model is the oracle);
    - with ``oracle`` on data that knows its true scenes (the synthetic benchmark),
      ``{split}/render_compare_oracle/...``: the same search against the benchmark's own
      renderer, a bound (it knows the scene);
    - ``bench/render_compare/ms_per_query`` (test): the honest search's time per query.

    ``refiner`` holds RenderCompareRefiner's settings; ``feature_layers`` sets how many
    modules of the teacher backbone make the features of ``refiner.score=features``.
    """

    def __init__(
        self,
        refiner: dict[str, Any] | None = None,
        oracle: bool = True,
        every_n_val_epochs: int = 1,
        feature_layers: int = 2,
    ) -> None:
        super().__init__()
        self.settings = dict(refiner or {})
        self.oracle = oracle
        self.every_n_val_epochs = max(1, every_n_val_epochs)
        self.feature_layers = feature_layers
        self._val_runs = 0
        RenderCompareRefiner(SceneModel(), features=lambda x: x, **self.settings)  # check keys

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self._val_runs += 1
        if (self._val_runs - 1) % self.every_n_val_epochs == 0:
            self.refine(trainer, pl_module, "val")

    def on_test_epoch_end(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
        self.refine(trainer, pl_module, "test")

    def refiner(self, scene_model: SceneModel, teacher: torch.nn.Module) -> RenderCompareRefiner:
        """The configured refiner against ``scene_model`` (features from ``teacher``)."""
        features = None
        if self.settings.get("score") == "features":
            features = teacher_features(teacher, self.feature_layers)
        return RenderCompareRefiner(scene_model, features=features, **self.settings)

    def refine(self, trainer: L.Trainer, pl_module: L.LightningModule, split: str) -> None:
        """Refine all queries of the finished evaluation epoch and log the figures."""
        if not pl_module.eval_outputs:
            return
        outputs = {
            key: torch.cat([batch[key] for batch in pl_module.eval_outputs])
            for key in pl_module.eval_outputs[0]
        }
        if trainer.world_size > 1:
            outputs = {k: pl_module.all_gather(v).flatten(0, 1) for k, v in outputs.items()}
        keep = first_occurrences(outputs["index"])
        outputs = {key: value[keep] for key, value in outputs.items()}
        data = trainer.datamodule
        intrinsics = data.intrinsics(split)[outputs["index"].cpu()].to(outputs["image"].device)
        models = {HONEST: pl_module.scene_model}
        if isinstance(pl_module.scene_model, OracleSceneModel):
            models = {ORACLE: pl_module.scene_model}
        elif self.oracle:
            scenes = oracle_scenes(data)
            if scenes is not None:
                models[ORACLE] = OracleSceneModel(scenes)
        figures: dict[str, Tensor] = {}
        for name, model in models.items():
            start = time.perf_counter()
            result = self.refiner(model, pl_module.teacher)(
                outputs["image"], intrinsics, outputs["estimate"], outputs["scene_estimate"]
            )
            seconds = time.perf_counter() - start
            pos, rot = pose_errors(result.poses.float(), outputs["pose"].float())
            summary = summarise_errors(pos, rot, outputs["scene"], pl_module.scene_names)
            figures |= {f"{split}/{name}/{key}": value for key, value in summary.items()}
            if split == "test":
                ms = torch.tensor(1000 * seconds / len(pos))
                figures[f"bench/{name}/ms_per_query"] = ms
        pl_module.log_dict(figures)


def oracle_scenes(data: Any) -> list[Any] | None:
    """The true scenes of a data module that knows them (the synthetic benchmark), else None."""
    source = getattr(data, "images", data)
    scenes = getattr(source, "oracle_scenes", None)
    return scenes() if callable(scenes) else None
