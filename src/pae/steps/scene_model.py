"""The scene_model step: fit a scene model from the train images, poses and intrinsics, then
test render-and-compare refinement of a frozen teacher (`test/render_compare/...`); given a
fitted one (``scene_model_ckpt``: on the command line or from a scene_fit step), only the
test. And pae-eval's test of a scene-model checkpoint."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from pae.callbacks.render_compare_confusion import RenderCompareConfusion
from pae.callbacks.render_compare_gallery import RenderCompareGallery
from pae.callbacks.render_compare_init import RenderCompareFromFile
from pae.callbacks.scene_quality import SceneModelQuality
from pae.core.checkpoints import load_teacher
from pae.runs import Metrics
from pae.runs.hparams import log_hparams
from pae.runs.inputs import build_data, check_data, required
from pae.runs.scene import build_scene_model, evaluate_scene_model, fitting_module
from pae.runs.trainer import (
    build_trainer,
    collect_metrics,
    fit_and_test,
    render_compare_callback,
    validate_and_test,
)


def fit_scene_model(
    cfg: DictConfig,
    step_dir: Path,
    teacher_ckpt: str | Path | None,
    student_ckpt: str | Path | None = None,
    decoder_ckpt: str | Path | None = None,
    scene_model_ckpt: str | Path | None = None,
) -> tuple[Metrics, Path | None]:
    """Fit the configured scene model (one whose class ``trains``: its checkpoint is written
    with max_epochs=0 too; others are only built), then test render-and-compare from the
    teacher's estimates -> (metrics, the last checkpoint or None); with ``scene_model_ckpt``
    that model is tested and nothing is fitted (-> its checkpoint)."""
    checkpoints = {
        "teacher_ckpt": teacher_ckpt,
        "student_ckpt": student_ckpt,
        "decoder_ckpt": decoder_ckpt,
    }
    teacher_path = required(teacher_ckpt, "teacher_ckpt", "render_compare")
    teacher = load_teacher(teacher_path, "teacher_ckpt")
    images = build_data(cfg, augment=False)
    check_data(cfg, teacher_path, teacher, images)
    settings = cfg.scene_model
    quality = SceneModelQuality(settings.quality_size, settings.quality_images)
    if scene_model_ckpt is not None:
        metrics = evaluate_scene_model(
            cfg, step_dir, scene_model_ckpt, teacher, images, quality, "scene_model"
        )
        return metrics, Path(scene_model_ckpt)
    scene_model, configs = build_scene_model(cfg, images, checkpoints)
    callback = render_compare_callback(cfg)
    configs = {"teacher_config": teacher.config, **configs}
    module = fitting_module(cfg, images, scene_model, teacher.model, configs, callback.query_width)
    callbacks = [
        callback,
        RenderCompareConfusion(callback),
        RenderCompareFromFile(callback),
        RenderCompareGallery(callback),
        quality,
    ]
    if scene_model.trains:  # max_epochs=0: saved untrained
        metrics, last = fit_and_test(
            cfg, step_dir, "scene_model", module, images, settings.max_epochs, callbacks
        )
        return metrics | collect_metrics(module.trainer, ("bench/render_compare",)), last
    trainer = build_trainer(cfg, step_dir, 0, callbacks, step="scene_model")
    metrics = validate_and_test(trainer, module, images)
    metrics |= collect_metrics(trainer, ("bench/",))
    log_hparams(trainer, cfg, metrics)
    return metrics, None
