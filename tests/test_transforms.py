import numpy as np
import pytest
import torch

from pae.data.transforms import IMAGENET_MEAN, IMAGENET_STD, ImageError, ImageTransform, load_image


def _batch(b: int = 6, h: int = 40, w: int = 48) -> torch.Tensor:
    return torch.randint(0, 256, (b, 3, h, w), dtype=torch.uint8)


def test_eval_transform_is_centre_crop_and_normalisation() -> None:
    images = _batch()
    out = ImageTransform(32, train=False)(images)
    top, left = (40 - 32) // 2, (48 - 32) // 2
    crop = images[:, :, top : top + 32, left : left + 32].float() / 255
    mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
    assert torch.allclose(out, (crop - mean) / std)


def test_train_crops_are_per_image_windows_of_the_input() -> None:
    torch.manual_seed(0)
    images = _batch(b=16)
    transform = ImageTransform(32, train=True, color_jitter=(0.0, 0.0, 0.0, 0.0))
    out = transform(images)
    assert out.shape == (16, 3, 32, 32)
    pixels = ImageTransform.unnormalize_batch(out)
    offsets = set()
    for b in range(16):  # each crop must be some 32x32 window of its own image
        windows = images[b].float().unfold(1, 32, 1).unfold(2, 32, 1) / 255  # [3, 9, 17, 32, 32]
        diff = (windows - pixels[b][:, None, None]).abs().amax(dim=(0, 3, 4))
        match = (diff < 1e-5).nonzero()
        assert len(match) >= 1
        offsets.add(tuple(match[0].tolist()))
    assert len(offsets) > 1, "crop offsets must differ between images"


def test_colour_jitter_differs_per_image() -> None:
    torch.manual_seed(0)
    one = _batch(b=1)
    images = one.repeat(8, 1, 1, 1)
    out = ImageTransform(40, train=True)(images)
    assert out.shape == (8, 3, 40, 40)
    per_image_mean = out.mean(dim=(1, 2, 3))
    assert per_image_mean.std() > 0.01


def test_channel_gain_scales_each_channel_by_its_own_factor_within_range() -> None:
    torch.manual_seed(0)
    grey = torch.full((64, 3, 8, 8), 128, dtype=torch.uint8)
    no_jitter = (0.0, 0.0, 0.0, 0.0)
    out = ImageTransform(8, train=True, color_jitter=no_jitter, channel_gain=0.2)(grey)
    gains = ImageTransform.unnormalize_batch(out).mean(dim=(2, 3)) / (128 / 255)  # [64, 3]
    assert gains.min() >= 0.8 - 1e-4 and gains.max() <= 1.2 + 1e-4
    assert (gains[:, 0] - gains[:, 1]).abs().max() > 0.05, "channels must differ (a tint)"
    assert gains.std(0).min() > 0.05, "factors must differ between images"
    plain = ImageTransform(8, train=True, color_jitter=no_jitter)(grey)
    assert torch.allclose(ImageTransform.unnormalize_batch(plain), grey.float() / 255, atol=1e-5)


def test_channel_gain_out_of_range_names_the_key(tmp_path) -> None:
    from pae.data.datamodule import PoseDataModule
    from pae.errors import ConfigError

    with pytest.raises(ConfigError, match=r"data.channel_gain: .*\[0, 1\), not 1.5"):
        PoseDataModule(str(tmp_path), "train.csv", "test.csv", channel_gain=1.5)


def test_crop_larger_than_image_is_a_clear_error() -> None:
    with pytest.raises(ImageError, match="smaller than the 64 px crop"):
        ImageTransform(64)(_batch())


def test_load_image_resizes_shorter_edge_and_converts_to_rgb(tmp_path) -> None:
    import cv2

    bgr = np.zeros((60, 90, 3), np.uint8)
    bgr[..., 0] = 255  # blue in OpenCV's BGR order
    path = tmp_path / "a.png"
    cv2.imwrite(str(path), bgr)
    rgb = load_image(str(path), 30)
    assert rgb.shape == (30, 45, 3)
    assert rgb[..., 2].min() == 255 and rgb[..., 0].max() == 0
    with pytest.raises(ImageError, match=r"missing\.png"):
        load_image(str(tmp_path / "missing.png"), 30)


def test_crop_shift_bounds_the_random_crop_around_the_centre() -> None:
    torch.manual_seed(0)
    columns = torch.arange(64, dtype=torch.uint8).expand(256, 3, 64, 64).contiguous()
    no_jitter = (0.0, 0.0, 0.0, 0.0)

    def corners(shift: int | None) -> torch.Tensor:
        out = ImageTransform(56, train=True, color_jitter=no_jitter, crop_shift_px=shift)
        rgb = ImageTransform.unnormalize_batch(out(columns))
        return (rgb[:, 0, 0, 0] * 255).round()

    assert set(corners(None).tolist()) == set(range(9)), "anywhere: every corner of 0..8"
    assert set(corners(2).tolist()) == {2.0, 3.0, 4.0, 5.0, 6.0}
    assert set(corners(0).tolist()) == {4.0}, "0: the centre crop"


def test_negative_crop_shift_names_the_key(tmp_path) -> None:
    from pae.data.datamodule import PoseDataModule
    from pae.errors import ConfigError

    with pytest.raises(ConfigError, match=r"data.crop_shift_px: .*not -1"):
        PoseDataModule(str(tmp_path), "train.csv", "test.csv", crop_shift_px=-1)
