"""Classical keypoints (OpenCV's SIFT or ORB, no weights) of batches of images, and mutual
nearest-neighbour matching with Lowe's ratio test batched over image pairs: what the
correspondence stage of render-and-compare and the scene model's triangulated depth share."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import cv2
import numpy as np
import torch
from torch import Tensor

from pae.core.threads import current_budget

DETECTORS = ("sift", "orb")


class Keypoints(NamedTuple):
    """Keypoints of ``B`` images, padded to ``K``: xy [B, K, 2] px, descriptors [B, K, D]
    (uint8 from :func:`detect`: SIFT's bytes, or ORB's 0/1 bits), count [B]."""

    xy: Tensor
    descriptors: Tensor
    count: Tensor

    @property
    def mask(self) -> Tensor:  # [B, K] real keypoints
        return torch.arange(self.xy.shape[1])[None] < self.count[:, None]


def _grey_uint8(images: Tensor) -> np.ndarray:
    """RGB [B, 3, H, W] in [0, 1] -> uint8 grey [B, H, W]."""
    grey = 0.299 * images[:, 0] + 0.587 * images[:, 1] + 0.114 * images[:, 2]
    return (grey.clamp(0, 1) * 255).round().to(torch.uint8).cpu().numpy()


def _detector(detector: str, keypoints: int, contrast: float) -> cv2.Feature2D:
    if detector == "sift":
        return cv2.SIFT_create(keypoints, contrastThreshold=contrast)
    fast = max(1, round(contrast * 500))
    return cv2.ORB_create(keypoints, edgeThreshold=15, patchSize=15, fastThreshold=fast)


def worker_threads() -> int:
    return max(1, current_budget().threads)


def detect(
    images: Tensor,
    detector: str = "sift",
    keypoints: int = 1000,
    contrast: float = 0.01,
    masks: Tensor | None = None,
) -> Keypoints:
    """Keypoints of RGB images [B, 3, H, W] in [0, 1], at most ``keypoints`` each (the
    strongest): ``detector`` one of :data:`DETECTORS`; ``contrast`` SIFT's contrast threshold
    (ORB's FAST threshold is ``contrast`` x 500 grey levels); ``masks`` [B, H, W] bool: only
    where True."""
    grey = _grey_uint8(images)
    allowed = None if masks is None else masks.to(torch.uint8).mul(255).cpu().numpy()
    binary = detector != "sift"

    def one(index: int) -> tuple[np.ndarray, np.ndarray]:
        mask = None if allowed is None else allowed[index]
        found, described = _detector(detector, keypoints, contrast).detectAndCompute(
            grey[index], mask
        )
        if described is None or not found:
            return np.zeros((0, 2), np.float32), np.zeros((0, 0), np.uint8)
        strength = np.array([k.response for k in found], np.float32)
        keep = np.argsort(-strength, kind="stable")[:keypoints]
        xy = np.array([found[i].pt for i in keep], np.float32)
        chosen = described[keep]
        if binary:
            return xy, np.unpackbits(chosen, axis=1)
        return xy, np.clip(np.rint(chosen), 0, 255).astype(np.uint8)  # SIFT's are whole bytes

    with ThreadPoolExecutor(worker_threads()) as pool:
        found = list(pool.map(one, range(len(grey))))
    size = max([len(xy) for xy, _ in found] + [1])
    dim = max([d.shape[1] for _, d in found] + [1])
    xy = torch.zeros(len(found), size, 2)
    descriptors = torch.zeros(len(found), size, dim, dtype=torch.uint8)
    count = torch.zeros(len(found), dtype=torch.long)
    for row, (points, described) in enumerate(found):
        xy[row, : len(points)] = torch.from_numpy(points)
        if len(points):
            descriptors[row, : len(points), : described.shape[1]] = torch.from_numpy(described)
        count[row] = len(points)
    return Keypoints(xy, descriptors, count)


def mutual_matches(
    query: Keypoints, reference: Keypoints, ratio: float, binary: bool
) -> tuple[Tensor, Tensor]:
    """For each query keypoint [B, K] the index [B, K] of its match among the reference's
    (mutual nearest neighbours passing the ratio test) and whether it has one [B, K]."""
    a, b = query.descriptors.float(), reference.descriptors.float()
    if binary:  # Hamming distances of 0/1 bits
        distance = a.sum(-1)[..., None] + b.sum(-1)[:, None] - 2 * a @ b.transpose(1, 2)
    else:
        distance = torch.cdist(a, b)
    far = torch.finfo(distance.dtype).max
    distance = distance.masked_fill(~reference.mask[:, None], far)
    distance = distance.masked_fill(~query.mask[..., None], far)
    if distance.shape[2] < 2:
        empty = torch.zeros(query.xy.shape[:2], dtype=torch.bool)
        return torch.zeros_like(empty, dtype=torch.long), empty
    two, nearest = distance.topk(2, dim=2, largest=False)
    back = distance.argmin(1)  # [B, M]: each reference keypoint's nearest query keypoint
    mutual = back.gather(1, nearest[..., 0]) == torch.arange(distance.shape[1])[None]
    passes = two[..., 0] < ratio * two[..., 1]
    return nearest[..., 0], mutual & passes & query.mask & (two[..., 0] < far)
