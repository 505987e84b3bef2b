"""The validation split carved from the train labels: whole train sequences held out per scene
(or, for a scene without enough sequences, the last fraction of its rows), so that model
selection never reads the test split."""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pae.core.errors import LabelError
from pae.data.labels import LabelTable

HeldOut = int | Sequence[str]
"""``data.val_sequences``: n (the last n train sequences of every scene, in numeric order), or
sequence names (``seq-06`` in every scene that has it, ``scene/seq`` in one)."""

CALIBRATION_ON_TEST = (
    "render_compare: the validation split is the test split (data.val_sequences=null, or "
    "data.val_labels the test labels), and render-and-compare would choose its gate, filters "
    "and scene rule on the test labels: hold out a validation split of the train labels "
    "(data.val_sequences=1, the last train sequence of each scene) or give data.val_labels=FILE"
)
"""Why a run with render-and-compare stops before any work when validation reads the test
split (the config check and the callback's setup say the same)."""


def validation_is_test(
    val_sequences: HeldOut | None, val_labels: str | Path | None, test_labels: str | Path | None
) -> bool:
    """Whether the validation split is the test split: no ``val_labels`` and ``val_sequences``
    None, or ``val_labels`` the test labels' file (the same file by its resolved path)."""
    if not val_labels:
        return val_sequences is None
    if test_labels is None:
        return False
    return Path(str(val_labels)).resolve() == Path(str(test_labels)).resolve()


def natural_key(name: str) -> list[int | str]:
    """Sort key that orders ``seq2`` before ``seq10`` (digit runs compare as numbers)."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)]


def _tail(rows: np.ndarray, fraction: float) -> np.ndarray:
    """The last ``ceil(fraction · n)`` of ``rows`` [n >= 2] (file order): at least one, never
    all."""
    count = min(max(1, int(np.ceil(fraction * len(rows)))), len(rows) - 1)
    return rows[len(rows) - count :]


def held_out_rows(
    table: LabelTable, sequences: HeldOut, fraction: float | None
) -> tuple[np.ndarray, list[str]]:
    """Which train rows form the validation split -> (mask [N] bool, one line per scene
    saying what it holds out).

    Per scene: with ``sequences`` an int n, its last n train sequences when it has more than
    n; with names, those of its sequences; a scene with too few sequences (or none named)
    falls back to the last ``fraction`` of its rows in file order (a contiguous block: nearby
    frames are alike); with ``fraction`` None it holds out nothing. A named sequence that no
    scene has, or a scene left without train rows, is a LabelError naming the file.
    """
    scene = np.asarray(table.scene)
    seq = np.asarray(table.seq)
    mask = np.zeros(len(table), dtype=bool)
    named = [] if isinstance(sequences, int) else [str(s) for s in sequences]
    held: list[str] = []
    for name in table.scene_names:
        rows = np.flatnonzero(scene == name)
        names = sorted({s for s in seq[rows] if s}, key=natural_key)
        if isinstance(sequences, int):
            chosen = names[-sequences:] if len(names) > sequences else []
        else:
            chosen = [s for s in names if s in named or f"{name}/{s}" in named]
        if chosen:
            picked = rows[np.isin(seq[rows], chosen)]
            what = f"{name}: sequence{'s' if len(chosen) > 1 else ''} {', '.join(chosen)}"
        elif fraction is not None and len(rows) > 1:
            picked = _tail(rows, fraction)
            what = f"{name}: its last rows (val_fraction={fraction:g})"
        else:
            held.append(f"{name}: nothing held out ({len(names)} train sequence(s))")
            continue
        if len(picked) == len(rows):
            raise LabelError(
                table.source, None, f"data.val_sequences holds out every train row of {name}"
            )
        mask[picked] = True
        held.append(f"{what}, {len(picked)} of {len(rows)} rows")
    known = set(seq) | {f"{a}/{b}" for a, b in zip(scene, seq, strict=True)}
    unknown = sorted(set(named) - known)
    if unknown:
        raise LabelError(
            table.source, None, f"data.val_sequences: no train rows of sequences {unknown}"
        )
    return mask, held


def scenes_short_of_sequences(table: LabelTable, sequences: HeldOut) -> dict[str, list[str]]:
    """With ``sequences`` an int n: the scenes with more than one train sequence but no more
    than n -> their sequences (natural order). held_out_rows gives them the fallback of a
    scene with one sequence (holding out all of theirs would leave no train rows), which the
    data module says in a warning: ``val_sequences=6`` may have meant ``[seq-06]``."""
    if not isinstance(sequences, int):
        return {}
    scene, seq = np.asarray(table.scene), np.asarray(table.seq)
    short = {}
    for name in table.scene_names:
        names = sorted({s for s in seq[scene == name] if s}, key=natural_key)
        if 1 < len(names) <= sequences:
            short[name] = names
    return short
