"""Poses of images from a finished run's checkpoints (`pae-localize`): the teacher's
estimates, optionally refined by render-and-compare against the run's scene model or by the
student's test-time refinements, read exactly as the run evaluated its test split."""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from torch import Tensor

from pae.apps.any_start import any_start_calibration as cached_calibration
from pae.apps.match_inputs import (
    MatchReader,
    configured_list,
    configured_matches,
    run_train_images,
)
from pae.apps.queries import Queries
from pae.core.camera import Intrinsics, resized_size
from pae.core.checkpoints import load_pae, load_scene_model
from pae.core.errors import CheckpointError, ConfigError, ImageError
from pae.core.geometry import pose_errors
from pae.core.provenance import DATA_RECORD
from pae.data.datamodule import PoseDataModule
from pae.data.dataset import PoseDataset
from pae.data.transforms import ImageTransform
from pae.lit.eval_outputs import EVAL, match_width
from pae.lit.scene_model import compare_queries
from pae.models.base import Latents
from pae.models.latents import compute_teacher_latents
from pae.render_compare import Calibration, CalibrationOptions, Sequences, refine
from pae.render_compare import Queries as CompareQueries
from pae.render_compare.calibration import scene_size, teacher_features
from pae.render_compare.correspondences import MatchQueries, TrainImages
from pae.render_compare.queries import recorded_match
from pae.render_compare.refiner import ACCEPT_ALL, BUILD_KEYS, refiner_defaults
from pae.render_compare.scene_decision import SceneRule
from pae.render_compare.scene_starts import latent_starts
from pae.render_compare.sequences import SequenceOptions
from pae.scene_model.base import SceneModel

TEACHER = "teacher"
RENDER_COMPARE = "render_compare"
STUDENT_METHODS = ("student", "refined", "knn_mean")
"""Methods of the student step's checkpoint besides the ``refine.alternatives`` by name."""
SAME_START_M = 2e-3
SAME_START_DEG = 0.2
"""Starts within these of the teacher's estimates are its estimates (a label file's rounding)."""


class Run(NamedTuple):
    """A finished run directory: its saved config, ``metrics.json`` (empty when absent) and
    the dataset root it read (``.hydra/data.yaml``; None when unrecorded)."""

    folder: Path
    config: DictConfig
    metrics: dict[str, Any]
    data_root: str | None

    @property
    def steps(self) -> list[str]:
        return list(self.config.stage.steps)

    def checkpoint(self, step: str, method: str) -> Path:
        """The last checkpoint of ``step`` (its given ``{step}_ckpt`` where it fitted none); a
        CheckpointError naming the run when it has neither (``method``: what needed it)."""
        folder = self.folder / step if len(self.steps) > 1 else self.folder
        path = folder / "checkpoints" / "last.ckpt"
        if not path.is_file() and self.config.get(f"{step}_ckpt"):
            path = Path(self.config.get(f"{step}_ckpt"))
        if step not in self.steps or not path.is_file():
            raise CheckpointError(
                f"{self.folder}: no {step} checkpoint ({path}), which {method} needs: the run's "
                f"steps are {self.steps}"
            )
        return path


def teacher_checkpoint(run: Run, method: str) -> Path | None:
    """The checkpoint whose teacher gives ``method``'s estimates: the student's for its
    methods, the scene model step's for render_compare (each keeps a copy of its teacher),
    else the teacher step's, else the first later step's; None for a run without a teacher
    (a scene_fit run: render_compare from another APR's starts only)."""
    step = {RENDER_COMPARE: "scene_model", TEACHER: None}.get(method, "student")
    if step is not None and step in run.steps:
        return run.checkpoint(step, method)
    carrying = [s for s in run.steps if s != "scene_fit"]
    if "teacher" in carrying:
        return run.checkpoint("teacher", method)
    return run.checkpoint(carrying[0], method) if carrying else None


def read_run(folder: str | Path) -> Run:
    """The run in ``folder`` (as ``pae-train`` leaves it, e.g. ``outputs/demo``)."""
    folder = Path(folder)
    saved = folder / ".hydra" / "config.yaml"
    if not saved.is_file():
        raise ConfigError(f"{folder}: not a pae-train run directory (no .hydra/config.yaml)")
    config = OmegaConf.load(saved)
    metrics_path = folder / "metrics.json"
    metrics = json.loads(metrics_path.read_text()) if metrics_path.is_file() else {}
    record = folder / ".hydra" / DATA_RECORD
    data_root = OmegaConf.load(record).get("root") if record.is_file() else None
    return Run(folder, config, metrics, data_root)


