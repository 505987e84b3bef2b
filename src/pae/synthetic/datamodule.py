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

RENDER_FOLDER = "data/synthetic"
"""Where datasets without an explicit ``root`` are rendered (relative to the working dir)."""


def default_root(
    scenes: int,
    train_frames: int,
    test_frames: int,
    size: int,
    render_seed: int,
    test_offset_m: float,
    poses: list[str] | None,
    train_lane_m: float = 0.5,
    yaw_stray_rad: float = 0.15,
    stray_m: float = 0.1,
    nuisances: synthetic.Nuisances | None = None,
    val_lane_m: float | None = None,
    val_walks: int = 0,
    surfaces: synthetic.SurfaceOptions | None = None,
    capture: synthetic.CaptureOptions | None = None,
) -> str:
    """The folder a synthetic dataset renders into: named by its settings, or, for
    ``poses``, by a digest of the label files' contents (so edited files render anew).
    ``nuisances`` that are on add a suffix naming them (``_light1_occl0.3…``), so do
    ``surfaces`` (``_plain0.3_repeat0.2_gloss0.3``) and ``capture`` (``_pipe1_jpeg75_x4``),
    a ``val_lane_m`` one naming it (``_val0``), validation walks their count (``_walks3``);
    off, the name is the one without them."""
    if poses:
        digest = hashlib.sha256()
        for path in poses:
            try:
                digest.update(Path(path).read_bytes())
            except OSError as err:
                raise LabelError(path, None, f"data.poses: cannot read ({err.strerror})") from None
        return f"{RENDER_FOLDER}/poses-{digest.hexdigest()[:12]}_px{size}_seed{render_seed}"
    return (
        f"{RENDER_FOLDER}/scenes{scenes}_train{train_frames}_test{test_frames}_px{size}"
        f"_seed{render_seed}_offset{test_offset_m:g}_lane{train_lane_m:g}"
        f"_yaw{yaw_stray_rad:g}_stray{stray_m:g}"
        f"{nuisances.folder_suffix() if nuisances is not None else ''}"
        f"{surfaces.folder_suffix() if surfaces is not None else ''}"
        f"{capture.folder_suffix() if capture is not None else ''}"
        f"{'' if val_lane_m is None else f'_val{val_lane_m:g}'}"
        f"{f'_walks{val_walks}' if val_walks else ''}"
    )


