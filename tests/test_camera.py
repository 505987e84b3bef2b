"""The camera's geometry in ``pae.data.camera``: intrinsics through a resize, and rays."""

from __future__ import annotations

import torch

from pae.data.camera import Intrinsics, scale_intrinsics


def test_a_resized_camera_matches_its_scaled_intrinsic_vector_exactly() -> None:
    camera = Intrinsics(fx=1171.3, fy=1169.9, cx=959.7, cy=539.2, width=1920, height=1080)
    for width, height in ((455, 256), (256, 144), (1920, 1080), (641, 359)):
        resized = camera.resized(width, height)
        vector = torch.tensor([camera.vector()], dtype=torch.float64)
        scaled = scale_intrinsics(vector, width / camera.width, height / camera.height)
        assert scaled[0].tolist() == resized.vector()
        assert (resized.width, resized.height) == (width, height)
