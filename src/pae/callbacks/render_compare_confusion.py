"""The scene confusion tables of a multi-scene teacher and of render-and-compare's scene
decision, after every refined evaluation: as figures and as a TensorBoard text table."""

from __future__ import annotations

import lightning as L

from pae.callbacks.render_compare import RenderCompareCallback
from pae.callbacks.tensorboard import tensorboard_loggers
from pae.lit.eval_outputs import EVAL, SceneModelEvaluation, collect_outputs
from pae.render_compare.confusion import confusion_figures, confusion_markdown, scene_confusion


class RenderCompareConfusion(L.Callback):
    """After ``refinement`` (the render-and-compare callback, listed before this one) refined
    a split of a teacher that predicts the scene: per method (``teacher`` and each
    render-and-compare method) the counts of queries by true and assigned scene, logged as
    ``{split}/{method}/scene_confusion/{true}/{assigned}`` and as the TensorBoard text
    ``{split}/scene_confusion``."""

    def __init__(self, refinement: RenderCompareCallback) -> None:
        super().__init__()
        self.refinement = refinement

    def on_validation_epoch_end(self, trainer: L.Trainer, pl_module: SceneModelEvaluation) -> None:
        self.log_tables(trainer, pl_module, "val")

    def on_test_epoch_end(self, trainer: L.Trainer, pl_module: SceneModelEvaluation) -> None:
        self.log_tables(trainer, pl_module, "test")

    def log_tables(self, trainer: L.Trainer, pl_module: SceneModelEvaluation, split: str) -> None:
        """Log the split's tables where its queries were refined."""
        names = pl_module.scene_names
        refinements = self.refinement.refinements.get(split)
        outputs = collect_outputs(trainer, pl_module)
        if refinements is None or outputs is None or len(names) < 2:
            return
        assigned = {"teacher": outputs[EVAL.scene_estimate]}
        assigned |= {method: found.scenes for method, found in refinements.items()}
        truth = outputs[EVAL.scene]
        tables = {method: scene_confusion(s, truth, len(names)) for method, s in assigned.items()}
        figures = {}
        for method, table in tables.items():
            figures |= confusion_figures(f"{split}/{method}", table, names)
        pl_module.log_dict(figures)
        text = confusion_markdown(tables, names)
        for logger in tensorboard_loggers(trainer):
            logger.experiment.add_text(f"{split}/scene_confusion", text, trainer.global_step)
