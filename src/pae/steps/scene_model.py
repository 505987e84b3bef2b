"""The scene_model step: fit a scene model from the train images, poses and intrinsics, then
test render-and-compare refinement of a frozen teacher (`test/render_compare/...`); and
pae-eval's test of a scene-model checkpoint."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from torch import Tensor

from pae.callbacks.render_compare_gallery import RenderCompareGallery
from pae.checkpoints import LoadedModel, load_decoder, load_pae, load_scene_model, load_teacher
from pae.data.rays import RayDataModule
from pae.errors import ConfigError
from pae.lit.scene_model import SceneModelModule
from pae.models.scene_model import PaeDecoderSceneModel, SceneModel
from pae.models.voxel_grid import camera_bounds
from pae.runs import Metrics
from pae.runs.hparams import log_hparams
from pae.runs.inputs import build_data, check_data, required
from pae.runs.trainer import (
    build_trainer,
    collect_metrics,
    fit_and_test,
    optimisation,
    validate_and_test,
)

SCENE_MODELS = ("voxel_grid", "pae_decoder", "oracle")


def camera_extent_m(positions: Tensor) -> float:
    """The largest side (m) of the box holding the middle 96 % of camera positions [N, 3]
    along each axis: the camera region's size, robust to a few stray frames."""
    if len(positions) < 2:
        return 0.0
    q = torch.tensor([0.02, 0.98], dtype=torch.float64)
    spread = positions.double().quantile(q, dim=0)
    return float((spread[1] - spread[0]).max())


def train_scale(data: Any, model: dict[str, Any], auto: Any) -> dict[str, Any]:
    """The voxel grid's bounds and contraction from the train cameras alone (never the
    scene's geometry): per scene the camera positions' bounds plus ``margin_m``, and
    ``contract``. ``margin_m: auto`` is ``max(auto.margin_floor_m, auto.margin_fraction ×
    extent)`` per scene (extent: :func:`camera_extent_m`); ``contract: auto`` contracts
    space when some scene's extent exceeds ``auto.contract_above_m`` (a street, not a room).
    Returns the model's config with ``bounds`` and ``contract`` set, and ``margin_m`` gone."""
    poses, scenes = data.train_poses()
    positions = [poses[scenes == s, :3] for s in range(data.n_scenes)]
    extents = [camera_extent_m(p) for p in positions]
    config = dict(model)
    margin = config.pop("margin_m")
    if margin == "auto":
        margins = [max(auto.margin_floor_m, auto.margin_fraction * e) for e in extents]
    else:
        margins = [margin] * len(positions)
    if config.get("contract") == "auto":
        config["contract"] = max(extents, default=0.0) > auto.contract_above_m
    pairs = zip(positions, margins, strict=True)
    config["bounds"] = [camera_bounds(p, m).tolist() for p, m in pairs]
    return config


def render_compare_callback(cfg: DictConfig) -> Any:
    """The callback of the `render_compare` group (refiner settings checked on creation)."""
    try:
        return instantiate(cfg.render_compare, _convert_="all")
    except Exception as err:  # an unknown or bad refiner option: one line
        message = " ".join(str(err).split())
        raise ConfigError(f"render_compare: {message[:300]}") from None


def build_scene_model(
    cfg: DictConfig, data: Any, ckpt: dict[str, str | Path | None]
) -> tuple[SceneModel, dict[str, Any]]:
    """The configured scene model and the config a checkpoint stores to rebuild it."""
    settings = cfg.scene_model
    name = settings.name
    if name == "voxel_grid":
        _, count = data.appearance_ids("train", settings.appearance)
        config = OmegaConf.to_container(settings.model, resolve=True)
        config = train_scale(data, config, settings.auto_scale)
        config["n_appearances"] = count
        return instantiate(config), {"scene_model_config": config}
    if name == "pae_decoder":
        student = required(ckpt["student"], "student_ckpt", "scene_model=pae_decoder")
        decoder_path = required(ckpt["decoder"], "decoder_ckpt", "scene_model=pae_decoder")
        pae, decoder = load_pae(student, "student_ckpt"), load_decoder(decoder_path, "decoder_ckpt")
        for path, loaded in ((student, pae), (decoder_path, decoder)):
            check_data(cfg, path, loaded, data)
        return PaeDecoderSceneModel(pae.model, decoder.model), {}
    if name == "oracle":
        from pae.callbacks.render_compare import oracle_scenes
        from pae.models.oracle_scene import OracleSceneModel

        scenes = oracle_scenes(data)
        if scenes is None:
            raise ConfigError(
                "scene_model=oracle renders the synthetic benchmark's true scenes; this data "
                "has none (use scene_model=voxel_grid)"
            )
        return OracleSceneModel(scenes), {}
    raise ConfigError(f"unknown scene_model.name {name!r}; choose one of {list(SCENE_MODELS)}")


