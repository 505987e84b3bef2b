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
    from pae.core.errors import ConfigError
    from pae.data.datamodule import PoseDataModule

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
    from pae.core.errors import ConfigError
    from pae.data.datamodule import PoseDataModule

    with pytest.raises(ConfigError, match=r"data.crop_shift_px: .*not -1"):
        PoseDataModule(str(tmp_path), "train.csv", "test.csv", crop_shift_px=-1)


def _sky(poses: torch.Tensor, intrinsics: torch.Tensor, h: int, w: int) -> torch.Tensor:
    """Images [B, 3, h, w] (values 0..255, float) of a world at infinity: each pixel's colour
    a smooth function of its ray's world direction, so a turned camera's view is exactly a
    homography of the unturned one's."""
    from pae.core.camera import camera_rays

    _, directions = camera_rays(poses, intrinsics.expand(len(poses), 4), w, h)
    d = directions / directions.norm(dim=-1, keepdim=True)
    x, y, z = d.unbind(-1)
    channels = [torch.sin(5 * x + 2 * z), torch.cos(4 * y - 3 * x), torch.sin(3 * x * z + 4 * y)]
    rgb = (torch.stack(channels, -1) + 1) * 127.5
    return rgb.view(len(poses), h, w, 3).permute(0, 3, 1, 2)


def test_turned_crop_without_offset_is_the_centre_crop() -> None:
    from pae.data.transforms import turned_crops

    images = _batch()
    warped, turns = turned_crops(
        images, torch.tensor([40.0, 40.0, 23.5, 19.5]), 32, torch.zeros(6, 2)
    )
    top, left = (40 - 32) // 2, (48 - 32) // 2
    assert torch.allclose(warped, images[:, :, top : top + 32, left : left + 32].float(), atol=1e-3)
    assert torch.equal(turns, torch.zeros(6, 3))


def test_turned_crop_is_the_view_of_the_turned_camera() -> None:
    from pae.core.geometry import orientation_error_deg
    from pae.core.pose_sampling import perturb, perturb_poses
    from pae.data.transforms import turned_crops

    torch.manual_seed(0)
    h = w = 64
    intrinsics = torch.tensor([50.2, 50.2, 31.5, 31.5], dtype=torch.float64)
    poses = perturb_poses(torch.tensor([[0.0, 0, 0, 1, 0, 0, 0]]).repeat(8, 1), 1.0, 60.0).double()
    offsets = torch.tensor(
        [[4.0, 0], [-4, 0], [0, 4], [0, -4], [3, -2.5], [-1, 2], [4, 4], [0.5, 0]]
    )
    warped, turns = turned_crops(_sky(poses, intrinsics, h, w), intrinsics, 56, offsets)
    turned = perturb(poses, torch.cat([torch.zeros(8, 3), turns.double()], -1))
    expected = _sky(turned, intrinsics, h, w)[:, :, 4:60, 4:60]
    inner = (slice(None), slice(None), slice(6, -6), slice(6, -6))  # the corners of (4, 4)
    # reach past the image, where the warp repeats its edge
    error = (warped - expected)[inner].abs()
    shifted = torch.stack(
        [
            _sky(poses, intrinsics, h, w)[i, :, 4 + int(v) : 60 + int(v), 4 + int(u) : 60 + int(u)]
            for i, (u, v) in enumerate(offsets.round().tolist())
        ]
    )
    assert error.max() < 0.5, "the warp is the turned camera's view (bilinear error only)"
    assert error.mean() < 0.2 * (shifted - expected)[inner].abs().mean()
    angles = orientation_error_deg(turned[:, 3:], poses[:, 3:])
    tilt = (offsets / 50.2).norm(dim=-1)
    assert torch.allclose(angles.double(), torch.rad2deg(torch.atan(tilt)).double(), atol=1e-3)


def test_crop_turns_camera_turns_the_train_labels_only(tiny_root) -> None:
    from pae.core.geometry import orientation_error_deg
    from pae.synthetic.datamodule import SyntheticDataModule
    from tests.conftest import TINY

    torch.manual_seed(0)
    data = SyntheticDataModule(
        root=str(tiny_root), **TINY, crop=28, shorter_edge=32, crop_turns_camera=True, batch_size=8
    )
    data.setup()
    batch = next(iter(data.train_dataloader()))
    data.trainer = type("T", (), {"training": True})()
    out = data.on_after_batch_transfer(dict(batch), 0)
    assert out["image"].shape[-2:] == (28, 28)
    angles = orientation_error_deg(out["pose"][:, 3:], batch["pose"][:, 3:])
    assert (angles > 0).any() and (angles < 6.5).all()  # 2 px each way at f = 25 px
    assert torch.equal(out["pose"][:, :3], batch["pose"][:, :3])
    data.trainer = type("T", (), {"training": False})()
    assert torch.equal(data.on_after_batch_transfer(dict(batch), 0)["pose"], batch["pose"])


