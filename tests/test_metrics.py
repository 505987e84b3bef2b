"""Error summaries on known numbers: numpy's median per scene, then the average over scenes."""

import numpy as np
import pytest
import torch

from pae.core.metrics import PoseErrorMetric, summarise_errors


def test_medians_are_numpys_per_scene_and_averaged_over_scenes() -> None:
    pos = torch.tensor([1.0, 2.0, 3.0, 4.0, 10.0, 20.0, 30.0])
    rot = torch.tensor([4.0, 3.0, 2.0, 1.0, 5.0, 7.0, 6.0])
    scene = torch.tensor([0, 0, 0, 0, 1, 1, 1])
    figures = summarise_errors(pos, rot, scene, ["a", "b"])
    assert figures["a/pos_median_m"].item() == 2.5  # torch.median would give 2
    assert figures["a/rot_median_deg"].item() == 2.5
    assert figures["b/pos_median_m"].item() == 20.0
    assert figures["b/rot_median_deg"].item() == 6.0
    assert figures["pos_median_m"].item() == pytest.approx((2.5 + 20.0) / 2)
    assert figures["rot_median_deg"].item() == pytest.approx((2.5 + 6.0) / 2)
    assert figures["a/pos_mean_m"].item() == pytest.approx(2.5)
    assert figures["pos_mean_m"].item() == pytest.approx((2.5 + 20.0) / 2)
    for name, index in (("a", 0), ("b", 1)):
        expected = np.median(pos[scene == index].numpy())
        assert figures[f"{name}/pos_median_m"].item() == pytest.approx(expected)


def test_one_scene_has_no_per_scene_keys() -> None:
    figures = summarise_errors(
        torch.tensor([1.0, 2.0, 3.0, 4.0]), torch.zeros(4), torch.zeros(4, dtype=torch.long), ["s"]
    )
    assert figures["pos_median_m"].item() == 2.5
    assert sorted(figures) == [
        "pos_mean_m",
        "pos_median_m",
        "rot_mean_deg",
        "rot_median_deg",
        "within_10cm_10deg",
        "within_5cm_5deg",
    ]


def test_within_shares_need_both_position_and_orientation() -> None:
    pos = torch.tensor([0.01, 0.04, 0.08, 0.01, 0.5])
    rot = torch.tensor([1.0, 4.9, 9.0, 7.0, 1.0])
    figures = summarise_errors(pos, rot, torch.zeros(5, dtype=torch.long), ["s"])
    assert figures["within_5cm_5deg"].item() == pytest.approx(2 / 5)
    assert figures["within_10cm_10deg"].item() == pytest.approx(4 / 5)


def test_metric_reports_the_median_of_position_errors() -> None:
    metric = PoseErrorMetric(["s"])
    target = torch.zeros(4, 7)
    target[:, 3] = 1.0
    pred = target.clone()
    pred[:, 0] = torch.tensor([1.0, 2.0, 3.0, 4.0])  # position errors 1..4 m
    metric.update(pred[:2], target[:2])
    metric.update(pred[2:], target[2:])
    figures = metric.compute()
    assert figures["pos_median_m"].item() == 2.5
    assert figures["rot_median_deg"].item() == 0.0
