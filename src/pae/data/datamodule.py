"""LightningDataModule over label files: train / val / test splits of one or more scenes."""

from __future__ import annotations

import hashlib
import sys
from collections.abc import Callable, Iterable
from functools import partial
from pathlib import Path
from typing import Any

import lightning as L
import numpy as np
import torch
from lightning.pytorch.utilities import rank_zero_info, rank_zero_only
from torch import Tensor
from torch.utils.data import DataLoader

from pae.core.camera import Intrinsics, resized_size, scale_intrinsics
from pae.core.errors import ConfigError, LabelError
from pae.core.run_context import current_run
from pae.core.threads import loader_workers
from pae.data.converted import recording_of
from pae.data.dataset import PoseDataset, collate_batch
from pae.data.fingerprint import DigestCache, images_blake2b, sampled_images_sha256
from pae.data.holdout import (
    HeldOut,
    held_out_rows,
    scenes_short_of_sequences,
    validation_is_test,
)
from pae.data.image_store import ImageStore
from pae.data.labels import LabelTable, focal_column_mismatch, focal_problems, read_labels
from pae.data.order import EpochOrder, trainer_epoch
from pae.data.settings import PoseDataSettings
from pae.data.transforms import ImageTransform, image_size


class PoseDataModule(L.LightningDataModule):
    """Pose-labelled images from label files (see docs/usage.md, "Data") under `root`.

    The validation split: `val_labels` when given; otherwise rows held out of the train
    labels, neither trained on nor stored for retrieval (`train_poses`, the fingerprint):
    `val_sequences` whole train sequences per scene and, for scenes with too few sequences
    (or label files without them), the last `val_fraction` of their rows (pae.data.holdout).
    `val_sequences` None: validation reads the test split (said once on stderr), for
    comparisons with runs that had no validation split only (`val_is_test`; render-and-compare,
    which calibrates on validation, refuses it).
    Augmentation (random crop, its corner at most `crop_shift_px` from the centre crop's, +
    colour jitter) runs batched on the device after transfer,
    for training batches only when `augment` is true; evaluation uses the centre crop. With
    `crop_turns_camera` the random crop is the view of the camera turned towards the crop's
    centre instead (the homography of that pure rotation), its label turned with it: needs
    `camera`, one for every train row.
    `balance_scenes` samples scenes equally often in multi-scene training; each epoch's order
    is drawn from (`order_seed`, epoch) alone (the run's `seed`).
    `pose_loss_init` records the initial s_x, s_q of the learned pose loss that suit the
    dataset's error scale (the configs of the pose losses read it). `camera` gives the
    intrinsics of the images as stored (`fx, fy, cx, cy` in px, `width`, `height`; see
    pae.core.camera), which `intrinsics` carries through the loaders' resize and crop; None
    where unknown (render-and-compare then cannot run). `scenes` keeps only
    those scenes of the label files (None: all). With `cache_images`, setup decodes the
    val/test images (a bad image fails the run before training) and the train images are
    decoded when first loaded: a student whose teacher latents are cached never reads them.
    With an `image_store` folder each image is decoded and resized once and read back from
    there by every later epoch, step and run (pae.data.image_store).
    """

    settings_types = (PoseDataSettings,)
    """The settings it takes by name besides ``root`` and the label files."""

    def __init__(self, root: str, train_labels: str, test_labels: str, **settings: Any) -> None:
        s = PoseDataSettings.given(settings)
        super().__init__()
        self.order_seed = s.order_seed
        self.camera = Intrinsics(**s.camera) if s.camera else None
        self.crop = s.crop
        self.root = Path(root)
        self.label_paths = {"train": train_labels, "val": s.val_labels or test_labels}
        self.label_paths["test"] = test_labels
        carve = not s.val_labels and s.val_sequences is not None
        self.holdout = (s.val_sequences, s.val_fraction) if carve else None
        self.val_is_test = validation_is_test(s.val_sequences, s.val_labels, test_labels)
        """Whether validation reads the test split (render-and-compare then refuses to run)."""
        self.shorter_edge = s.shorter_edge
        self.batch_size = s.batch_size
        self.eval_batch_size = s.eval_batch_size
        self.num_workers = s.num_workers
        self.cache_images = s.cache_images
        self.image_store = ImageStore(s.image_store) if s.image_store else None
        self.balance_scenes = s.balance_scenes
        self.augment = s.augment
        self.pose_loss_init = dict(s.pose_loss_init or {})
        self.keep_scenes = list(s.scenes) if s.scenes else None
        try:
            self.train_transform = ImageTransform(
                s.crop,
                train=True,
                color_jitter=tuple(s.color_jitter),
                channel_gain=s.channel_gain,
                crop_shift_px=s.crop_shift_px,
            )
        except ValueError as err:  # its message starts with the key
            raise ConfigError(f"data.{err}") from None
        self.eval_transform = ImageTransform(s.crop, train=False)
        self.crop_turns_camera = s.crop_turns_camera
        self._turn_intrinsics: Tensor | None = None
        self.tables: dict[str, LabelTable] = {}
        self.datasets: dict[str, PoseDataset] = {}
        self.scene_names: list[str] = []
        self._fingerprint: dict[str, Any] | None = None
        self.train_batches: Callable[[PoseDataModule], DataLoader] | None = None
        """Another kind of train batch (a scene model's rays: ``pae.scene_model.rays.RayLoader``):
        called with this module, it gives the train loader; None: the train images."""

    def setup(self, stage: str | None = None) -> None:
        if self.datasets:
            return
        read = {
            path: self._keep_scenes(read_labels(path)) for path in set(self.label_paths.values())
        }
        self.tables = {split: read[path] for split, path in self.label_paths.items()}
        files = {id(table): table for table in self.tables.values()}.values()
        mismatch = focal_column_mismatch(files)
        if mismatch is not None:
            raise mismatch
        self._check_focal_lengths(files)
        self.scene_names = self.tables["train"].scene_names
        for table in self.tables.values():
            unknown = sorted(set(table.scene_names) - set(self.scene_names))
            if unknown:
                raise LabelError(
                    table.source,
                    None,
                    f"scenes {unknown} do not occur in the train labels "
                    f"{self.tables['train'].source}",
                )
        if self.holdout is not None:
            self._hold_out(*self.holdout)
        elif self.val_is_test:
            _warn_val_is_test()
        datasets: dict[int, PoseDataset] = {}
        for split, table in self.tables.items():
            if id(table) not in datasets:
                datasets[id(table)] = PoseDataset(
                    table,
                    self.root,
                    self.scene_names,
                    self.shorter_edge,
                    cache=self.cache_images,
                    store=self.image_store,
                )
            self.datasets[split] = datasets[id(table)]
        self.datasets["val"].load()
        self.datasets["test"].load()
        if self.crop_turns_camera and self.augment:
            self._turn_intrinsics = self._one_train_camera()

    def _one_train_camera(self) -> Tensor:
        """The train images' intrinsics [4] (fx, fy, cx, cy in px, as the dataset holds them)
        for ``crop_turns_camera``; ConfigError without ``camera`` or with several."""
        if self.camera is None:
            raise ConfigError(
                "data.crop_turns_camera: needs data.camera (fx, fy, cx, cy, width, height of "
                "the images as stored)"
            )
        rows = self.intrinsics("train", crop=False)
        if len(rows) and not torch.equal(rows, rows[:1].expand_as(rows)):
            raise ConfigError(
                f"data.crop_turns_camera: needs one camera for every train row; the focal "
                f"column of {self.tables['train'].source} gives several"
            )
        return rows[0] if len(rows) else torch.zeros(4)

    def _check_focal_lengths(self, tables: Iterable[LabelTable]) -> None:
        """LabelError at the first row whose focal length is implausible for the width of the
        images it refers to: ``data.camera``'s width, else that of the file's first image."""
        for table in tables:
            if table.focal is None or not len(table):
                continue
            if self.camera is not None:
                width = self.camera.width
            else:
                width = image_size(str(self.root / table.img_path[0]))[1]
            problems = focal_problems(table, width)
            if problems:
                first = min(problems)
                raise LabelError(table.source, table.file_line(first), problems[first])

    def _hold_out(self, sequences: HeldOut, fraction: float | None) -> None:
        """Move the held-out train rows into the val table (see pae.data.holdout)."""
        train = self.tables["train"]
        mask, held = held_out_rows(train, sequences, fraction)
        if not mask.any():
            raise LabelError(
                train.source,
                None,
                f"data.val_sequences={sequences} with data.val_fraction={fraction} holds out "
                "no train rows (set data.val_fraction, or give data.val_labels)",
            )
        self.tables["val"], self.tables["train"] = train.select(mask), train.select(~mask)
        rank_zero_info("validation split, held out of the train labels: " + "; ".join(held))
        short = scenes_short_of_sequences(train, sequences)
        if short:
            scene, names = next(iter(short.items()))
            instead = "nothing" if fraction is None else f"their last {100 * fraction:g} % of rows"
            rank_zero_info(
                f"data: warning: data.val_sequences={sequences} holds out the last {sequences} "
                f"train sequences of each scene, but {', '.join(short)} have no more than "
                f"{sequences} ({scene}: {names[0]} to {names[-1]}): they hold out {instead} "
                f"instead (data.val_sequences=[{names[-1]}] names a sequence)"
            )

    def _keep_scenes(self, table: LabelTable) -> LabelTable:
        if self.keep_scenes is None:
            return table
        missing = sorted(set(self.keep_scenes) - set(table.scene_names))
        if missing:
            raise LabelError(
                table.source, None, f"no rows of scenes {missing} (it has {table.scene_names})"
            )
        return table.select([i for i, s in enumerate(table.scene) if s in self.keep_scenes])

    @property
    def n_scenes(self) -> int:
        return len(self.scene_names)

    def scenes_without_rows(self, split: str) -> list[str]:
        """The train scenes that have no rows in `split` (val, test): its per-scene figures
        and their overall average leave them out."""
        present = set(self.tables[split].scene_names)
        return [scene for scene in self.scene_names if scene not in present]

    def train_poses(self) -> tuple[Tensor, Tensor]:
        """The train poses [N, 7] and scene ids [N] (the store for pose retrieval)."""
        dataset = self.datasets["train"]
        return dataset.poses, dataset.scenes

    def store_poses(self) -> tuple[Tensor, Tensor]:
        """The poses [N, 7] and scene ids [N] kNN refinement retrieves among: the train poses
        (a student's data module may add rendered views')."""
        return self.train_poses()

    def intrinsics(self, split: str, crop: bool = True) -> Tensor:
        """Intrinsics [N, 4] (fx, fy, cx, cy in px) of the split's images as the networks see
        them (resized, centre-cropped; ``crop=False``: resized only, as the dataset holds
        them): ``data.camera``, with a label file's ``focal`` column per row, carried through
        the images' size on disk, the loaders' resize and the crop. ConfigError when the data
        has no camera."""
        if self.camera is None:
            raise ConfigError(
                "data.camera is not set: render-and-compare needs the camera's intrinsics "
                "(fx, fy, cx, cy, width, height of the images as stored)"
            )
        dataset, table = self.datasets[split], self.tables[split]
        height, width = dataset.image_size or (self.camera.height, self.camera.width)
        stored = self.camera.resized(width, height)  # the images on disk may be another size
        if crop:
            seen = stored.preprocessed(self.shorter_edge, self.crop)
        else:
            seen = stored.resized(*resized_size(width, height, self.shorter_edge))
        vectors = torch.tensor([seen.vector()], dtype=torch.float64).repeat(len(table), 1)
        if table.focal is not None:  # per-row focal lengths (px at the camera's size)
            focal = torch.from_numpy(table.focal)
            vectors[:, 0] = focal * (seen.fx / self.camera.fx)
            vectors[:, 1] = focal * (seen.fy / self.camera.fy)
        return vectors.float()

    def images_at(self, split: str, width: int) -> tuple[Tensor, Tensor]:
        """The split's images resized (not cropped) to ``width`` px wide, uint8 [N, 3, H, W],
        and their intrinsics [N, 4] (px at that size), in the split's order: what a
        correspondence stage detects keypoints on (``pae.render_compare.correspondences``)."""
        dataset = self.datasets[split]
        height, stored_width = dataset.image_size or (self.camera.height, self.camera.width)
        shorter = round(width * min(height, stored_width) / stored_width)
        sized = PoseDataset(dataset.table, self.root, self.scene_names, shorter, cache=True)
        images = sized.images if len(sized) else torch.zeros(0, 3, shorter, width)
        assert images is not None
        own = self.intrinsics(split, crop=False)
        h, w = resized_size(stored_width, height, self.shorter_edge)[::-1]
        scale_x, scale_y = images.shape[-1] / w, images.shape[-2] / h
        return images, scale_intrinsics(own, scale_x, scale_y)

    def appearance_ids(self, split: str = "train", per: str = "sequence") -> tuple[Tensor, int]:
        """Index [N] of each row's appearance among the split's, and their count: what a
        scene model's appearance is keyed on. ``per``: ``sequence`` (one per scene and
        sequence) or ``image`` (one per row: exposure and light that drift within a
        sequence)."""
        table = self.tables[split]
        if per == "image":
            return torch.arange(len(table.scene)), len(table.scene)
        if per != "sequence":
            raise ConfigError(f"scene_model.appearance: unknown {per!r}; choose sequence or image")
        keys = [f"{scene}/{seq}" for scene, seq in zip(table.scene, table.seq, strict=True)]
        names = sorted(set(keys))
        index = {key: i for i, key in enumerate(names)}
        return torch.tensor([index[key] for key in keys], dtype=torch.long), len(names)

    def recording_ids(self, split: str) -> Tensor:
        """Index [N] of each row's recording among the split's (:func:`recording_of`: its
        image's folder, or the sequence an ACE-layout name holds), what the render-and-compare
        sequence options group queries by: a user's recording is where a frame came from,
        never a label column (the ``scene`` of a test row is its true scene)."""
        keys = [recording_of(path) for path in self.tables[split].img_path]
        index = {key: i for i, key in enumerate(dict.fromkeys(keys))}
        return torch.tensor([index[key] for key in keys], dtype=torch.long)

    def fingerprint(self) -> dict[str, Any]:
        """What identifies the training data: its scene names, a SHA-256 of its train poses
        (float64 [N, 7], as read from the train label file) and a BLAKE2b of its train images
        (:func:`pae.data.fingerprint.images_blake2b`: paths, sizes, every byte of each file),
        computed once; each file's BLAKE2b is kept beside the data (or in the image store
        where the root is read-only, :meth:`pae.data.fingerprint.DigestCache.beside`), so a
        later step or run hashes only the files that changed. Checkpoints record it."""
        if self._fingerprint is None:
            train = self.tables["train"]
            poses = np.ascontiguousarray(train.poses, dtype=np.float64)
            spare = None if self.image_store is None else self.image_store.folder
            cache = DigestCache.beside(self.root, spare)
            self._fingerprint = {
                "scenes": list(self.scene_names),
                "train_poses_sha256": hashlib.sha256(poses.tobytes()).hexdigest(),
                "train_images_blake2b": images_blake2b(train, self.root, cache),
            }
        return dict(self._fingerprint)

    def sampled_images_sha256(self) -> str:
        """The older hash of the train images that checkpoints written before recorded
        (:func:`pae.data.fingerprint.sampled_images_sha256`: 4 KiB of each file)."""
        return sampled_images_sha256(self.tables["train"], self.root)

    def describe(self) -> dict[str, Any]:
        """What this module reads: ``root``, ``scenes`` and, per split, its label file, the
        number of frames and the file's SHA-256 (``val`` only when it has its own file)."""
        tables = self.tables or {
            split: self._keep_scenes(read_labels(path)) for split, path in self.label_paths.items()
        }
        splits = {}
        for split, path in self.label_paths.items():
            if split == "val" and path == self.label_paths["test"]:
                continue
            splits[split] = {
                "labels": str(Path(path).resolve()),
                "frames": len(tables[split]),
                "sha256": hashlib.sha256(Path(path).read_bytes()).hexdigest(),
            }
        return {
            "root": str(self.root.resolve()),
            "scenes": list(tables["train"].scene_names),
            "splits": splits,
        }

    def _loader(self, dataset: PoseDataset, batch_size: int, **kwargs: Any) -> DataLoader:
        """A loader of ``dataset`` with its own generator (for its workers' seeds): making one
        draws nothing from torch's global generators; ``num_workers`` workers, at most the
        threads pae uses (pae.core.threads)."""
        dataset.load()  # here, once: loader workers get the decoded images
        workers = loader_workers(self.num_workers)
        return DataLoader(
            dataset,
            batch_size=batch_size,
            num_workers=workers,
            collate_fn=collate_batch,
            persistent_workers=workers > 0,
            generator=torch.Generator(),
            **kwargs,
        )

    def train_dataloader(self) -> DataLoader:
        """The train batches: the rows in the order of the epoch under way drawn from
        (``order_seed``, epoch) alone (:class:`pae.data.order.EpochOrder`; scenes drawn
        equally often with ``balance_scenes``), the last partial batch dropped."""
        if self.train_batches is not None:
            return self.train_batches(self)
        dataset = self.datasets["train"]
        weights = None
        if self.balance_scenes and self.n_scenes > 1:
            counts = torch.bincount(dataset.scenes, minlength=self.n_scenes).float()
            weights = (1.0 / counts)[dataset.scenes]
        epoch = partial(trainer_epoch, self)
        sampler = EpochOrder(len(dataset), self.order_seed, epoch, weights)
        return self._loader(dataset, self.batch_size, sampler=sampler, drop_last=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader(self.datasets["val"], self.eval_batch_size)

    def test_dataloader(self) -> DataLoader:
        return self._loader(self.datasets["test"], self.eval_batch_size)

    def train_eval_dataloader(self) -> DataLoader:
        """The train split in order, for evaluation-style passes (latent caching)."""
        return self._loader(self.datasets["train"], self.eval_batch_size)

    def preprocess(self, images: Tensor, train: bool) -> Tensor:
        """uint8 [B, 3, H, W] -> network input [B, 3, crop, crop] (see ImageTransform)."""
        transform = self.train_transform if train and self.augment else self.eval_transform
        return transform.to(images.device)(images)

    def on_after_batch_transfer(self, batch: Any, dataloader_idx: int) -> Any:
        image = batch.get("image") if isinstance(batch, dict) else None
        if image is not None and image.dtype == torch.uint8:
            training = self.trainer is not None and self.trainer.training
            if training and self._turn_intrinsics is not None:
                images, poses = self.train_transform.turned_batch(
                    image, batch["pose"], self._turn_intrinsics
                )
                return {**batch, "image": images, "pose": poses}
            batch = {**batch, "image": self.preprocess(image, training)}
        return batch


@rank_zero_only
def _warn_val_is_test() -> None:
    """Say once per run that the val split is the test split."""
    if current_run().first_time("val_is_test"):
        print(
            "pae: warning: data.val_sequences=null: validation reads the test split, so val/ "
            "figures are test figures",
            file=sys.stderr,
        )