class SyntheticDataModule(PoseDataModule):
    """The synthetic benchmark, rendered under ``data/synthetic`` on first use, or the
    `pae-data synth` output at a given ``root``.

    Without ``poses``: the benchmark's rooms and routes (``scenes``, frames per scene, the
    lateral offsets of the test and train sequences from the route, ``test_offset_m`` and
    ``train_lane_m``, how far they stray from their lanes, ``stray_m``, and their yaw from
    the route's heading, ``yaw_stray_rad``; ``val_lane_m`` not None: the last train
    sequence's offset, so that the validation split walks between the lanes; ``val_walks``
    more validation sequences per scene walking where it walks, held out on top of
    ``val_sequences``, an integer then), and its
    nuisances, all off (0) by default:
    ``lighting_change`` (strength in ``[0, 1]`` of lighting and exposure changing between and
    within sequences), ``occluder_fraction`` (share of frames with a person-sized box in front
    of the camera), ``sensor_noise_std`` (extra Gaussian noise, std of values in ``[0, 1]``)
    and ``motion_blur_px`` (longest motion blur, px); see
    :mod:`pae.synthetic.nuisances`. Surfaces and capture of real data, all off by default:
    ``plain_surface_share``, ``repeated_surface_share`` and ``glossy_surface_share`` (shares
    of the surfaces plain-painted, periodic and glossy; :mod:`pae.synthetic.surfaces`),
    ``camera_pipeline`` (strength in ``[0, 1]`` of vignetting, gamma, auto-exposure and
    drifting exposure and white balance), ``jpeg_quality`` (0: off) and ``render_scale``
    (images stored that many times ``size``, downsampled to ``shorter_edge`` by the loaders);
    :mod:`pae.synthetic.capture`. With ``poses``
    (label files, e.g. a real dataset's train and test labels): one image per row at that
    row's pose, in a world built around them (``pae-data synth --poses``). ``root`` None
    picks a folder under ``data/synthetic`` named by these settings and renders into it when
    its label files are missing (a non-empty folder without them is an error, never
    overwritten). A given ``root`` is only read: without label files it is an error naming
    it, so a mistyped path never trains on freshly rendered data. The defaults are
    ``pae-data synth``'s (``pae.synthetic.DEFAULT_*``), the values of
    ``conf/data/synthetic.yaml``. With a given ``root``, ``train_frames`` and
    ``test_frames`` only describe it: None where its scenes hold different counts.
    """

    def __init__(
        self,
        root: str | None = None,
        scenes: int = synthetic.DEFAULT_SCENES,
        train_frames: int | None = synthetic.DEFAULT_TRAIN_FRAMES,
        test_frames: int | None = synthetic.DEFAULT_TEST_FRAMES,
        size: int = synthetic.DEFAULT_SIZE,
        render_seed: int = 0,
        test_offset_m: float = synthetic.DEFAULT_TEST_OFFSET_M,
        poses: list[str] | None = None,
        train_lane_m: float = 0.5,
        yaw_stray_rad: float = 0.15,
        stray_m: float = 0.1,
        lighting_change: float = 0.0,
        occluder_fraction: float = 0.0,
        sensor_noise_std: float = 0.0,
        motion_blur_px: float = 0.0,
        val_lane_m: float | None = None,
        val_walks: int = 0,
        plain_surface_share: float = 0.0,
        repeated_surface_share: float = 0.0,
        glossy_surface_share: float = 0.0,
        camera_pipeline: float = 0.0,
        jpeg_quality: int = 0,
        render_scale: int = 1,
        **kwargs: Any,
    ) -> None:
        poses = [str(p) for p in poses] if poses else None
        nuisances = synthetic.Nuisances(
            lighting_change, occluder_fraction, sensor_noise_std, motion_blur_px
        )
        surfaces = synthetic.SurfaceOptions(
            plain_surface_share, repeated_surface_share, glossy_surface_share
        )
        capture = synthetic.CaptureOptions(camera_pipeline, jpeg_quality, render_scale)
        if poses and nuisances.active:
            raise ValueError(
                "data.poses renders the given rows without nuisances: set lighting_change, "
                "occluder_fraction, sensor_noise_std and motion_blur_px to 0"
            )
        if poses and (surfaces.active or capture.active):
            raise ValueError(
                "data.poses renders the given rows with the plain surfaces and capture: set "
                "the *_surface_share settings, camera_pipeline and jpeg_quality to 0 and "
                "render_scale to 1"
            )
        if val_walks:
            held = kwargs.get("val_sequences", 1)
            if type(held) is not int or kwargs.get("val_labels"):
                raise ValueError(
                    f"data.val_walks={val_walks} holds its walks out on top of "
                    f"data.val_sequences: set it to an integer and data.val_labels to null, "
                    f"got {held!r}"
                )
            kwargs["val_sequences"] = held + val_walks
        self.renders_on_first_use = root is None
        if root is None:
            root = default_root(
                scenes,
                train_frames,
                test_frames,
                size,
                render_seed,
                test_offset_m,
                poses,
                train_lane_m,
                yaw_stray_rad,
                stray_m,
                nuisances,
                val_lane_m,
                val_walks,
                surfaces,
                capture,
            )
        labels = Path(root) / "labels"
        if kwargs.get("camera") is None:
            stored = size * render_scale
            camera = synthetic.PinholeCamera(stored)
            f, c = camera.focal_px, camera.principal_point
            kwargs["camera"] = {
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
            **kwargs,
        )
        self.poses = poses
        self.render_args = {
            "scenes": scenes,
            "train_frames": train_frames,
            "test_frames": test_frames,
            "size": size,
            "seed": render_seed,
            "test_offset_m": test_offset_m,
            "train_lane_m": train_lane_m,
            "yaw_stray_rad": yaw_stray_rad,
            "stray_m": stray_m,
            "lighting_change": lighting_change,
            "occluder_fraction": occluder_fraction,
            "sensor_noise_std": sensor_noise_std,
            "motion_blur_px": motion_blur_px,
            "val_lane_m": val_lane_m,
            "val_walks": val_walks,
            "plain_surface_share": plain_surface_share,
            "repeated_surface_share": repeated_surface_share,
            "glossy_surface_share": glossy_surface_share,
            "camera_pipeline": camera_pipeline,
            "jpeg_quality": jpeg_quality,
            "render_scale": render_scale,
        }

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
                    self.render_args["size"],
                    self.render_args["seed"],
                    required_splits=("train", "test"),
                    progress=progress,
                )
            else:
                written = synthetic.write_synthetic_dataset(
                    self.root, **self.render_args, progress=progress
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
        seed = self.render_args["seed"]
        if self.poses:
            from pae.data.labels import LabelTable, read_labels
            from pae.synthetic.poses import scenes_at_poses

            table = LabelTable.concat(read_labels(path) for path in self.poses)
            worlds = dict(zip(table.scene_names, scenes_at_poses(table, seed), strict=True))
        else:
            args = self.render_args
            surfaces = synthetic.SurfaceOptions(*(args[key] for key in synthetic.SURFACE_BOUNDS))
            worlds = {
                synthetic.scene_name(i): synthetic.dress_surfaces(
                    synthetic.make_scene(i, seed, args["test_offset_m"], args["train_lane_m"]),
                    surfaces,
                    synthetic.surface_seed(seed, i),
                )
                for i in range(args["scenes"])
            }
        return [worlds[name] for name in self.scene_names]
