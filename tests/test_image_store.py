"""The on-disk store of decoded images: what it gives back equals a fresh decode, it decodes
each image once, and it never serves a stale or broken entry."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from pae.core.errors import ImageError
from pae.data import image_store
from pae.data.dataset import PoseDataset
from pae.data.image_store import ImageStore
from pae.data.labels import LabelTable
from pae.data.transforms import load_sized_image


def _write_image(path: Path, seed: int, size: tuple[int, int] = (48, 64)) -> None:
    rng = np.random.default_rng(seed)
    pixels = rng.integers(0, 256, (*size, 3), dtype=np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), pixels)


def _frames(folder: Path, count: int) -> tuple[list[str], LabelTable]:
    """``count`` random images written under ``folder`` and a train label table of them."""
    paths = [f"seq-01/frame-{i:06d}.color.png" for i in range(count)]
    for i, path in enumerate(paths):
        _write_image(folder / path, i)
    table = LabelTable(
        scene=["chess"] * count,
        split=["train"] * count,
        seq=["seq-01"] * count,
        img_path=paths,
        poses=np.tile([0.0, 0, 0, 1, 0, 0, 0], (count, 1)),
    )
    return paths, table


def test_a_stored_image_equals_a_fresh_decode_and_is_decoded_once(tmp_path, monkeypatch) -> None:
    picture = tmp_path / "a.png"
    _write_image(picture, 0)
    store = ImageStore(tmp_path / "store")
    image, size = store.read(str(picture), 24)
    fresh, fresh_size = load_sized_image(str(picture), 24)
    assert size == fresh_size == (48, 64)
    np.testing.assert_array_equal(image, fresh)
    assert image.shape == (24, 32, 3)

    def no_decode(path: str, shorter_edge: int) -> None:
        raise AssertionError("decoded again")

    monkeypatch.setattr(image_store, "load_sized_image", no_decode)
    again, again_size = store.read(str(picture), 24)
    np.testing.assert_array_equal(again, fresh)
    assert again_size == (48, 64)
    with pytest.raises(AssertionError, match="decoded again"):  # another size: another entry
        store.read(str(picture), 12)


def test_a_rewritten_image_or_a_broken_entry_is_decoded_anew(tmp_path) -> None:
    picture = tmp_path / "a.png"
    _write_image(picture, 0)
    store = ImageStore(tmp_path / "store")
    first, _ = store.read(str(picture), 24)
    entry = store.entry(str(picture), 24)
    entry.write_bytes(entry.read_bytes()[:-7])  # cut short, as by a full disk
    np.testing.assert_array_equal(store.read(str(picture), 24)[0], first)
    assert entry.stat().st_size == 16 + 24 * 32 * 3
    _write_image(picture, 1)
    stat = picture.stat()
    os.utime(picture, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
    rewritten, _ = store.read(str(picture), 24)
    np.testing.assert_array_equal(rewritten, load_sized_image(str(picture), 24)[0])
    assert not np.array_equal(rewritten, first)


def test_hard_links_get_entries_of_their_own_and_a_missing_image_is_named(tmp_path) -> None:
    picture = tmp_path / "a.png"
    _write_image(picture, 0)
    os.link(picture, tmp_path / "b.png")
    store = ImageStore(tmp_path / "store")
    assert store.entry(str(picture), 24) != store.entry(str(tmp_path / "b.png"), 24)
    with pytest.raises(ImageError, match=r"missing\.png"):
        store.read(str(tmp_path / "missing.png"), 24)


def test_a_dataset_reads_the_same_batches_through_a_store(tmp_path) -> None:
    paths, table = _frames(tmp_path, 5)
    plain = PoseDataset(table, tmp_path, ["chess"], 24)
    stored = PoseDataset(table, tmp_path, ["chess"], 24, store=ImageStore(tmp_path / "store"))
    for _ in range(2):  # the first read fills the store, the second reads it back
        batch = stored.__getitems__([4, 0, 2])["image"]
        assert torch.equal(batch, plain.__getitems__([4, 0, 2])["image"])
    cached = PoseDataset(
        table, tmp_path, ["chess"], 24, cache=True, store=ImageStore(tmp_path / "store")
    )
    assert torch.equal(cached.images, plain.__getitems__(list(range(5)))["image"])
    _write_image(tmp_path / paths[3], 3, size=(40, 64))
    with pytest.raises(ImageError, match="frame-000003"):
        stored.__getitems__([3])


def test_pae_data_store_fills_the_folder_once_and_names_a_missing_image(tmp_path, capsys) -> None:
    from pae.data_cli import main

    paths = [f"seq-01/frame-{i:06d}.color.png" for i in range(3)]
    for i, path in enumerate(paths):
        _write_image(tmp_path / path, i)
    labels = tmp_path / "chess_train.csv"
    rows = [f"chess,train,seq-01,{path},0,0,0,1,0,0,0" for path in paths]
    labels.write_text("scene,split,seq,img_path,t1,t2,t3,q1,q2,q3,q4\n" + "\n".join(rows) + "\n")
    command = [
        "store",
        str(labels),
        str(tmp_path),
        "--store",
        str(tmp_path / "s"),
        "--shorter-edge",
        "24",
    ]
    assert main(command) == 0
    assert "3 of 3 images decoded" in capsys.readouterr().out
    store = ImageStore(tmp_path / "s")
    for path in paths:
        image, _ = store.read(str(tmp_path / path), 24)
        np.testing.assert_array_equal(image, load_sized_image(str(tmp_path / path), 24)[0])
    assert main(command) == 0
    assert "0 of 3 images decoded" in capsys.readouterr().out
    (tmp_path / paths[1]).unlink()
    assert main(command) == 1
    assert "frame-000001.color.png: missing" in capsys.readouterr().err


def test_a_store_that_cannot_be_written_is_one_line_naming_the_setting(tmp_path) -> None:
    from pae.core.errors import ConfigError

    picture = tmp_path / "a.png"
    _write_image(picture, 0)
    (tmp_path / "taken").write_text("a file where the store's folder should be")
    with pytest.raises(ConfigError, match=r"^data\.image_store: cannot write .*taken"):
        ImageStore(tmp_path / "taken").read(str(picture), 24)
