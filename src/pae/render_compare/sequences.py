"""Render-and-compare over query sequences. The frames of one walk lie close together (a
tenth of a metre apart on the synthetic benchmark, about a centimetre in 7-Scenes' test label
files, 0.4-0.8 m on Cambridge's streets): a frame that its APR's start left outside the
search's reach can be found from its neighbours' refined poses (:func:`propagate`), a frame
that alone lands off the walk stands out from those around it (:func:`median_filter`,
:func:`hampel_filter`), and a recording never leaves its scene (:func:`vote_scenes`).

None reads a pose: only which sequence each query belongs to (``sequences`` [B], any integer
ids) and, within a sequence, the order of its frames, which is their row order (label and
estimates files list each sequence's frames in order). Per-image refiners (NeFeS, this
refiner without these options) use neither."""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import torch
from torch import Tensor

from pae.core.geometry import normalize_quaternion
from pae.render_compare.gate import RenderCompareResult
from pae.render_compare.refiner import RenderCompareRefiner

WINDOW_FITS = ("median", "hampel")
HAMPEL_SPREADS = 3.0
"""A frame lies off its window (:func:`hampel_filter`) beyond this many robust spreads."""
MAD_TO_SD = 1.4826
"""The median absolute deviation of a normal sample times this: its standard deviation."""


@dataclasses.dataclass(frozen=True)
class SequenceOptions:
    """How render-and-compare uses the query sequences (both 0: each query on its own)."""

    passes: int = 0
    """Propagation passes after the refinement from the starts: in each, every query next to
    one whose pose changed in the pass before (in the first, every query) is refined again
    from that neighbour's pose, and the higher-scoring pose kept (:func:`propagate`)."""
    window: int = 0
    """The gated poses replaced by their median over this many frames centred on each (odd;
    0 or 1: none; :func:`median_filter`)."""
    vote_scene: bool = False
    """Each query refined in the scene most of its sequence's starts are in
    (:func:`vote_scenes`): a recording never leaves its scene."""
    fit: str = "median"
    """What the window does: ``median`` puts the per-component median of its frames in each
    pose's place (:func:`median_filter`), ``hampel`` only in the place of a pose that lies
    off it (:func:`hampel_filter`: a sharp frame keeps its own pose)."""

    def __post_init__(self) -> None:
        if self.fit not in WINDOW_FITS:
            raise ValueError(
                f"render_compare.sequence_fit must be one of {', '.join(WINDOW_FITS)}, "
                f"not {self.fit!r}"
            )
        if self.passes < 0:
            raise ValueError(f"render_compare.sequence_passes must be >= 0, not {self.passes}")
        if self.window < 0 or (self.window > 1 and self.window % 2 == 0):
            raise ValueError(f"render_compare.sequence_window must be 0 or odd, not {self.window}")

    @property
    def active(self) -> bool:
        return bool(self.passes) or self.window > 1 or self.vote_scene


class Sequences(NamedTuple):
    """The queries' sequences: ``ids`` [B] (any integer per query, each sequence's frames in
    row order) and how render-and-compare uses them (``options``)."""

    ids: Tensor
    options: SequenceOptions = SequenceOptions()


def vote_scenes(scenes: Tensor, sequences: Tensor) -> Tensor:
    """Scenes [B] -> each replaced by the scene most queries of its sequence (sequences [B])
    are in (a tie: the lowest scene index)."""
    _, recording = torch.unique(sequences, return_inverse=True)
    counts = torch.zeros(
        int(recording.max()) + 1 if len(recording) else 0,
        int(scenes.max()) + 1 if len(scenes) else 0,
        device=scenes.device,
    )
    counts.index_put_((recording, scenes), torch.ones_like(scenes, dtype=counts.dtype), True)
    return counts.argmax(1)[recording] if len(scenes) else scenes


def neighbour_rows(sequences: Tensor, scenes: Tensor, offset: int) -> Tensor:
    """Row [B] of each query's frame ``offset`` frames along its sequence (sequences [B],
    rows in frame order within each), or -1 where that frame is beyond the sequence's ends or
    was refined in another scene (scenes [B]: its pose lies in that scene's frame)."""
    order = torch.argsort(sequences, stable=True)
    place = torch.empty_like(order)
    place[order] = torch.arange(len(order), device=order.device)
    target = place + offset
    inside = (target >= 0) & (target < len(order))
    rows = order[target.clamp(0, max(len(order) - 1, 0))]
    same = inside & (sequences[rows] == sequences) & (scenes[rows] == scenes)
    return torch.where(same, rows, torch.full_like(rows, -1))