def test_crop_turns_camera_needs_one_camera(tiny_root, tmp_path) -> None:
    from pae.core.errors import ConfigError
    from pae.data.datamodule import PoseDataModule
    from pae.data.labels import read_labels
    from tests.conftest import FOCAL_CAMERA, with_focal_column

    data = PoseDataModule(str(tmp_path), "train.csv", "test.csv", crop_turns_camera=True)
    with pytest.raises(ConfigError, match=r"data.crop_turns_camera: needs data.camera"):
        data._one_train_camera()
    rows = len(read_labels(tiny_root / "labels" / "all_train.csv"))
    labels, test_labels = with_focal_column(tiny_root, tmp_path, np.linspace(20.0, 30.0, rows))
    several = PoseDataModule(
        str(tiny_root),
        str(labels),
        str(test_labels),
        shorter_edge=32,
        crop=28,
        camera=FOCAL_CAMERA,
        crop_turns_camera=True,
    )
    with pytest.raises(ConfigError, match=r"needs one camera for every train row; the focal col"):
        several.setup()


def test_crop_turns_camera_must_be_a_boolean(compose_train) -> None:
    """The data schema types the key: composing refuses a value that is not a boolean."""
    from hydra.errors import ConfigCompositionException

    with pytest.raises(ConfigCompositionException, match=r"data\.crop_turns_camera=maybe"):
        compose_train("data.crop_turns_camera=maybe")


def _with_orientation(encoded: bytes, orientation: int) -> bytes:
    """A JPEG's bytes with an EXIF APP1 segment (big-endian TIFF, one IFD entry: the
    orientation tag) after its start-of-image marker, as a phone camera writes it."""
    import struct

    entry = struct.pack(">HHIHH", 0x0112, 3, 1, orientation, 0)
    tiff = b"MM\x00\x2a" + struct.pack(">I", 8) + struct.pack(">H", 1) + entry + bytes(4)
    app1 = b"Exif\x00\x00" + tiff
    return encoded[:2] + b"\xff\xe1" + struct.pack(">H", len(app1) + 2) + app1 + encoded[2:]


def test_an_exif_turned_photo_is_refused_by_the_size_check_the_loader_and_check(
    tmp_path,
) -> None:
    """A landscape JPEG tagged EXIF orientation 6 (a phone's portrait photo), which OpenCV's
    IMREAD_COLOR turns and IMREAD_UNCHANGED does not: image_size, the loader and
    ``pae-data check`` refuse it alike, in one line naming the file and the command that
    bakes the turn in; untagged or tagged 1, both read the stored pixels."""
    import cv2

    from pae.data.exif import exif_orientation
    from pae.data.label_images import find_image_problems
    from pae.data.labels import LabelTable
    from pae.data.transforms import image_size

    bgr = np.zeros((24, 40, 3), np.uint8)
    bgr[:, :20] = 255
    encoded = cv2.imencode(".jpg", bgr)[1].tobytes()
    turned, upright = tmp_path / "portrait.jpg", tmp_path / "upright.jpg"
    turned.write_bytes(_with_orientation(encoded, 6))
    upright.write_bytes(_with_orientation(encoded, 1))
    assert exif_orientation(turned.read_bytes()) == 6 and exif_orientation(encoded) == 1
    # the hazard: one decoder turns the photo, the other does not
    assert cv2.imread(str(turned), cv2.IMREAD_COLOR).shape[:2] == (40, 24)
    assert cv2.imread(str(turned), cv2.IMREAD_UNCHANGED).shape[:2] == (24, 40)
    message = (
        rf"^{turned}: EXIF orientation 6 \(the stored pixels shown turned 90° clockwise\): "
        r".* bake the turn into the pixels with exiftran -ai FILE .*$"
    )
    with pytest.raises(ImageError, match=message) as size_error:
        image_size(str(turned))
    assert "\n" not in str(size_error.value)
    with pytest.raises(ImageError, match=message):
        load_image(str(turned), 24)
    table = LabelTable(
        ["s"] * 2,
        ["train"] * 2,
        [""] * 2,
        ["portrait.jpg", "upright.jpg"],
        np.tile([0, 0, 0, 1, 0, 0, 0], (2, 1)),
        source="l.csv",
    )
    [problem] = find_image_problems(table, tmp_path)
    assert problem.startswith("l.csv:2: EXIF orientation 6") and "'portrait.jpg'" in problem
    assert image_size(str(upright)) == (24, 40)
    assert load_image(str(upright), 24, (24, 40)).shape == (24, 40, 3)


def test_a_png_exif_chunk_is_read_too() -> None:
    """PNG's eXIf chunk (before the image data) holds the same TIFF block."""
    import struct
    import zlib

    import cv2

    from pae.data.exif import exif_orientation

    encoded = cv2.imencode(".png", np.zeros((4, 6, 3), np.uint8))[1].tobytes()
    tiff = _with_orientation(b"\xff\xd8", 8)[2 + 4 + 6 :]  # the TIFF block alone
    chunk = struct.pack(">I", len(tiff)) + b"eXIf" + tiff
    chunk += struct.pack(">I", zlib.crc32(b"eXIf" + tiff))
    idat = encoded.index(b"IDAT") - 4
    assert exif_orientation(encoded[:idat] + chunk + encoded[idat:]) == 8
    assert exif_orientation(encoded) == 1
