"""The EXIF orientation of an image file (JPEG's APP1 segment, PNG's ``eXIf`` chunk).

A phone stores a portrait photo as landscape pixels and a tag saying how to turn them for
display. OpenCV's ``IMREAD_COLOR`` applies the tag, ``IMREAD_UNCHANGED`` does not, and a pose
or a camera calibrated on the stored pixels no longer fits turned ones: pae reads every image
with the tag ignored and refuses one whose tag turns it (:func:`orientation_problem`).
"""

from __future__ import annotations

import struct

import numpy as np

__all__ = ["BAKE_COMMAND", "exif_orientation", "orientation_problem"]

ORIENTATION_TAG = 0x0112
TURNS = {
    2: "mirrored",
    3: "turned 180°",
    4: "flipped upside down",
    5: "mirrored and turned 90° counter-clockwise",
    6: "turned 90° clockwise",
    7: "mirrored and turned 90° clockwise",
    8: "turned 90° counter-clockwise",
}
"""How a viewer shows the stored pixels under each EXIF orientation but 1 (as stored)."""
BAKE_COMMAND = "exiftran -ai FILE (or ImageMagick's mogrify -auto-orient FILE)"
"""A command that turns the pixels as the tag says and resets it."""
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _tiff_orientation(tiff: memoryview) -> int:
    """The orientation tag of an EXIF block's first IFD (1 where it has none)."""
    order = {b"II": "<", b"MM": ">"}.get(bytes(tiff[:2]))
    if order is None:
        return 1
    (ifd,) = struct.unpack_from(f"{order}I", tiff, 4)
    (count,) = struct.unpack_from(f"{order}H", tiff, ifd)
    for entry in range(ifd + 2, ifd + 2 + 12 * count, 12):
        tag, kind = struct.unpack_from(f"{order}HH", tiff, entry)
        if tag == ORIENTATION_TAG and kind == 3:  # SHORT
            (value,) = struct.unpack_from(f"{order}H", tiff, entry + 8)
            return value if value in TURNS else 1
    return 1


def _exif_block(data: memoryview) -> memoryview | None:
    """The EXIF (TIFF) block of a JPEG or PNG file's bytes, None where it has none."""
    if bytes(data[:2]) == b"\xff\xd8":  # JPEG: marker segments up to the scan
        offset = 2
        while offset + 4 <= len(data) and data[offset] == 0xFF:
            marker = data[offset + 1]
            if marker in (0xD9, 0xDA):  # end of image, start of scan
                return None
            if marker == 0xFF or 0xD0 <= marker <= 0xD7 or marker == 0x01:  # no length
                offset += 1 if marker == 0xFF else 2
                continue
            (length,) = struct.unpack_from(">H", data, offset + 2)
            segment = data[offset + 4 : offset + 2 + length]
            if marker == 0xE1 and bytes(segment[:6]) == b"Exif\x00\x00":
                return segment[6:]
            offset += 2 + length
    elif bytes(data[:8]) == _PNG_SIGNATURE:  # PNG: chunks up to the image data
        offset = 8
        while offset + 8 <= len(data):
            length, kind = struct.unpack_from(">I4s", data, offset)
            if kind in (b"IDAT", b"IEND"):
                return None
            if kind == b"eXIf":
                return data[offset + 8 : offset + 8 + length]
            offset += 12 + length
    return None


def exif_orientation(data: np.ndarray | bytes) -> int:
    """The EXIF orientation (1 to 8; 1: the pixels as stored) of an image file's bytes
    (``np.fromfile`` of it); 1 for a file without the tag, a malformed one or another
    format."""
    view = memoryview(data).cast("B")
    try:
        block = _exif_block(view)
        return 1 if block is None else _tiff_orientation(block)
    except struct.error:
        return 1


def orientation_problem(data: np.ndarray | bytes) -> str:
    """Why an image file's bytes cannot be used as they are (``""`` where they can): an EXIF
    orientation that turns them, with the command that bakes the turn into the pixels."""
    orientation = exif_orientation(data)
    if orientation == 1:
        return ""
    return (
        f"EXIF orientation {orientation} (the stored pixels shown {TURNS[orientation]}): pae "
        "reads the pixels as stored, viewers and other tools turn them, so a pose or camera "
        f"fits one of the two only; bake the turn into the pixels with {BAKE_COMMAND}, then "
        "reconstruct and convert from those images"
    )