@torch.no_grad()
def propagate(
    refiner: RenderCompareRefiner,
    images: Tensor,
    intrinsics: Tensor,
    scenes: Tensor,
    result: RenderCompareResult,
    sequences: Tensor,
    passes: int,
) -> RenderCompareResult:
    """``result`` (of queries images [B, 3, H, W], intrinsics [B, 4] in scenes [B]) after up to
    ``passes`` propagation passes: each query whose previous or next frame changed pose in the
    pass before is refined from that frame's pose as it stands, and the refined pose replaces
    its own where it scores higher (scores at the finest level, each against a rendering at
    its own pose). Stops early when a pass changes nothing. A pass refines the queries started
    from their previous frames as one batch, then those started from their next frames; the
    draws are keyed by the query's row, the pass and the side (the batch changes no result).
    ``initial_score`` stays the start's."""
    n = len(scenes)
    device = result.poses.device
    sides = [neighbour_rows(sequences, scenes, offset) for offset in (-1, 1)]
    poses, score = result.poses.clone(), result.score.clone()
    changed = torch.ones(n, dtype=torch.bool, device=device)
    for index in range(passes):
        improved = torch.zeros_like(changed)
        for side, neighbour in enumerate(sides):
            rows = ((neighbour >= 0) & changed[neighbour.clamp_min(0)]).nonzero().flatten()
            if not len(rows):
                continue
            keys = (rows + n * (2 * index + side + 1)).cpu()
            found = refiner(
                images[rows], intrinsics[rows], poses[neighbour[rows]], scenes[rows], keys=keys
            )
            better = found.score > score[rows]
            kept = rows[better]
            poses[kept] = found.poses[better].to(poses.dtype)
            score[kept] = found.score[better].to(score.dtype)
            improved[kept] = True
        changed = improved
        if not changed.any():
            break
    return RenderCompareResult(poses, score, result.initial_score)


def median_filter(poses: Tensor, sequences: Tensor, scenes: Tensor, window: int) -> Tensor:
    """Poses [..., B, 7] -> each replaced by the per-component median of the poses of the
    ``window`` frames centred on it along its sequence (a frame beyond the sequence's ends or
    in another scene counts as its own pose; quaternions sign-aligned to its own and
    renormalised): a frame that alone lands off the walk takes its neighbours' path."""
    if window <= 1:
        return poses
    around, _ = _window(poses, sequences, scenes, window)
    return _median(around)


def _window(poses: Tensor, sequences: Tensor, scenes: Tensor, window: int) -> tuple[Tensor, Tensor]:
    """The poses [..., B, window, 7] of the ``window`` frames centred on each query along its
    sequence (one beyond its ends or in another scene: its own pose), each quaternion's sign
    that of the one nearest its own, and which of them are its neighbours' [B, window]."""
    half = window // 2
    rows = torch.stack(
        [neighbour_rows(sequences, scenes, offset) for offset in range(-half, half + 1)], 1
    )
    present = rows >= 0
    own = torch.arange(poses.shape[-2], device=poses.device)
    around = poses[..., torch.where(present, rows, own[:, None]), :]
    quaternions = around[..., 3:]
    aligned = (quaternions * poses[..., None, 3:]).sum(-1, keepdim=True) >= 0
    quaternions = torch.where(aligned, quaternions, -quaternions)
    return torch.cat([around[..., :3], quaternions], -1), present


def _median(around: Tensor) -> Tensor:
    """Poses [..., B, W, 7] (quaternions sign-aligned) -> their per-component median [..., B,
    7], the quaternion renormalised."""
    position = around[..., :3].median(-2).values
    return torch.cat([position, normalize_quaternion(around[..., 3:].median(-2).values)], -1)


def hampel_filter(poses: Tensor, sequences: Tensor, scenes: Tensor, window: int) -> Tensor:
    """Poses [..., B, 7] -> the :func:`median_filter`'s pose only where a frame's own lies off
    it (a Hampel filter): where its position's distance from the window's median position is
    more than ``HAMPEL_SPREADS`` × 1.4826 × the median of the window frames' distances from
    it, or its orientation's angle the same way; elsewhere its own pose. A walk whose frames
    are sharp keeps them (a hand-held camera's turns included), and a frame that alone lands
    off the walk takes its neighbours' path."""
    if window <= 1:
        return poses
    around, present = _window(poses, sequences, scenes, window)
    median = _median(around)
    apart = (around[..., :3] - median[..., None, :3]).norm(dim=-1)
    turned = (around[..., 3:] * median[..., None, 3:]).sum(-1).abs().clamp(max=1.0).acos()
    off = torch.zeros(poses.shape[:-1], dtype=torch.bool, device=poses.device)
    for distance in (apart, turned):
        spread = distance.masked_fill(~present, math.nan).nanmedian(-1).values
        own = distance[..., window // 2]
        off |= own > HAMPEL_SPREADS * MAD_TO_SD * spread
    return torch.where(off[..., None], median, poses)


def window_filter(
    poses: Tensor, sequences: Tensor, scenes: Tensor, options: SequenceOptions
) -> Tensor:
    """Poses [..., B, 7] through the window ``options`` name (:func:`median_filter` or
    :func:`hampel_filter`)."""
    fit = hampel_filter if options.fit == "hampel" else median_filter
    return fit(poses, sequences, scenes, options.window)