def methods_of(run: Run) -> list[str]:
    """The methods ``pae-localize`` can give for ``run``'s config (whether or not the run
    trained their steps): teacher, render_compare, the student's and its alternatives."""
    alternatives = list((run.config.get("refine") or {}).get("alternatives") or {})
    return [TEACHER, RENDER_COMPARE, *STUDENT_METHODS, *alternatives]


def data_module(run: Run, **overrides: Any) -> PoseDataModule:
    """The run's data module (not set up), reading the dataset root it recorded."""
    if run.data_root is not None:
        overrides = {"root": run.data_root, **overrides}
    return instantiate(run.config.data, **overrides)


def query_intrinsics(
    camera: Intrinsics | None,
    size: tuple[int, int],
    shorter_edge: int,
    crop: int | None,
    focal: np.ndarray | None = None,
    focal_px: float | None = None,
) -> Tensor:
    """Intrinsics [N, 4] (fx, fy, cx, cy in px) of N images of ``size`` (h, w) px on disk, as
    the teacher sees them (shorter edge resized to ``shorter_edge``, centre ``crop``; None:
    not cropped):
    ``camera`` (the run's ``data.camera``) scaled to that size, with a label file's focal
    lengths ``focal`` [N] (px at the camera's width) where given. ``focal_px``: the images'
    focal length in px at their size on disk instead (principal point: the camera's, else
    the image centre)."""
    h, w = size
    if focal_px is not None:
        centred = Intrinsics(1.0, 1.0, (w - 1) / 2, (h - 1) / 2, w, h)
        camera = (centred if camera is None else camera.resized(w, h)).with_focal(focal_px)
        focal = None
    if camera is None:
        raise ConfigError(
            "the run's data has no camera (data.camera): give --focal PX, the images' focal "
            "length in px"
        )
    on_disk = camera.resized(w, h)
    if crop is None:
        seen = on_disk.resized(*resized_size(w, h, shorter_edge))
    else:
        seen = on_disk.preprocessed(shorter_edge, crop)
    vectors = torch.tensor([seen.vector()], dtype=torch.float64)
    if focal is not None:
        vectors = vectors.repeat(len(focal), 1)
        scale = seen.fx / camera.fx
        vectors[:, :2] = torch.as_tensor(focal, dtype=torch.float64)[:, None] * scale
    return vectors.float()


class Estimates(NamedTuple):
    """The teacher's answer for every query: pose [N, 7] (unit quaternion), scene [N] it
    assigns, latents [N, 2d] ([z_x, z_q]); for render-and-compare, the query images [N, 3,
    h, w] in [0, 1] at its compare width and their intrinsics [N, 4] (else None), and for
    teachers that classify the scene its pose for every scene [N, S, 7], its latents for
    every scene [N, S, 2d] and its scene logits [N, S] (else None)."""

    pose: Tensor
    scene: Tensor
    latents: Tensor
    images: Tensor | None
    intrinsics: Tensor | None
    scene_poses: Tensor | None = None
    scene_latents: Tensor | None = None
    scene_logits: Tensor | None = None


def no_estimates(n: int) -> dict[str, Tensor]:
    """The placeholders of ``n`` queries where no teacher estimates them (a run without one,
    its starts from another APR): identity poses, scene 0, no latents."""
    pose = torch.zeros(n, 7)
    pose[:, 3] = 1.0
    scene = torch.zeros(n, dtype=torch.long)
    return {EVAL.estimate: pose, EVAL.scene_estimate: scene, "latents": torch.zeros(n, 0)}


