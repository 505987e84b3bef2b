"""The GPU check (experiments/bench/gpu.sh, pae.bench.gpu) on the CPU: its skip without a CUDA
device, and its check of the torch engine's answers against the compiled engine's."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
import torch

from pae.bench import gpu
from pae.render_compare.gate import RenderCompareResult

SCRIPT = Path(__file__).resolve().parents[1] / "experiments" / "bench" / "gpu.sh"


def test_without_cuda_the_module_says_skipped_and_writes_nothing(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert gpu.main(["--out", str(tmp_path / "gpu.json")]) == 0
    assert capsys.readouterr().out == "no CUDA device: skipped\n"
    assert not (tmp_path / "gpu.json").exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="the skip path needs a machine without CUDA")
def test_the_script_skips_in_one_line_and_exits_0_without_cuda(tmp_path: Path) -> None:
    result = subprocess.run(
        [str(SCRIPT), str(tmp_path / "gpu.json")], capture_output=True, text=True
    )
    assert (result.returncode, result.stdout) == (0, "no CUDA device: skipped\n")
    assert not (tmp_path / "gpu.json").exists()


@pytest.fixture(scope="module")
def cpu_answers() -> tuple[RenderCompareResult, RenderCompareResult]:
    """The compiled engine's and the torch engine's answers on the same queries, both on
    the CPU (the check's logic; on a GPU the torch engine runs there)."""
    return gpu.engine_answers(queries=16, device="cpu")


def test_the_torch_and_compiled_engines_give_the_same_answers(cpu_answers) -> None:
    figures = gpu.answers_agree(*cpu_answers)
    assert figures["bench/gpu/engines/agree"] == 1.0
    assert figures["bench/gpu/engines/queries"] == 16
    assert figures["bench/gpu/engines/same_pose_share"] >= gpu.MIN_SAME_SHARE
    assert figures["bench/gpu/engines/position_median_diff_m"] < 1e-4
    assert figures["bench/gpu/engines/initial_score_median_diff"] <= gpu.SCORE_MEDIAN_ATOL
    assert figures["bench/gpu/engines/initial_score_max_diff"] <= gpu.SCORE_MAX_ATOL


def test_the_check_fails_on_moved_poses_or_other_start_scores(cpu_answers) -> None:
    compiled, tensor = cpu_answers
    moved = tensor.poses.clone()
    moved[:8, 0] += 2 * gpu.SAME_POSE_M  # half the queries a little elsewhere
    figures = gpu.answers_agree(compiled, tensor._replace(poses=moved))
    assert figures["bench/gpu/engines/same_pose_share"] <= 0.5
    assert figures["bench/gpu/engines/agree"] == 0.0
    shifted = tensor.initial_score + 2 * gpu.SCORE_MEDIAN_ATOL  # every query a little
    assert gpu.answers_agree(compiled, tensor._replace(initial_score=shifted))[
        "bench/gpu/engines/agree"
    ] == pytest.approx(0.0)
    one_off = tensor.initial_score.clone()
    one_off[0] += 0.08  # one query by as much as TF32 convolutions moved it on an H200
    assert gpu.answers_agree(compiled, tensor._replace(initial_score=one_off))[
        "bench/gpu/engines/agree"
    ] == pytest.approx(0.0)


def test_the_stage_differences_measure_the_device_side_against_the_cpu(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Both sides on the CPU: every difference 0. A device whose renderer gives other grey
    levels and depths (the scene model, once moved there, renders them 5 % darker and 10 %
    deeper) shows in the reference figures, and in them only."""
    import pae.bench.render_compare as room

    figures = gpu.stage_differences(queries=4, device="cpu")
    assert len([k for k in figures if "target_level" in k]) >= 2
    assert "bench/gpu/stages/reference_depth_max_diff_m" in figures
    assert all(value == 0.0 for value in figures.values())

    room_grid = room.room_grid

    def grid_that_renders_otherwise_once_moved(*args, **kwargs):
        model = room_grid(*args, **kwargs)
        to, render, moved = model.to, model.render, [False]

        def move(device):
            moved[0] = not moved[0]  # stage_differences moves it to the device, then back
            return to(device)

        def rendered(*args, **kwargs):
            out = render(*args, **kwargs)
            return out._replace(rgb=out.rgb * 0.95, depth=out.depth * 1.1) if moved[0] else out

        model.to, model.render = move, rendered
        return model

    monkeypatch.setattr(room, "room_grid", grid_that_renders_otherwise_once_moved)
    figures = gpu.stage_differences(queries=4, device="cpu")
    assert all(figures[k] == 0.0 for k in figures if "target_level" in k)
    assert figures["bench/gpu/stages/reference_grey_max_diff"] > 0.005
    assert figures["bench/gpu/stages/reference_depth_max_diff_m"] > 0.05


def test_float32_arithmetic_turns_tf32_off_inside_and_restores_the_settings() -> None:
    from pae.render_compare.images import float32_arithmetic

    before = torch.get_float32_matmul_precision()
    torch.set_float32_matmul_precision("high")
    try:
        with float32_arithmetic():
            assert torch.get_float32_matmul_precision() == "highest"
            assert not torch.backends.cudnn.allow_tf32
        assert torch.get_float32_matmul_precision() == "high"
        assert torch.backends.cudnn.allow_tf32
    finally:
        torch.set_float32_matmul_precision(before)


def test_the_refiner_takes_larger_chunks_off_the_cpu() -> None:
    from pae.bench.render_compare import room_grid
    from pae.render_compare.refiner import RenderCompareRefiner

    refiner = RenderCompareRefiner.configured(room_grid(1), chunk=8, gpu_chunk=512)
    assert refiner.chunk_for(torch.device("cpu")) == 8
    assert refiner.chunk_for(torch.device("cuda", 0)) == 512
    with pytest.raises(ValueError, match="chunk and gpu_chunk >= 1"):
        RenderCompareRefiner.configured(room_grid(1), gpu_chunk=0)
