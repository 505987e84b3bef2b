"""Image + pose datasets over label tables, with an optional in-memory image cache."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor
from torch.utils.data import Dataset, default_collate

from pae.core.errors import ImageError, LabelError
from pae.data.image_store import ImageStore
from pae.data.label_images import odd_sizes, outside_root
from pae.data.labels import LabelTable
from pae.data.transforms import check_image_size, image_size, load_image, load_sized_image


class PoseDataset(Dataset):
    """Rows of a label table: `{"image": uint8 [3, H, W], "pose": [7], "scene": long, "index"}`.

    Images are read with OpenCV relative to `root` (a path escaping it is a LabelError) and
    must all have one size (ImageError naming the file otherwise: with the cache, the one of
    another size than most, as `pae-data check` reports; without, one of another size than
    the first image); they are resized so their shorter edge is `shorter_edge` px,
    a batch at a time on `workers` threads. With cache=True all images are decoded once, on
    first use (or `load`), into one uint8 tensor and a batch is a single indexing operation.
    """

    def __init__(
        self,
        table: LabelTable,
        root: str | Path,
        scene_names: list[str],
        shorter_edge: int,
        cache: bool = False,
        workers: int = 2,
        store: ImageStore | None = None,
    ) -> None:
        self.table = table
        self.root = Path(root)
        self.shorter_edge = shorter_edge
        self.poses = torch.as_tensor(table.poses, dtype=torch.float32)
        self.scenes = torch.as_tensor(table.scene_ids(scene_names), dtype=torch.long)
        outside = outside_root(table.img_path, self.root)
        if outside:
            i = outside[0]
            raise LabelError(
                table.source,
                table.file_line(i),
                f"image path escapes the root {root}: {table.img_path[i]!r}",
            )
        self.paths = [str(self.root / p) for p in table.img_path]
        self.image_size = image_size(self.paths[0]) if self.paths else None
        self.workers = max(1, workers)
        self.cache = cache
        self.store = store
        self._cached: Tensor | None = None

    def load(self) -> None:
        """Decode every image into the cache now (cache=True; done once)."""
        if self.cache and self._cached is None:
            self._cached = self._decode_all()

    def _decode_all(self) -> Tensor:
        """Every image -> uint8 [N, 3, H, W]; an image of another size than most is an
        ImageError naming it and its row."""
        with ThreadPoolExecutor(self.workers) as pool:
            loaded = list(pool.map(self._load_sized, self.paths))
        odd = odd_sizes({i: size for i, (_, size) in enumerate(loaded)})
        if odd:
            i = min(odd)
            where = f"{self.table.source or 'row'}:{self.table.file_line(i)}"
            raise ImageError(f"{self.paths[i]} ({where}): {odd[i]}")
        images = np.stack([image for image, _ in loaded])
        return torch.from_numpy(images).permute(0, 3, 1, 2).contiguous()

    @property
    def images(self) -> Tensor | None:
        """All images, uint8 [N, 3, H, W], with cache=True (decoded on first use); else None."""
        self.load()
        return self._cached

    def _decode(self, paths: list[str]) -> Tensor:
        """Decode images on `workers` threads (OpenCV releases the GIL) -> uint8 [N, 3, H, W]."""
        with ThreadPoolExecutor(self.workers) as pool:
            arrays = list(pool.map(self._load, paths))
        return torch.from_numpy(np.stack(arrays)).permute(0, 3, 1, 2).contiguous()

    def _load_sized(self, path: str) -> tuple[np.ndarray, tuple[int, int]]:
        """The image at ``path`` resized, and its (h, w) in the file."""
        if self.store is None:
            return load_sized_image(path, self.shorter_edge)
        return self.store.read(path, self.shorter_edge)

    def _load(self, path: str) -> np.ndarray:
        if self.store is None:
            return load_image(path, self.shorter_edge, self.image_size)
        image, file_size = self.store.read(path, self.shorter_edge)
        check_image_size(path, file_size, self.image_size)
        return image

    def __len__(self) -> int:
        return len(self.paths)

    def _image(self, index: int) -> Tensor:
        if self.images is not None:
            return self.images[index]
        return torch.from_numpy(self._load(self.paths[index])).permute(2, 0, 1)

    def __getitem__(self, index: int) -> dict[str, Tensor]:
        return {
            "image": self._image(index),
            "pose": self.poses[index],
            "scene": self.scenes[index],
            "index": torch.tensor(index),
        }

    def __getitems__(self, indices: list[int]) -> dict[str, Tensor]:
        idx = torch.as_tensor(indices, dtype=torch.long)
        if self.images is not None:
            images = self.images[idx]
        else:
            images = self._decode([self.paths[i] for i in indices])
        return {"image": images, "pose": self.poses[idx], "scene": self.scenes[idx], "index": idx}


def collate_batch(batch: Any) -> Any:
    """Collate for datasets that may already return whole batches from `__getitems__`."""
    return batch if isinstance(batch, dict) else default_collate(batch)