@torch.no_grad()
def estimate(
    teacher: torch.nn.Module | None,
    queries: Queries,
    data: PoseDataModule,
    intrinsics: Callable[[tuple[int, int], np.ndarray | None], Tensor] | None,
    compare_width: int | None,
    batch_size: int,
    device: torch.device,
    progress: Callable[[int, int], None],
) -> Estimates:
    """The teacher's estimates of every query, a batch at a time, pre-processed as the run
    evaluated its test split (placeholders without a ``teacher``); ``intrinsics`` ((h, w)
    on disk, focal lengths of the rows or None -> [B, 4]): keep the images for
    render-and-compare at ``compare_width`` px."""
    table = queries.table
    dataset = PoseDataset(table, queries.root, table.scene_names, data.shorter_edge)
    if dataset.image_size is None:
        raise ImageError("no images to localise")
    teacher = None if teacher is None else teacher.to(device)
    transform = ImageTransform(data.crop, train=False).to(device)
    parts: list[dict[str, Tensor]] = []
    total = len(dataset)
    for start in range(0, total, batch_size):
        rows = list(range(start, min(start + batch_size, total)))
        images = transform(dataset.__getitems__(rows)["image"].to(device))
        part = no_estimates(len(rows))
        if teacher is not None:
            answer = teacher.estimate(images, torch.zeros(len(rows), dtype=torch.long).to(device))
            part = {
                EVAL.estimate: answer.pose.cpu(),
                EVAL.scene_estimate: answer.scene.cpu(),
                "latents": answer.latents.joint().cpu(),
            }
        if intrinsics is not None:
            focal = None if table.focal is None else table.focal[rows]
            rgb = ImageTransform.unnormalize_batch(images)
            vectors = intrinsics(dataset.image_size, focal).expand(len(rows), 4).to(device)
            small, vectors = compare_queries(rgb, vectors, compare_width)
            part |= {EVAL.image: small.cpu(), EVAL.intrinsics: vectors.cpu()}
            scene_poses = None if teacher is None else teacher.scene_poses(images)
            if scene_poses is not None:
                part[EVAL.scene_poses] = scene_poses.cpu()
                part["scene_latents"] = teacher.scene_latents(images).cpu()
                part[EVAL.scene_logits] = answer.latents.scene_logits.cpu()
        parts.append(part)
        progress(rows[-1] + 1, total)
    joined = {key: torch.cat([p[key] for p in parts]) for key in parts[0]}
    return Estimates(
        joined[EVAL.estimate],
        joined[EVAL.scene_estimate],
        joined["latents"],
        joined.get(EVAL.image),
        joined.get(EVAL.intrinsics),
        joined.get(EVAL.scene_poses),
        joined.get("scene_latents"),
        joined.get(EVAL.scene_logits),
    )


def render_compare_settings(run: Run) -> tuple[dict[str, Any], Calibration]:
    """RenderCompareRefiner's settings of the run (``render_compare.refiner``, with the
    steps it chose on val and applied at test where metrics.json records them) and the
    acceptance gate and scene rule it applied at test (as configured where unrecorded:
    ``auto`` then is margin 0, no floor, no scene check)."""
    config = run.config.render_compare
    configured = OmegaConf.to_container(config.refiner, resolve=True)
    assert isinstance(configured, dict)
    settings = refiner_defaults() | {
        name: value for name, value in configured.items() if name not in BUILD_KEYS
    }
    for name, default in settings.items():
        key = f"test/{RENDER_COMPARE}/{name}"
        if key in run.metrics:
            kind = int if isinstance(default, int) and not isinstance(default, bool) else float
            settings[name] = kind(run.metrics[key])

    def chosen(name: str, fallback: float) -> float:
        recorded = run.metrics.get(f"test/{RENDER_COMPARE}/{name}")
        if recorded is not None:
            return float(recorded)
        configured = config.get(name)
        return float(configured) if isinstance(configured, int | float) else fallback

    rule = SceneRule(
        chosen("scene_check_below", ACCEPT_ALL),
        chosen("scene_probe_scale", 0.0),
        chosen("scene_prior_weight", 0.0),
        chosen("scene_move_margin", 0.0),
    )
    gate = chosen("accept_margin", 0.0), chosen("accept_score", ACCEPT_ALL)
    match = recorded_match(run.metrics, f"test/{RENDER_COMPARE}")
    if match is None:  # unrecorded: the one configured stage, if any
        listed = configured_matches(run.config)
        match = CalibrationOptions(matches_from_val=listed).uncalibrated().match
    return settings, Calibration(*gate, scene=rule, match=match)


def compare_width(settings: dict[str, Any]) -> int:
    """The width (px) at which the refiner compares queries."""
    return int(settings.get("resolution", refiner_defaults()["resolution"]))


def scene_model_path(run: Run) -> Path:
    """The scene model the run's render-and-compare used: ``scene_model_ckpt`` when given, else
    the checkpoint of its scene_fit step, else of its scene_model step."""
    if run.config.get("scene_model_ckpt"):
        return Path(run.config.scene_model_ckpt)
    step = "scene_fit" if "scene_fit" in run.steps else "scene_model"
    return run.checkpoint(step, RENDER_COMPARE)


