"""PoseDataModule over the embedded synthetic benchmark, rendered on first use under
data/synthetic/ (a given ``root`` is read, never rendered into)."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

from pae import synthetic
from pae.core.console import Progress, say
from pae.core.errors import LabelError
from pae.data.datamodule import PoseDataModule
from pae.data.settings import PoseDataSettings
from pae.synthetic.settings import SYNTHETIC_LOADING, SyntheticSettings

RENDER_FOLDER = "data/synthetic"
"""Where datasets without an explicit ``root`` are rendered (relative to the working dir)."""


def default_root(settings: SyntheticSettings, poses: list[str] | None = None) -> str:
    """The folder a synthetic dataset renders into: named by its settings
    (:meth:`SyntheticSettings.folder_name`), or, for ``poses``, by a digest of the label
    files' contents (so edited files render anew) with its size and seed."""
    if poses:
        digest = hashlib.sha256()
        for path in poses:
            try:
                digest.update(Path(path).read_bytes())
            except OSError as err:
                raise LabelError(path, None, f"data.poses: cannot read ({err.strerror})") from None
        options = "".join(
            part.folder_suffix()
            for part in (settings.nuisances, settings.surfaces, settings.capture)
        )
        name = f"poses-{digest.hexdigest()[:12]}_px{settings.size}_seed{settings.seed}{options}"
        return f"{RENDER_FOLDER}/{name}"
    return f"{RENDER_FOLDER}/{settings.folder_name()}"


class SyntheticDataModule(PoseDataModule):
    """The synthetic benchmark, rendered under ``data/synthetic`` on first use, or the
    `pae-data synth` output at a given ``root``.

    ``settings``: the benchmark's (the names of
    :class:`~pae.synthetic.settings.SyntheticSettings`, its seed as ``render_seed``; their
    defaults there), and :class:`~pae.data.datamodule.PoseDataModule`'s. Without ``poses``:
    the benchmark's rooms, routes, nuisances, surfaces and capture. With ``poses`` (label
    files, e.g. a real dataset's train and test labels): one image per row at that row's pose,
    in a world built around them (``pae-data synth --poses``). ``root`` None picks a folder
    under ``data/synthetic`` named by the settings and renders into it when its label files
    are missing (a non-empty folder without them is an error, never overwritten). A given
    ``root`` is only read: without label files it is an error naming it, so a mistyped path
    never trains on freshly rendered data; ``train_frames`` and ``test_frames`` (per scene;
    None: the benchmark's) then only describe it (None where its scenes hold different
    counts).
    """

    settings_types = (SyntheticSettings, PoseDataSettings)
    """The settings it takes by name besides ``root``, ``poses`` and ``render_seed`` (the
    benchmark's seed)."""

    def __init__(
        self,
        root: str | None = None,
        poses: list[str] | None = None,
        render_seed: int = 0,
        train_frames: int | None = None,
        test_frames: int | None = None,
        **settings: Any,
    ) -> None:
        poses = [str(p) for p in poses] if poses else None
        settings = {**SYNTHETIC_LOADING, **settings}
        rendering = {
            name: settings.pop(name)
            for name in SyntheticSettings.names()
            if name != "seed" and name in settings
        }
        counts = {"train_frames": train_frames, "test_frames": test_frames}
        rendering |= {name: count for name, count in counts.items() if count is not None}
        self.render_settings = SyntheticSettings(**rendering, seed=render_seed)
        val_walks = self.render_settings.val_walks
        if val_walks:
            held = settings.get("val_sequences", 1)
            if type(held) is not int or settings.get("val_labels"):
                raise ValueError(
                    f"data.val_walks={val_walks} holds its walks out on top of "
                    f"data.val_sequences: set it to an integer and data.val_labels to null, "
                    f"got {held!r}"
                )
            settings["val_sequences"] = held + val_walks
        self.renders_on_first_use = root is None
        if root is None:
            root = default_root(self.render_settings, poses)
        labels = Path(root) / "labels"
        if settings["shorter_edge"] is None:
            settings["shorter_edge"] = self.render_settings.size
        if settings.get("camera") is None:
            stored = self.render_settings.size * self.render_settings.render_scale
            camera = synthetic.PinholeCamera(stored)
            f, c = camera.focal_px, camera.principal_point
            settings["camera"] = {
                "fx": f,
                "fy": f,
                "cx": c,
                "cy": c,
                "width": stored,
                "height": stored,
            }
        super().__init__(
            root=root,
            train_labels=str(labels / "all_train.csv"),
            test_labels=str(labels / "all_test.csv"),
            **settings,
        )
        self.poses = poses

    def prepare_data(self) -> None:
        if all(Path(p).is_file() for p in self.label_paths.values()):
            return
        if not self.renders_on_first_use:
            raise LabelError(
                self.label_paths["train"],
                None,
                f"no such file: data.root={self.root} is read, never rendered into "
                f"(`pae-data synth {self.root}` renders a dataset there; without data.root "
                f"the default benchmark renders under {RENDER_FOLDER}/)",
            )
        progress = Progress(f"rendering {self.root} (first use)", "frames", say)
        try:
            if self.poses:
                from pae.synthetic.poses import write_dataset_at_poses

                written = write_dataset_at_poses(
                    self.root,
                    self.poses,
                    self.render_settings.size,
                    self.render_settings.seed,
                    required_splits=("train", "test"),
                    progress=progress,
                    options=self.render_settings,
                )
            else:
                written = synthetic.write_synthetic_dataset(
                    self.root, self.render_settings, progress=progress
                )
        except FileExistsError as err:
            raise LabelError(
                self.label_paths["train"], None, f"file not found, and not rendered: {err}"
            ) from None
        for line in written.summary().splitlines():
            say(line)

    def setup(self, stage: str | None = None) -> None:
        self.prepare_data()
        super().setup(stage)

    def oracle_scenes(self) -> list[synthetic.SyntheticScene]:
        """The true scenes the images were rendered from, in ``scene_names`` order: what the
        ``oracle`` scene model renders (a bound that knows the scene, not a method)."""
        settings = self.render_settings
        seed = settings.seed
        if self.poses:
            from pae.data.labels import LabelTable, read_labels
            from pae.synthetic.poses import scenes_at_poses

            table = LabelTable.concat(read_labels(path) for path in self.poses)
            dressed = scenes_at_poses(table, seed, settings.surfaces)
            worlds = dict(zip(table.scene_names, dressed, strict=True))
        else:
            worlds = {
                synthetic.scene_name(i): synthetic.dress_surfaces(
                    synthetic.make_scene(i, seed, settings.test_offset_m, settings.train_lane_m),
                    settings.surfaces,
                    synthetic.surface_seed(seed, i),
                )
                for i in range(settings.scenes)
            }
        return [worlds[name] for name in self.scene_names]
