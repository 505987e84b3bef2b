"""The train images' fingerprint with its cache beside the data: a re-run reads no unchanged
image, hashes a changed or new one again, and gives the hash a run without the cache gives."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from pae.core.errors import ImageError
from pae.data import fingerprint
from pae.data.datamodule import PoseDataModule
from pae.data.fingerprint import CACHE_NAME, DigestCache, images_blake2b
from pae.data.labels import LabelTable


def _images(root: Path, count: int) -> LabelTable:
    """``count`` files of random bytes under ``root``, an hour old, and their label table."""
    rng = np.random.default_rng(0)
    paths = [f"seq-01/frame-{i:06d}.color.png" for i in range(count)]
    for path in paths:
        (root / path).parent.mkdir(parents=True, exist_ok=True)
        (root / path).write_bytes(rng.bytes(3000))
        _age(root / path, 3600)
    poses = np.tile([0.0, 0, 0, 1, 0, 0, 0], (count, 1))
    return LabelTable(["chess"] * count, ["train"] * count, ["seq-01"] * count, paths, poses)


def _age(path: Path, seconds: int) -> None:
    """Set ``path``'s modification time ``seconds`` before now."""
    stamp = int((os.path.getmtime(path) - seconds) * 1e9)
    os.utime(path, ns=(stamp, stamp))


@pytest.fixture
def hashed(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """The files whose every byte is read, in order, from the moment the fixture is used."""
    names: list[str] = []
    whole_file = fingerprint._whole_file

    def counted(handle):
        names.append(Path(handle.name).name)
        return whole_file(handle)

    monkeypatch.setattr(fingerprint, "_whole_file", counted)
    return names


def test_a_rerun_reads_only_the_images_that_changed(tmp_path: Path, hashed: list[str]) -> None:
    table = _images(tmp_path, 4)
    plain = images_blake2b(table, tmp_path)
    assert len(hashed) == 4
    assert images_blake2b(table, tmp_path, DigestCache.beside(tmp_path)) == plain
    assert len(hashed) == 8 and (tmp_path / CACHE_NAME).is_file()
    assert images_blake2b(table, tmp_path, DigestCache.beside(tmp_path)) == plain
    assert len(hashed) == 8, "no unchanged image read again"

    edited = tmp_path / table.img_path[1]
    edited.write_bytes(np.random.default_rng(9).bytes(3000))  # same size, a new mtime
    changed = images_blake2b(table, tmp_path, DigestCache.beside(tmp_path))
    assert hashed[8:] == [edited.name] and changed != plain
    assert changed == images_blake2b(table, tmp_path)
    del hashed[:]
    _age(tmp_path / table.img_path[2], 60)  # the same bytes at another time: read again
    assert images_blake2b(table, tmp_path, DigestCache.beside(tmp_path)) == changed
    assert hashed == [Path(table.img_path[2]).name]

    more = LabelTable.concat([table, _images(tmp_path / "more", 1)])
    more.img_path[-1] = f"more/{more.img_path[-1]}"
    del hashed[:]
    grown = images_blake2b(more, tmp_path, DigestCache.beside(tmp_path))
    assert hashed == ["frame-000000.color.png"], "only the new file hashed"
    assert grown == images_blake2b(more, tmp_path)

    (tmp_path / CACHE_NAME).write_text('{"blake2b": {"seq-01/frame-000000.color.png": [1')
    del hashed[:]
    assert images_blake2b(table, tmp_path, DigestCache.beside(tmp_path)) == changed
    assert len(hashed) == 4, "a broken cache: every file hashed again and the cache rewritten"
    assert images_blake2b(table, tmp_path, DigestCache.beside(tmp_path)) == changed
    assert len(hashed) == 4

    (tmp_path / table.img_path[3]).unlink()
    with pytest.raises(ImageError, match=r"frame-000003.*row:"):
        images_blake2b(table, tmp_path, DigestCache.beside(tmp_path))


def _module(root: Path, **kwargs) -> PoseDataModule:
    data = PoseDataModule(
        root=str(root),
        train_labels=str(root / "labels" / "all_train.csv"),
        test_labels=str(root / "labels" / "all_test.csv"),
        shorter_edge=32,
        crop=28,
        **kwargs,
    )
    data.setup()
    return data


def test_the_data_module_keeps_the_cache_beside_the_data_or_in_the_image_store(
    tiny_root: Path, tmp_path: Path, hashed: list[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    root = tmp_path / "data"
    shutil.copytree(tiny_root, root, ignore=shutil.ignore_patterns(CACHE_NAME))
    plain = images_blake2b(_module(root).tables["train"], root)
    images = len(hashed)
    assert _module(root).fingerprint()["train_images_blake2b"] == plain
    assert len(hashed) == 2 * images and (root / CACHE_NAME).is_file()
    assert _module(root).fingerprint()["train_images_blake2b"] == plain
    assert len(hashed) == 2 * images, "a later run reads no image"

    (root / CACHE_NAME).unlink()
    writable = os.access
    monkeypatch.setattr(os, "access", lambda path, mode: path != root and writable(path, mode))
    store = tmp_path / "store"
    for _ in range(2):
        data = _module(root, image_store=str(store))
        assert data.fingerprint()["train_images_blake2b"] == plain
    assert len(hashed) == 3 * images, "a read-only root: the cache in the image store"
    assert [p.name.startswith(".pae_fingerprint_cache.") for p in store.iterdir()] == [True]
    assert _module(root).fingerprint()["train_images_blake2b"] == plain
    assert len(hashed) == 4 * images and not (root / CACHE_NAME).exists(), "and else none"
