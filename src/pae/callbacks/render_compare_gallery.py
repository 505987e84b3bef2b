"""What render-and-compare does, as TensorBoard images: per scene a few queries, each beside
the scene model's rendering at the teacher's estimate and at the refined pose, labelled with
their errors; and the cumulative error curves of the teacher and render-and-compare."""

from __future__ import annotations

from pathlib import Path

import lightning as L
import torch
from lightning.pytorch.loggers import TensorBoardLogger
from torch import Tensor, nn

from pae.callbacks.error_curves import error_curves_figure
from pae.callbacks.render_compare import HONEST, ORACLE, RenderCompareCallback
from pae.callbacks.tensorboard import log_figure, tensorboard_loggers
from pae.callbacks.trajectory import log_trajectories
from pae.core.camera import scale_intrinsics
from pae.core.geometry import pose_errors
from pae.lit.eval_outputs import EVAL, SceneModelEvaluation, collect_outputs
from pae.report.gallery import gallery_figure, gallery_labels, read_query_errors


class RenderCompareGallery(L.Callback):
    """After every test (and, with ``on_val``, every validation run), per scene ``queries``
    queries evenly spaced over the evaluated split: the query | the scene model's rendering at
    the teacher's estimate | at the pose render-and-compare refined it to (the one the gate
    kept), each labelled with its position (m) and orientation (deg) error; TensorBoard
    image ``{split}/render_compare/gallery/<scene>``, panels ``panel_px`` px wide.

    The refined poses are those ``refinement`` kept (through the gate, in the scene its scene
    decision chose, rendered there), so they are the poses its figures count. With them,
    ``{split}/cumulative_errors``:
    the teacher's and each render-and-compare method's cumulative error curves over the
    whole split (:meth:`curves`), and per scene the trajectory figure
    ``{split}/trajectory/<scene>``: the true positions, the teacher's and each
    render-and-compare method's (``RenderCompareCallback.refined``)."""

    def __init__(
        self,
        refinement: RenderCompareCallback,
        queries: int = 4,
        panel_px: int = 128,
        on_val: bool = False,
    ) -> None:
        super().__init__()
        self.refinement = refinement
        self.queries = queries
        self.panel_px = panel_px
        self.on_val = on_val

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: SceneModelEvaluation) -> None:
        if self.on_val:
            self.draw(trainer, pl_module, "val")

    def on_test_epoch_end(self, trainer: L.Trainer, pl_module: SceneModelEvaluation) -> None:
        self.draw(trainer, pl_module, "test")

    def picked(self, scene: Tensor) -> Tensor:
        """Rows [K] of ``queries`` queries of each scene ids [N], evenly spaced over the
        scene's queries in split order, scene by scene."""
        rows = []
        for index in scene.unique().tolist():
            members = (scene == index).nonzero().flatten()
            spaced = torch.linspace(0, len(members) - 1, min(self.queries, len(members)))
            rows.append(members[spaced.round().long().unique()])
        return torch.cat(rows)

    @torch.no_grad()
    def draw(self, trainer: L.Trainer, pl_module: SceneModelEvaluation, split: str) -> None:
        """Render the picked queries' poses and log one figure per scene."""
        loggers = tensorboard_loggers(trainer)
        if not loggers or trainer.world_size > 1:
            return
        outputs = collect_outputs(trainer, pl_module, gather=False)
        kept = self.refinement.refinements.get(split, {})
        refinement = kept.get(HONEST, kept.get(ORACLE))
        if outputs is None or refinement is None:
            return
        rows = self.picked(outputs[EVAL.scene].cpu())
        model = pl_module.scene_model
        picked = {key: value[rows.to(value.device)] for key, value in outputs.items()}
        estimate = picked[EVAL.estimate].float()
        own = rows.to(refinement.poses.device)
        refined, accepted = refinement.poses[own].float(), refinement.accepted[own]
        decided = refinement.scenes[own].to(picked[EVAL.scene_estimate])
        images = picked[EVAL.image]
        h, w = images.shape[-2:]
        scale = self.panel_px / w
        size = (round(h * scale), self.panel_px)
        intrinsics = scale_intrinsics(picked[EVAL.intrinsics], scale, scale)
        views = ((estimate, picked[EVAL.scene_estimate]), (refined.to(estimate), decided))
        renders = [
            model.render(poses, scenes, intrinsics, size[1], size[0]).rgb for poses, scenes in views
        ]
        query = nn.functional.interpolate(images, size=size, mode="nearest")
        panels = torch.stack([query, *(r.to(query) for r in renders)], 1)  # [K, 3, 3, h, w]
        truth = picked[EVAL.pose].float()
        errors = [pose_errors(p.float(), truth) for p in (estimate, refined.to(truth))]
        labels = gallery_labels(picked[EVAL.index], errors, accepted.cpu())
        self.curves(trainer, loggers, split)
        methods = self.refinement.refined.get(split)
        if methods is not None:
            truth_all = outputs[EVAL.pose].float()
            log_trajectories(
                trainer, split, truth_all, methods, outputs[EVAL.scene], pl_module.scene_names
            )
        names = pl_module.scene_names
        scenes = picked[EVAL.scene].cpu()
        for index in scenes.unique().tolist():
            mask = scenes == index
            title = f"{names[index]} ({split}): query | at the teacher's | at the refined pose"
            figure = gallery_figure(
                title,
                panels[mask],
                [labels[i] for i in mask.nonzero().flatten().tolist()],
                self.panel_px,
            )
            tag = f"{split}/render_compare/gallery/{names[index]}"
            log_figure(loggers, tag, figure, trainer.global_step)

    @staticmethod
    def curves(trainer: L.Trainer, loggers: list[TensorBoardLogger], split: str) -> None:
        """Cumulative error curves of the teacher and of each render-and-compare method,
        from the per-query files the refinement callback wrote (after its gate), as the
        image ``{split}/cumulative_errors``."""
        folder = Path(trainer.log_dir or "")
        position, orientation, scenes = read_query_errors(folder, split, (HONEST, ORACLE))
        if not position:
            return
        names = sorted(set(scenes))
        ids = torch.tensor([names.index(s) for s in scenes])
        title = f"{split} split, {len(ids)} queries"
        image = error_curves_figure(title, position, orientation, ids, names)
        log_figure(loggers, f"{split}/cumulative_errors", image, trainer.global_step)
