import numpy as np
import torch

from pae.callbacks.refinement import trajectory_image


def test_trajectory_image_draws_each_track_in_its_colour() -> None:
    gt = torch.tensor([[0.0, 0.0, 1.5, 1, 0, 0, 0], [2.0, 1.0, 1.5, 1, 0, 0, 0]])
    teacher = gt + torch.tensor([0.0, 0.5, 0, 0, 0, 0, 0])
    refined = gt + torch.tensor([1.0, 0.0, 0, 0, 0, 0, 0])
    image = trajectory_image(gt, teacher, refined, size=100)
    assert image.shape == (100, 100, 3) and image.dtype == np.uint8
    colours = {tuple(c) for c in image.reshape(-1, 3)}
    assert {(255, 255, 255), (0, 160, 0), (220, 0, 0), (0, 0, 220)} <= colours
    # the first ground-truth point is the plot's lower-left corner (x min, y min)
    assert tuple(image[100 - 1 - 20, 20]) == (0, 160, 0)
