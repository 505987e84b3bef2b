"""The images a label file names: whether each lies inside the data root, decodes, and has
the size most images have (one size per label file), for ``pae-data check`` and the loaders."""

from __future__ import annotations

import os
from collections import Counter
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from pae.core.errors import LabelError
from pae.data.exif import orientation_problem
from pae.data.labels import LabelTable, focal_problems

__all__ = ["find_image_problems", "odd_sizes", "outside_root"]


def outside_root(img_paths: Sequence[str], root: str | os.PathLike[str]) -> list[int]:
    """Indices of the paths that escape ``root`` once joined to it, resolved lexically (``..``
    and absolute paths; symbolic links inside ``root`` are allowed). Loaders and
    ``pae-data check`` share this rule."""
    root_abs = os.path.abspath(root)
    return [
        i
        for i, img_path in enumerate(img_paths)
        if os.path.commonpath((root_abs, os.path.normpath(os.path.join(root_abs, img_path))))
        != root_abs
    ]


def find_image_problems(
    table: LabelTable, root: str | os.PathLike[str], workers: int | None = None
) -> list[str]:
    """One message per row whose image is outside ``root``, missing, not decodable, turned by
    its EXIF orientation (:func:`pae.data.exif.orientation_problem`), or of another size than
    most images (loaders need one size per label file), or whose focal length is implausible
    for the width of most images (``focal_problems``).

    Images are fully decoded with OpenCV, on ``workers`` threads.
    """
    root_abs = os.path.abspath(root)
    if not os.path.isdir(root_abs):
        raise LabelError(str(root), None, "image root is not a directory")
    problems = {
        i: f"image path escapes the root {root}: {table.img_path[i]!r}"
        for i in outside_root(table.img_path, root_abs)
    }
    resolved = [
        (i, os.path.join(root_abs, p)) for i, p in enumerate(table.img_path) if i not in problems
    ]
    sizes: dict[int, tuple[int, int]] = {}
    with ThreadPoolExecutor(max_workers=workers or min(8, os.cpu_count() or 1)) as pool:
        outcomes = pool.map(_image_problem, (full for _, full in resolved))
        for (i, _), (outcome, shape) in zip(resolved, outcomes, strict=True):
            if outcome:
                problems[i] = f"{outcome}: {table.img_path[i]!r}"
            else:
                sizes[i] = shape
    for i, problem in odd_sizes(sizes).items():
        problems[i] = f"{problem}: {table.img_path[i]!r}"
    if sizes:
        [(width, _)] = Counter(w for _, w in sizes.values()).most_common(1)
        problems = focal_problems(table, width) | problems
    location = table.source or "row"
    return [f"{location}:{table.file_line(i)}: {problems[i]}" for i in sorted(problems)]


def odd_sizes(sizes: Mapping[int, tuple[int, int]]) -> dict[int, str]:
    """Rows whose image size (h, w) in px is not the one most images have (the earliest of
    equally common ones), each with why: one size per label file."""
    counts = Counter(sizes.values())
    if len(counts) < 2:
        return {}
    (common_h, common_w), count = counts.most_common(1)[0]
    return {
        i: (
            f"image is {w}x{h} px, unlike the {common_w}x{common_h} px of most images ({count} "
            f"of {len(sizes)}; one size per label file)"
        )
        for i, (h, w) in sizes.items()
        if (h, w) != (common_h, common_w)
    }


def _image_problem(path: str) -> tuple[str, tuple[int, ...]]:
    """Why the image at ``path`` cannot be used (``""`` if it decodes) and its (h, w)."""
    import cv2

    if not os.path.exists(path):
        return "image not found", ()
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except OSError as error:
        return f"image unreadable ({error.strerror or error})", ()
    if data.size == 0:
        return "image file is empty", ()
    try:
        image = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    except cv2.error:
        image = None
    if image is None:
        return "image is corrupt (cannot be decoded)", ()
    return orientation_problem(data), image.shape[:2]
