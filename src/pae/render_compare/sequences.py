"""Render-and-compare over query sequences. The frames of one walk lie close together (a
tenth of a metre apart on the synthetic benchmark, about a centimetre in 7-Scenes' test label
files, 0.4-0.8 m on Cambridge's streets): a frame that its APR's start left outside the
search's reach can be found from its neighbours' refined poses (:func:`propagate`), a frame
that alone lands off the walk stands out from those around it (:func:`median_filter`), and a
recording never leaves its scene (:func:`vote_scenes`).

None reads a pose: only which sequence each query belongs to (``sequences`` [B], any integer
ids) and, within a sequence, the order of its frames, which is their row order (label and
estimates files list each sequence's frames in order). Per-image refiners (NeFeS, this
refiner without these options) use neither."""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import torch
from torch import Tensor

from pae.core.geometry import normalize_quaternion
from pae.render_compare.gate import RenderCompareResult
from pae.render_compare.refiner import RenderCompareRefiner


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

    def __post_init__(self) -> None:
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
    half = window // 2
    own = torch.arange(poses.shape[-2], device=poses.device)
    rows = torch.stack(
        [neighbour_rows(sequences, scenes, offset) for offset in range(-half, half + 1)], 1
    )
    rows = torch.where(rows >= 0, rows, own[:, None])
    around = poses[..., rows, :]  # [..., B, window, 7]
    position = around[..., :3].median(-2).values
    quaternions = around[..., 3:]
    aligned = (quaternions * poses[..., None, 3:]).sum(-1, keepdim=True) >= 0
    quaternions = torch.where(aligned, quaternions, -quaternions)
    return torch.cat([position, normalize_quaternion(quaternions.median(-2).values)], -1)
