"""Batched image pre-processing on uint8 batches, run on the batch's device.

Per-sample random crops (or views of turned cameras, ``turned_crops``) and colour jitter are
drawn with tensor ops over the whole batch, so augmentation costs no Python loop per image.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from pae.core.errors import ImageError
from pae.core.geometry import quaternion_to_matrix, rotation_vector_to_quaternion
from pae.core.pose_sampling import perturb
from pae.data.exif import orientation_problem

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def read_image(path: str, flags: int) -> np.ndarray:
    """The image at ``path`` decoded by OpenCV with ``flags``, the pixels as stored (EXIF
    orientation ignored); ImageError naming ``path`` if it is missing or cannot be decoded, or
    if its EXIF orientation turns it (:func:`pae.data.exif.orientation_problem`): the size
    check and the loaders see one image."""
    try:
        data = np.fromfile(path, dtype=np.uint8)
        image = cv2.imdecode(data, flags | cv2.IMREAD_IGNORE_ORIENTATION)
    except (OSError, cv2.error):
        image = None
    if image is None:
        raise ImageError(f"{path}: missing or unreadable image")
    problem = orientation_problem(data)
    if problem:
        raise ImageError(f"{path}: {problem}")
    return image


def image_size(path: str) -> tuple[int, int]:
    """(h, w) in px of the image at `path` (ImageError as :func:`read_image`)."""
    image = read_image(path, cv2.IMREAD_UNCHANGED)
    return image.shape[0], image.shape[1]


def load_sized_image(path: str, shorter_edge: int) -> tuple[np.ndarray, tuple[int, int]]:
    """Read an image with OpenCV (:func:`read_image`, BGR -> RGB) and resize its shorter edge
    -> (uint8 [H, W, 3], the (h, w) in px it had in the file)."""
    image = read_image(path, cv2.IMREAD_COLOR)
    h, w = image.shape[:2]
    scale = shorter_edge / min(h, w)
    if scale != 1.0:
        size = (max(shorter_edge, round(w * scale)), max(shorter_edge, round(h * scale)))
        interpolation = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
        image = cv2.resize(image, size, interpolation=interpolation)
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB), (h, w)


def load_image(path: str, shorter_edge: int, size: tuple[int, int] | None = None) -> np.ndarray:
    """Read an image with OpenCV (BGR -> RGB) and resize its shorter edge -> uint8 [H, W, 3].

    `size` (h, w) in px: the size of the label file's first image, which every image must
    have (ImageError otherwise).
    """
    image, file_size = load_sized_image(path, shorter_edge)
    check_image_size(path, file_size, size)
    return image


def check_image_size(path: str, file_size: tuple[int, int], size: tuple[int, int] | None) -> None:
    """An ImageError naming ``path`` where its image's (h, w) ``file_size`` is not ``size``
    (the label file's first image's; None: any size)."""
    h, w = file_size
    if size is not None and (h, w) != tuple(size):
        raise ImageError(
            f"{path}: image is {w}x{h} px, unlike the {size[1]}x{size[0]} px of the label "
            "file's first image (all images of a label file must have one size; `pae-data "
            "check LABELS ROOT` names the odd ones)"
        )


def _gray(images: Tensor) -> Tensor:
    """[B, 3, H, W] -> luma [B, 1, H, W] (ITU-R 601)."""
    r, g, b = images.unbind(1)
    return (0.299 * r + 0.587 * g + 0.114 * b).unsqueeze(1)


def _rotate_hue(images: Tensor, turns: Tensor) -> Tensor:
    """Rotate the chroma of [B, 3, H, W] RGB images by `turns` [B] of a full turn (YIQ space)."""
    to_yiq = images.new_tensor(
        [[0.299, 0.587, 0.114], [0.596, -0.274, -0.322], [0.211, -0.523, 0.312]]
    )
    from_yiq = torch.linalg.inv(to_yiq)
    angle = 2 * math.pi * turns
    cos, sin = angle.cos(), angle.sin()
    one, zero = torch.ones_like(cos), torch.zeros_like(cos)
    rotation = torch.stack(
        [
            torch.stack([one, zero, zero], -1),
            torch.stack([zero, cos, -sin], -1),
            torch.stack([zero, sin, cos], -1),
        ],
        -2,
    )  # [B, 3, 3]
    matrix = from_yiq @ rotation @ to_yiq
    return torch.einsum("bij,bjhw->bihw", matrix, images)


def turned_crops(
    images: Tensor, intrinsics: Tensor, crop: int, offsets: Tensor
) -> tuple[Tensor, Tensor]:
    """Views of cameras turned so that each optical axis passes through the pixel ``offsets``
    [B, 2] (px; column, row) from the principal point of its image.

    images [B, C, H, W] (uint8 or float) of cameras with ``intrinsics`` [4] (fx, fy, cx, cy in
    px of H x W images) are warped by the homography of that pure rotation (exact for any
    scene; bilinear, edge pixels repeated) -> float [B, C, crop, crop] with the centre crop's
    intrinsics (offsets 0: the centre crop) and the turns [B, 3]: rotation vectors (rad) in the
    camera frame, the turned camera-to-world rotation ``R' = R · exp(turn)``.
    """
    h, w = images.shape[-2:]
    device = images.device
    fx, fy, cx, cy = intrinsics.to(device, torch.float64).unbind(-1)
    tangent = torch.stack([offsets[:, 0] / fx, offsets[:, 1] / fy], -1).double()  # [B, 2]
    tilt = tangent.norm(dim=-1, keepdim=True)
    per_tangent = torch.where(tilt > 0, torch.atan(tilt) / tilt.clamp_min(1e-12), 1.0)
    turns = torch.cat([-tangent[:, 1:], tangent[:, :1], torch.zeros_like(tilt)], -1) * per_tangent
    rotation = quaternion_to_matrix(rotation_vector_to_quaternion(turns))  # old from turned
    top, left = (h - crop) // 2, (w - crop) // 2
    steps = torch.arange(crop, device=device, dtype=torch.float64)
    x = ((steps + left - cx) / fx)[None, :].expand(crop, crop)
    y = ((steps + top - cy) / fy)[:, None].expand(crop, crop)
    rays = torch.stack([x, y, torch.ones_like(x)], -1)  # [crop, crop, 3], turned camera
    seen = torch.einsum("bij,hwj->bhwi", rotation, rays)
    u = fx * seen[..., 0] / seen[..., 2] + cx
    v = fy * seen[..., 1] / seen[..., 2] + cy
    grid = torch.stack([(2 * u + 1) / w - 1, (2 * v + 1) / h - 1], -1).float()
    warped = F.grid_sample(
        images.float(), grid, mode="bilinear", padding_mode="border", align_corners=False
    )
    return warped, turns.float()


class ImageTransform(nn.Module):
    """uint8 [B, 3, H, W] -> normalised float [B, 3, crop, crop].

    train=True: random crop (its corner at most ``crop_shift_px`` px from the centre crop's
    along each axis; None: anywhere in the image) plus per-image colour jitter (brightness,
    contrast, saturation factors drawn from [1 - j, 1 + j], hue shift from [-j_h, j_h] turns)
    and, with ``channel_gain`` g > 0, a white-balance jitter (each colour channel times a
    factor drawn from [1 - g, 1 + g], a tinted light or camera); train=False: centre crop only
    (the paper's test pre-processing, also used to train PAEs). ``turned_batch`` takes the
    random crop as a turn of the camera instead, and turns the labels with it.
    """

    def __init__(
        self,
        crop: int,
        train: bool = False,
        color_jitter: tuple[float, float, float, float] = (0.5, 0.5, 0.5, 0.2),
        channel_gain: float = 0.0,
        crop_shift_px: int | None = None,
    ) -> None:
        super().__init__()
        if not 0.0 <= channel_gain < 1.0:
            raise ValueError(f"channel_gain: must lie in [0, 1), not {channel_gain}")
        whole = isinstance(crop_shift_px, int) and not isinstance(crop_shift_px, bool)
        if crop_shift_px is not None and not (whole and crop_shift_px >= 0):
            raise ValueError(
                f"crop_shift_px: must be a whole number >= 0 or null, not {crop_shift_px!r}"
            )
        self.crop = crop
        self.train_mode = train
        self.color_jitter = tuple(float(v) for v in color_jitter)
        self.channel_gain = float(channel_gain)
        self.crop_shift_px = crop_shift_px

    def _corners(self, b: int, margin: int, device: torch.device) -> Tensor:
        """Random crop corners [b] along one axis with ``margin`` px of image to spare."""
        if self.crop_shift_px is None:
            return torch.randint(0, margin + 1, (b,), device=device)
        low = max(0, margin // 2 - self.crop_shift_px)
        high = min(margin, margin // 2 + self.crop_shift_px)
        return torch.randint(low, high + 1, (b,), device=device)

    def _offsets(self, b: int, h: int, w: int, device: torch.device) -> Tensor:
        """Crop centres' offsets [b, 2] (px; column, row) from the centre crop's, uniform within
        the random crop's range (``crop_shift_px`` or the image's margin)."""
        margins = torch.tensor([w - self.crop, h - self.crop], device=device) / 2
        if self.crop_shift_px is not None:
            margins = margins.clamp_max(self.crop_shift_px)
        return (2 * torch.rand(b, 2, device=device) - 1) * margins

    def turned_batch(
        self, images: Tensor, poses: Tensor, intrinsics: Tensor
    ) -> tuple[Tensor, Tensor]:
        """uint8 [B, 3, H, W] of cameras with ``intrinsics`` [4] (px of H x W) and their poses
        [B, 7] -> network input [B, 3, crop, crop] and poses [B, 7]: each image the view of its
        camera turned towards a random crop centre (:func:`turned_crops`, offsets within the
        random crop's range), colour-jittered, and its pose turned with it."""
        b, _, h, w = images.shape
        self._check_size(h, w)
        offsets = self._offsets(b, h, w, images.device)
        warped, turns = turned_crops(images, intrinsics, self.crop, offsets)
        steps = torch.cat([torch.zeros_like(turns), turns], -1).to(poses.dtype)
        images = self._jitter((warped / 255.0).clamp(0, 1))
        return self.normalize_batch(images), perturb(poses, steps)

    def _check_size(self, h: int, w: int) -> None:
        """ImageError for images of h x w px smaller than the crop."""
        if min(h, w) < self.crop:
            raise ImageError(f"images of {h}x{w} px are smaller than the {self.crop} px crop")

    def _crop(self, images: Tensor) -> Tensor:
        b, _, h, w = images.shape
        self._check_size(h, w)
        if not self.train_mode:
            top, left = (h - self.crop) // 2, (w - self.crop) // 2
            return images[:, :, top : top + self.crop, left : left + self.crop]
        top = self._corners(b, h - self.crop, images.device)
        left = self._corners(b, w - self.crop, images.device)
        offsets = torch.arange(self.crop, device=images.device)
        rows = (top[:, None] + offsets)[:, :, None]  # [B, crop, 1]
        cols = (left[:, None] + offsets)[:, None, :]  # [B, 1, crop]
        batch = torch.arange(b, device=images.device)[:, None, None]
        return images.permute(0, 2, 3, 1)[batch, rows, cols].permute(0, 3, 1, 2)

    def _jitter(self, images: Tensor) -> Tensor:
        b = images.shape[0]
        brightness, contrast, saturation, hue = self.color_jitter

        def factor(strength: float, channels: int = 1) -> Tensor:
            low = max(0.0, 1 - strength)
            draw = torch.empty(b, channels, 1, 1, device=images.device)
            return draw.uniform_(low, 1 + strength)

        if self.channel_gain > 0:
            images = images * factor(self.channel_gain, 3)
        images = (images * factor(brightness)).clamp(0, 1)
        mean_gray = _gray(images).mean(dim=(2, 3), keepdim=True)
        images = (mean_gray + factor(contrast) * (images - mean_gray)).clamp(0, 1)
        gray = _gray(images)
        images = (gray + factor(saturation) * (images - gray)).clamp(0, 1)
        if hue > 0:
            turns = torch.empty(b, device=images.device).uniform_(-hue, hue)
            images = _rotate_hue(images, turns).clamp(0, 1)
        return images

    @staticmethod
    def unnormalize_batch(images: Tensor) -> Tensor:
        """Network input [B, 3, h, w] -> RGB in [0, 1]."""
        mean = images.new_tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
        std = images.new_tensor(IMAGENET_STD).view(1, 3, 1, 1)
        return (images * std + mean).clamp(0, 1)

    @staticmethod
    def normalize_batch(images: Tensor) -> Tensor:
        """RGB in [0, 1] [B, 3, h, w] -> network input."""
        mean = images.new_tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
        std = images.new_tensor(IMAGENET_STD).view(1, 3, 1, 1)
        return (images - mean) / std

    def forward(self, images: Tensor) -> Tensor:
        images = self._crop(images).float() / 255.0
        if self.train_mode:
            images = self._jitter(images)
        return self.normalize_batch(images)