def fit_scene_model(
    cfg: DictConfig,
    step_dir: Path,
    teacher_ckpt: str | Path | None,
    student_ckpt: str | Path | None = None,
    decoder_ckpt: str | Path | None = None,
) -> tuple[Metrics, Path | None]:
    """Fit the configured scene model (voxel_grid, whose checkpoint is written with
    max_epochs=0 too; pae_decoder and oracle have nothing to fit), then test
    render-and-compare from the teacher's estimates -> (metrics, the last checkpoint or
    None)."""
    ckpt = {"teacher": teacher_ckpt, "student": student_ckpt, "decoder": decoder_ckpt}
    teacher_path = required(ckpt["teacher"], "teacher_ckpt", "render_compare")
    teacher = load_teacher(teacher_path, "teacher_ckpt")
    images = build_data(cfg, augment=False)
    check_data(cfg, teacher_path, teacher, images)
    scene_model, configs = build_scene_model(cfg, images, ckpt)
    settings = cfg.scene_model
    callback = render_compare_callback(cfg)
    data = RayDataModule(
        images,
        settings.rays_per_batch,
        settings.batches_per_epoch,
        settings.image_size,
        settings.appearance,
    )
    module = SceneModelModule(
        scene_model,
        teacher.model,
        **optimisation(settings),
        scene_names=images.scene_names,
        configs={"teacher_config": teacher.config, **configs},
        tv_weight=settings.tv_weight,
        fit_trim=settings.fit_trim,
        fit_trim_from_epoch=settings.fit_trim_from_epoch,
        appearance_lr=settings.appearance_lr,
        quality_size=settings.quality_size,
        quality_images=settings.quality_images,
        query_width=callback.query_width,
    )
    callbacks = [callback, RenderCompareGallery(callback)]
    if settings.name == "voxel_grid":  # the one that trains; max_epochs=0: saved untrained
        metrics, last = fit_and_test(
            cfg, step_dir, "scene_model", module, data, settings.max_epochs, callbacks
        )
        return metrics | collect_metrics(module.trainer, ("bench/render_compare",)), last
    trainer = build_trainer(cfg, step_dir, 0, callbacks, step="scene_model")
    metrics = validate_and_test(trainer, module, data)
    metrics |= collect_metrics(trainer, ("bench/",))
    log_hparams(trainer, cfg, metrics)
    return metrics, None


def evaluate_scene_model(
    cfg: DictConfig, run_dir: Path, path: str | Path, teacher: LoadedModel, data: Any
) -> Metrics:
    """Test render-and-compare (the `render_compare` group's settings) with the scene model
    of checkpoint ``path`` from ``teacher``'s estimates on ``data`` (pae-eval)."""
    loaded = load_scene_model(path, "scene_model_ckpt")
    check_data(cfg, path, loaded, data)
    callback = render_compare_callback(cfg)
    module = SceneModelModule(
        loaded.model,
        teacher.model,
        optimizer=torch.optim.Adam,
        scene_names=data.scene_names,
        configs={"teacher_config": teacher.config, "scene_model_config": loaded.config},
        query_width=callback.query_width,
    )
    gallery = RenderCompareGallery(callback)
    trainer = build_trainer(cfg, run_dir / "render_compare", 0, [callback, gallery])
    metrics = validate_and_test(trainer, module, data)
    metrics |= collect_metrics(trainer, ("bench/",))
    log_hparams(trainer, cfg, metrics)
    return metrics