@torch.no_grad()
def split_queries(data: PoseDataModule, split: str, width: int | None) -> dict[str, Tensor]:
    """A labelled split's queries as render-and-compare takes them: ``image`` [N, 3, h, w]
    (RGB in [0, 1], pre-processed as evaluated, area-resized to ``width`` px wide),
    ``intrinsics`` [N, 4] at that size, the true ``pose`` [N, 7] and ``scene`` [N], in the
    split's order (``data`` set up)."""
    loader = data.val_dataloader() if split == "val" else data.test_dataloader()
    intrinsics = data.intrinsics(split)
    parts: dict[str, list[Tensor]] = {"image": [], "intrinsics": [], "pose": [], "scene": []}
    for batch in loader:
        rgb = ImageTransform.unnormalize_batch(data.preprocess(batch["image"], False))
        small, vectors = compare_queries(rgb, intrinsics[batch["index"]], width)
        parts["image"].append(small)
        parts["intrinsics"].append(vectors)
        parts["pose"].append(batch["pose"].float())
        parts["scene"].append(batch["scene"])
    return {key: torch.cat(value) for key, value in parts.items()}


def any_start_calibration(
    run: Run,
    model: SceneModel,
    settings: dict[str, Any],
    features: Any,
    device: torch.device,
    teacher: torch.nn.Module | None,
) -> tuple[Calibration, TrainImages | None]:
    """The gate, first steps and correspondence stage (among the run's
    ``render_compare.matches_from_val``) for starts from another APR, chosen on the run's
    validation split and kept in the run folder
    (:func:`pae.apps.any_start.any_start_calibration`), and the train views read for it
    (None: none read)."""
    data = data_module(run, cache_images=False)
    data.setup()
    if data.val_is_test or not len(data.datasets["val"]):
        raise ConfigError(
            f"{run.folder}: the run has no validation split held out of its train data "
            "(data.val_sequences), so no gate can be chosen for another APR's starts without "
            "reading test labels: --init-gate run keeps the run's own"
        )
    val = split_queries(data, "val", compare_width(settings))
    positions, _ = data.train_poses()
    size = scene_size(positions[:, :3].double())
    on_device = {key: value.to(device) for key, value in val.items()}
    checkpoint = (model, scene_model_path(run))
    matches = configured_matches(run.config)
    width = match_width(matches)
    read: list[TrainImages] = []

    def val_matching() -> MatchQueries:
        read.append(run_train_images((run.folder, run.config), data, width, teacher))
        images, intrinsics = data.images_at("val", width)
        return MatchQueries(images, intrinsics, read[0])

    stages = (matches, val_matching if width else None)
    filters = configured_list(run.config, "filters_from_val")
    shares = configured_list(run.config, "match_shares_from_val")
    chosen = cached_calibration(
        run.folder, checkpoint, on_device, size, settings, features, stages, filters, shares
    )
    return chosen, (read[0] if read else None)


def scene_starts(
    run: Run, teacher: torch.nn.Module, found: Estimates, device: torch.device
) -> Tensor:
    """Render-and-compare's starts [N, S, K, 7] in every scene for a multi-scene teacher's
    queries as the run's scene-model step made them (:func:`latent_starts`, from the run's
    train images, the validation rows held out)."""
    assert found.scene_poses is not None and found.scene_latents is not None
    data = data_module(run, cache_images=False)
    data.setup()
    store = {
        k: v.to(device) for k, v in compute_teacher_latents(teacher, data, device).tensors.items()
    }
    joint = torch.cat([store["z_x"], store["z_q"]], -1)
    poses, latents = found.scene_poses.to(device), found.scene_latents.to(device)
    return latent_starts(poses, latents, joint, store["pose"], store["scene"])


def are_estimates_of(starts: Tensor, estimates: Tensor) -> bool:
    """Whether starts [N, 7] are the estimates [N, 7] as a label file keeps them (within
    ``SAME_START_M`` and ``SAME_START_DEG``)."""
    position, orientation = pose_errors(starts.double(), estimates.double())
    return bool((position <= SAME_START_M).all() and (orientation <= SAME_START_DEG).all())


class Refined(NamedTuple):
    """Render-and-compare's answer for the queries: poses [N, 7], scenes [N], whether the
    gate accepted each refinement [N] (bool), the calibration applied, the seconds spent
    choosing it (0 where it was the run's or read back) and, where a correspondence stage
    ran, the shares of the queries whose keypoints gave a pose and whose kept refinement
    came from another start (None: no stage)."""

    poses: Tensor
    scenes: Tensor
    accepted: Tensor
    calibration: Calibration
    calibrate_s: float = 0.0
    stage_shares: tuple[float, float] | None = None


