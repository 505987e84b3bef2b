"""Image operations of render-and-compare: grey levels, Gaussian and band-pass filtering,
and the (trimmed) zero-mean normalised cross-correlation the refiner scores with."""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator

import torch
import torch.nn.functional as F
from torch import Tensor

CONTRAST_FLOOR = 0.5
"""The local contrast's floor in :func:`band_pass`, as a share of the image's RMS: flat
regions (a plain wall) are not raised to the contrast of textured ones, where they would
compare noise."""
CONTRAST_EPSILON = 1e-3
"""Added to the local contrast (grey levels): an image with no texture at all stays flat
rather than its rounding errors raised to unit contrast."""


def grey(images: Tensor) -> Tensor:
    """RGB [B, 3, H, W] -> luma [B, 1, H, W] (ITU-R 601)."""
    weights = images.new_tensor([0.299, 0.587, 0.114]).view(1, 3, 1, 1)
    return (images * weights).sum(1, keepdim=True)


def clip_bright(images: Tensor, quantile: float) -> Tensor:
    """[B, C, H, W] with every value above its image's ``quantile`` (over its C·H·W values)
    lowered to it, so that highlights and saturated patches become flat; 0: unchanged."""
    if not quantile:
        return images
    ceiling = images.flatten(1).quantile(quantile, dim=1)
    return torch.minimum(images, ceiling.view(-1, *[1] * (images.dim() - 1)))


@contextlib.contextmanager
def float32_arithmetic() -> Iterator[None]:
    """A context in which convolutions and matrix products keep float32 on every device: no
    TF32, which cuDNN uses for convolutions by default on Ampere and later GPUs and matrix
    products use where ``torch.set_float32_matmul_precision`` allows it. The band-pass
    subtracts two blurs of the same image, and a 10-bit mantissa in each moved the refiner's
    scores on an H200 by up to 0.08 against the CPU's (experiments/bench/README.md)."""
    precision = torch.get_float32_matmul_precision()
    cudnn = torch.backends.cudnn
    try:
        torch.set_float32_matmul_precision("highest")
        with cudnn.flags(
            enabled=cudnn.enabled,
            benchmark=cudnn.benchmark,
            deterministic=cudnn.deterministic,
            allow_tf32=False,
        ):
            yield
    finally:
        torch.set_float32_matmul_precision(precision)


def gaussian_blur(images: Tensor, sigma_px: float) -> Tensor:
    """Separable Gaussian blur of [B, C, H, W] (σ in px; 0: unchanged), edges replicated, in
    float32 on every device (:func:`float32_arithmetic`)."""
    if sigma_px <= 0:
        return images
    radius = max(1, math.ceil(3 * sigma_px))
    x = torch.arange(-radius, radius + 1, dtype=images.dtype, device=images.device)
    kernel = torch.exp(-0.5 * (x / sigma_px) ** 2)
    kernel = kernel / kernel.sum()
    c = images.shape[1]
    padded = F.pad(images, (radius, radius, radius, radius), mode="replicate")
    with float32_arithmetic():
        rows = F.conv2d(padded, kernel.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
        return F.conv2d(rows, kernel.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)


def zncc(a: Tensor, b: Tensor, weights: Tensor) -> Tensor:
    """Weighted zero-mean normalised cross-correlation over the last dimension of a, b
    [..., P] with weights [..., P] >= 0 -> [...] in [-1, 1] (0 where a side is flat)."""
    total = weights.sum(-1, keepdim=True).clamp_min(1e-9)
    a = a - (weights * a).sum(-1, keepdim=True) / total
    b = b - (weights * b).sum(-1, keepdim=True) / total
    cov = (weights * a * b).sum(-1)
    var = (weights * a * a).sum(-1) * (weights * b * b).sum(-1)
    return cov / var.clamp_min(1e-12).sqrt()


def trimmed_zncc(
    a: Tensor, b: Tensor, weights: Tensor, trim_sigma: float, passes: int = 2
) -> Tensor:
    """ZNCC [...] of a, b [..., P] over the points the fit explains: ``passes`` times, after
    a weighted least-squares fit ``a ≈ gain·b + offset`` on the points kept so far, the
    points whose residual exceeds ``trim_sigma`` residual standard deviations (an occluder, a
    highlight) are dropped (of all points, so a point may come back). ``trim_sigma <= 0``:
    plain :func:`zncc`. The selection is not differentiated; the score is, through the kept
    points."""
    if trim_sigma <= 0 or passes < 1:
        return zncc(a, b, weights)
    kept = weights
    with torch.no_grad():
        for _ in range(passes):
            total = kept.sum(-1, keepdim=True).clamp_min(1e-9)
            mean_a = (kept * a).sum(-1, keepdim=True) / total
            mean_b = (kept * b).sum(-1, keepdim=True) / total
            cov = (kept * (a - mean_a) * (b - mean_b)).sum(-1, keepdim=True)
            var_a = (kept * (a - mean_a).square()).sum(-1, keepdim=True)
            var_b = (kept * (b - mean_b).square()).sum(-1, keepdim=True)
            gain = cov / var_b.clamp_min(1e-12)
            sigma = ((var_a - gain * cov).clamp_min(0) / total).sqrt()
            residual = (a - mean_a) - gain * (b - mean_b)
            kept = weights * (residual.abs() <= trim_sigma * sigma).to(weights.dtype)
    return zncc(a, b, kept)


def band_pass(
    images: Tensor, sigma_px: float, highpass_sigma_px: float, contrast_sigma_px: float = 0.0
) -> Tensor:
    """[B, C, H, W] blurred at ``sigma_px`` minus, when ``highpass_sigma_px`` > 0, its blur at
    that wider σ (a difference of Gaussians: smooth shading and light fall-off removed); when
    ``contrast_sigma_px`` > 0, divided by its local contrast (its RMS within that σ, px) plus
    ``CONTRAST_FLOOR`` × its RMS over the image, so that a region's structure counts alike
    whether vignetting, exposure or a highlight made it dim or bright there."""
    blurred = gaussian_blur(images, sigma_px)
    if highpass_sigma_px > 0:
        blurred = blurred - gaussian_blur(images, highpass_sigma_px)
    if contrast_sigma_px <= 0:
        return blurred
    local = gaussian_blur(blurred.square(), contrast_sigma_px).clamp_min(0).sqrt()
    whole = blurred.square().mean((-2, -1), keepdim=True).sqrt()
    return blurred / (local + CONTRAST_FLOOR * whole + CONTRAST_EPSILON)


def compare_size(height: int, width: int, compare_width: int) -> tuple[int, int]:
    """The (height, width) in px at which a query of ``height × width`` px is compared at
    ``compare_width`` (never wider than the query)."""
    width_px = min(compare_width, width)
    return max(4, round(height * width_px / width)), width_px


def pyramid_widths(resolution: int, levels: int, width: int) -> list[int]:
    """Compare widths (px), coarse to fine: the finest ``min(resolution, width)``, each level
    half the next (at least 8 px)."""
    finest = min(resolution, width)
    return [max(8, round(finest / 2**level)) for level in reversed(range(levels))]
