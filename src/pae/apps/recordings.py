"""The recordings of pae-localize's queries (``--sequences``): which recording each image came
from, by the folder it sits in or by a column of the starts file, and each recording's frames
in order, for render-and-compare's sequence options (:mod:`pae.render_compare.sequences`)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import PurePosixPath
from typing import Any, NamedTuple, TypeVar

import torch
from torch import Tensor

from pae.core.errors import ConfigError, LabelError
from pae.data.converted import recording_of
from pae.data.starts import Starts, match_starts
from pae.render_compare.sequences import SequenceOptions

SOURCES = ("folders", "column")
"""Where ``--sequences`` reads each frame's recording: the folder the image sits in (and the
sequence an ACE-layout name holds, :func:`pae.data.converted.recording_of`), or the starts
file's ``seq`` column."""
T = TypeVar("T", bound=tuple)


class Recordings(NamedTuple):
    """Each query's recording: ``order`` [N], the rows that put every recording's frames
    together in frame order (by name); ``ids`` [N], the recording of each row in that order
    (an index into ``names``)."""

    order: Tensor
    ids: Tensor
    names: list[str]

    def restore(self, values: Tensor) -> Tensor:
        """``values`` [N, ...] in the recordings' order back in the queries' order."""
        restored = torch.empty_like(values)
        restored[self.order.to(values.device)] = values
        return restored


def recording_keys(
    images: Sequence[str], source: str, starts: Starts | None, starts_path: str
) -> list[str]:
    """The recording of each image path: its folder (``folders``) or the ``seq`` column of
    the starts file read from ``starts_path`` (``column``); a ConfigError where that file has
    no such column, and a LabelError naming the first frame without a recording where the
    column names some frames' recordings and not others'."""
    if source not in SOURCES:
        raise ConfigError(f"--sequences {source!r}: choose one of {SOURCES}")
    if source == "folders":
        return [recording_of(image) for image in images]
    if starts is None or starts.recordings is None:
        raise ConfigError(
            f"--sequences column: {starts_path or 'no --init FILE'} has no recording column "
            "(a pae label file's seq); --sequences folders takes the images' folders"
        )
    rows = match_starts(images, starts, starts_path)
    keys = [starts.recordings[row].strip() for row in rows]
    missing = [i for i, key in enumerate(keys) if not key]
    if missing and len(missing) < len(keys):
        first = int(rows[missing[0]])
        raise LabelError(
            starts_path,
            starts.lines[first],
            f"image {starts.names[first]} has no recording (seq) while "
            f"{len(keys) - len(missing)} other frames have one: give every frame's or none",
        )
    if missing:
        raise ConfigError(f"--sequences column: {starts_path} names no frame's recording (seq)")
    return keys


def recordings_of(
    images: Sequence[str], source: str, starts: Starts | None = None, starts_path: str = ""
) -> Recordings:
    """The recordings of ``images`` (:func:`recording_keys`), each one's frames ordered by
    their paths (a recording's frames named in the order they were taken: 7-Scenes'
    ``frame-000000``, a phone's ``IMG_0001``)."""
    keys = recording_keys(images, source, starts, starts_path)
    names = list(dict.fromkeys(keys))
    index = {key: i for i, key in enumerate(names)}
    order = sorted(range(len(images)), key=lambda i: (index[keys[i]], _frame_key(images[i])))
    ids = torch.tensor([index[keys[i]] for i in order], dtype=torch.long)
    return Recordings(torch.tensor(order, dtype=torch.long), ids, names)


def _frame_key(path: str) -> tuple[str, ...]:
    """A path's parts, compared folder by folder then by name."""
    return PurePosixPath(path.replace("\\", "/")).parts


def reordered(values: T, order: Tensor) -> T:
    """A NamedTuple of per-query tensors [N, ...] (or None) with its rows taken in ``order``."""
    return type(values)(*(None if v is None else v[order.to(v.device)] for v in values))


def sequence_options(
    run: Any, passes: int | None, window: int | None, fit: str | None = None
) -> SequenceOptions:
    """How ``--sequences`` refines each recording: ``passes``, ``window`` and ``fit`` where
    given, else the run's (passes and window as it recorded them at test, else as
    configured), and the run's scene vote; a ConfigError where neither uses the frames'
    order."""
    config = run.config.get("render_compare") or {}

    def chosen(name: str, given: int | None) -> int:
        if given is not None:
            return given
        recorded = run.metrics.get(f"test/render_compare/{name}")
        return int(recorded if recorded is not None else config.get(name, 0) or 0)

    try:
        options = SequenceOptions(
            chosen("sequence_passes", passes),
            chosen("sequence_window", window),
            bool(config.get("sequence_scene_vote", False)),
            fit or str(config.get("sequence_fit", "median")),
        )
    except ValueError as err:
        raise ConfigError(str(err).replace("render_compare.sequence_", "--sequence-")) from None
    if not options.passes and options.window <= 1:
        raise ConfigError(
            f"--sequences: {run.folder} uses no sequence passes or window: give "
            "--sequence-passes N (and --sequence-window W, odd)"
        )
    return options
