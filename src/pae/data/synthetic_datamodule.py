"""PoseDataModule over the embedded synthetic benchmark, rendered on first use."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from lightning.pytorch.utilities import rank_zero_info

from pae.data.datamodule import PoseDataModule
from pae.data.labels import LabelError


class SyntheticDataModule(PoseDataModule):
    """Renders `pae-data synth` output into `root` when its label files are missing (a
    non-empty `root` without them is an error, never overwritten)."""

    def __init__(
        self,
        root: str,
        scenes: int = 2,
        train_frames: int = 800,
        test_frames: int = 250,
        size: int = 64,
        render_seed: int = 0,
        **kwargs: Any,
    ) -> None:
        labels = Path(root) / "labels"
        super().__init__(
            root=root,
            train_labels=str(labels / "all_train.csv"),
            test_labels=str(labels / "all_test.csv"),
            **kwargs,
        )
        self.render_args = {
            "scenes": scenes,
            "train_frames": train_frames,
            "test_frames": test_frames,
            "size": size,
            "seed": render_seed,
        }

    def prepare_data(self) -> None:
        if all(Path(p).is_file() for p in self.label_paths.values()):
            return
        from pae.data.synthetic import write_synthetic_dataset

        try:
            rank_zero_info(write_synthetic_dataset(self.root, **self.render_args).summary())
        except FileExistsError as err:
            raise LabelError(
                self.label_paths["train"], None, f"file not found, and not rendered: {err}"
            ) from None

    def setup(self, stage: str | None = None) -> None:
        self.prepare_data()
        super().setup(stage)
