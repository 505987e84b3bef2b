"""experiments/render_compare_real_starts/gate_val.py: the gate families fitted on val."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import pytest
import torch

FOLDER = Path(__file__).resolve().parents[1] / "experiments/render_compare_real_starts"


def _gate_val() -> ModuleType:
    spec = importlib.util.spec_from_file_location("gate_val", FOLDER / "gate_val.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _record(blocks: int = 4) -> dict:
    """A 1-m scene whose val queries come in three kinds, eight (a ladder's length) each per
    block: near starts refined a little closer with little gain, starts refined far away into
    a wrong pose with a larger gain, far starts brought home with the largest gain."""
    kinds = {  # start m, refined m, moved m, gain
        "near": (0.03, 0.01, 0.02, 0.02),
        "wrong": (0.05, 0.5, 0.5, 0.1),
        "home": (0.3, 0.01, 0.3, 0.5),
    }
    rows = [kinds[name] for _ in range(blocks) for name in kinds for _ in range(8)]
    start, refined, moved, gain = torch.tensor(rows).T
    return {
        "gain": gain,
        "score": torch.full_like(gain, 0.5),
        "moved_m": moved,
        "start_m": start,
        "refined_m": refined,
        "rung": torch.arange(len(rows)) % 8,
        "size_m": 1.0,
    }


def test_evidence_per_distance_keeps_near_refinements_that_a_margin_cannot() -> None:
    gate_val = _gate_val()
    record = _record()
    every = torch.arange(len(record["gain"]))
    near = torch.arange(len(every)) % 24 < 8
    values = {}
    for family in ("A", "B", "C"):
        gate = gate_val.fitted(family, record, every)
        kept = gate_val.accepted(family, record, every, gate)
        values[family] = gate_val.objective(record, every, kept)
        if family == "C":
            assert kept[near].all() and not kept[(every % 24 >= 8) & (every % 24 < 16)].any()
        else:  # one margin on the gain: the near refinements go with the wrong ones
            assert not kept[near].any()
    assert values["C"] < values["A"] - 0.1
    assert values["B"] == pytest.approx(values["A"])  # equal scores: nothing vouches alone


def test_cross_validation_scores_each_family_on_the_half_it_was_not_fitted_on() -> None:
    gate_val = _gate_val()
    families = gate_val.cross_validated(_record())
    assert set(families) == {"A", "B", "C"}
    for row in families.values():
        assert row["cross_validated"] == pytest.approx(sum(row["held_out"]) / 2)
        assert len(row["rungs"]) == 8
    assert families["C"]["cross_validated"] < families["A"]["cross_validated"]


def test_compensated_starts_keep_the_point_ahead_on_the_optical_axis() -> None:
    from pae.core.geometry import quaternion_to_matrix
    from pae.core.pose_sampling import perturb_poses

    gate_val = _gate_val()
    truth = perturb_poses(torch.zeros(64, 7) + torch.tensor([0.0] * 3 + [1.0, 0, 0, 0]), 1.0, 90.0)
    size = 2.0
    starts = gate_val.compensated_starts(truth, size, torch.Generator().manual_seed(0))

    def forward(poses: torch.Tensor) -> torch.Tensor:
        return quaternion_to_matrix(poses[:, 3:].double())[:, :, 2]

    point = truth[:, :3].double() + gate_val.LOOK_AT_SHARE * size * forward(truth)
    towards = point - starts[:, :3].double()
    towards = towards / towards.norm(dim=-1, keepdim=True)
    assert torch.allclose(forward(starts), towards, atol=1e-5)
    moved = (starts[:, :3] - truth[:, :3]).norm(dim=-1)
    rung_scale = torch.tensor(gate_val.LADDER)[torch.arange(64) % 8] * size
    assert (moved <= 2 * rung_scale + 1e-6).all() and (moved > 0).all()


def test_a_mixed_ladder_of_the_same_starts_changes_nothing_and_of_other_starts_does() -> None:
    gate_val = _gate_val()
    record = _record()
    same = gate_val.mixed_against_random(record, record)
    assert same == {"random_change": 0.0, "compensated_change": 0.0}
    near_only = dict(record)
    near_only["gain"] = torch.full_like(record["gain"], 0.02)
    near_only["start_m"], near_only["refined_m"] = (
        torch.full_like(record["gain"], v) for v in (0.03, 0.01)
    )
    other = gate_val.mixed_against_random(record, near_only)
    assert other["compensated_change"] < 0  # the mixed gate keeps the near refinements


def test_todays_family_is_the_calibrations_own_gate() -> None:
    from pae.render_compare.calibration import choose_gate

    gate_val = _gate_val()
    generator = torch.Generator().manual_seed(0)
    count = 400
    start = 0.01 + torch.rand(count, generator=generator)
    record = {
        "gain": torch.randn(count, generator=generator) * 0.2,
        "score": torch.rand(count, generator=generator),
        "start_m": start,
        "refined_m": start * torch.rand(count, generator=generator) * 2,
        "moved_m": torch.rand(count, generator=generator),
        "size_m": 1.0,
    }
    every = torch.arange(count)
    margin, floor, alone = gate_val.fitted("A", record, every)
    expected = choose_gate(
        record["gain"], record["score"], record["refined_m"], record["start_m"],
        objective="log_ratio",
    )  # fmt: skip
    assert (margin, floor) == pytest.approx(expected) and alone == gate_val.NEVER


def test_by_distance_bins_the_starts() -> None:
    gate_val = _gate_val()
    record = _record()
    rows = gate_val.by_distance(record)
    assert [r["queries"] for r in rows] == [32, 32, 0]  # near 3 cm; wrong 5 cm; home 30 cm
    assert rows[0]["refined_median_m"] == pytest.approx(0.01) and rows[0]["nearer"] == 1.0
    assert rows[1]["nearer"] == 0.0
    assert rows[0]["start_score_median"] == pytest.approx(0.48)
    assert rows[2] == {"start_m": [0.07, 0.12], "queries": 0}
    assert "7-12 cm" not in gate_val.distances_line("empty bin", rows)