def render_compare(
    run: Run,
    teacher: torch.nn.Module | None,
    found: Estimates,
    device: torch.device,
    gate: str = "run",
    matching: MatchReader | None = None,
    recordings: tuple[Tensor, SequenceOptions] | None = None,
) -> Refined:
    """Render-and-compare of the queries against the run's scene model from ``found.pose``
    (the teacher's estimates, or another APR's; without a ``teacher`` only the latter),
    through ``gate``: ``run`` the gate, steps and scene decision the run chose on val for its
    teacher and applied at test (a multi-scene teacher's queries decided between scenes as
    in the run), ``any`` those chosen on the run's validation split for starts of any error
    scale (:func:`any_start_calibration`; in the scene given); ``matching``
    (:data:`MatchReader`): the correspondence stage the gate's calibration chose runs too;
    ``recordings``: each query's recording [N] (its frames in row order) and how the
    refinement uses them."""
    loaded = load_scene_model(scene_model_path(run), "scene_model_ckpt")
    settings, calibration = render_compare_settings(run)
    features = None
    if settings.get("score") == "features":
        if teacher is None:
            raise ConfigError(f"{run.folder}: score=features needs the run's teacher; it has none")
        features = teacher_features(teacher, run.config.render_compare.feature_layers)
    model = loaded.model.to(device)
    scene_poses = scene_logits = None
    calibrate_s = time.perf_counter()
    train = None
    if gate == "any":
        calibration, train = any_start_calibration(run, model, settings, features, device, teacher)
    elif teacher is not None and found.scene_poses is not None and found.scene_logits is not None:
        scene_poses = scene_starts(run, teacher, found, device)
        scene_logits = found.scene_logits.to(device)
    calibrate_s = time.perf_counter() - calibrate_s if gate == "any" else 0.0
    sequences = None
    if recordings is not None:
        sequences = Sequences(recordings[0].to(device), recordings[1])
    assert found.images is not None and found.intrinsics is not None
    queries = CompareQueries(
        found.images.to(device),
        found.intrinsics.to(device),
        found.scene.to(device),
        scene_poses=scene_poses,
        scene_logits=scene_logits,
        matching=None if matching is None else matching(calibration.match, train),
    )
    refined = refine(
        model,
        queries,
        found.pose.to(device),
        calibration,
        sequences,
        settings | {"features": features},
    )
    poses, scenes, accepted = refined.poses.cpu(), refined.scenes.cpu(), refined.accepted.cpu()
    shares = None
    if refined.matched is not None and refined.from_match is not None:
        shares = float(refined.matched.float().mean()), float(refined.from_match.float().mean())
    return Refined(poses, scenes, accepted, calibration, calibrate_s, shares)


def student_poses(run: Run, method: str, teacher: torch.nn.Module, found: Estimates) -> Tensor:
    """The poses [N, 7] of a student method (``student``, ``refined``, ``knn_mean`` or a
    ``refine.alternatives`` entry) with the run's student checkpoint and refine settings,
    retrieving among the run's train poses (the validation rows held out, as in the run)."""
    from pae.runs.inputs import check_data
    from pae.runs.trainer import refinement_callbacks

    path = run.checkpoint("student", method)
    pae = load_pae(path, "student_ckpt")
    if method == "student":
        with torch.no_grad():
            return teacher.regress(pae.model(found.pose, found.scene)).cpu()
    callbacks = refinement_callbacks(run.config)
    if not callbacks:
        raise ConfigError(f"{run.folder}: the run has no refinement (refine=none)")
    refinement = callbacks[0]
    data = data_module(run, cache_images=False)
    data.setup()
    check_data(run.config, path, pae, data)
    store = refinement.store(*data.train_poses())
    d = found.latents.shape[-1] // 2
    query = Latents(found.latents[:, :d], found.latents[:, d:])
    if method in refinement.alternatives:
        factory = refinement.alternatives[method]
        return factory(index=store, pae=pae.model)(query, found.pose, found.scene).poses
    refiner = refinement.refiner(pae.model, store)
    result = refiner(query, found.pose, found.scene)
    if method == "knn_mean":
        return refiner.neighbour_mean(result.neighbour_indices, found.pose)
    return result.poses
