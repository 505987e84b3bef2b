"""experiments/render_compare_real_starts' run.py and table.py: every K-th test image only,
said in the table; seeds.py's spread."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import pytest

FOLDER = Path(__file__).resolve().parents[1] / "experiments/render_compare_real_starts"
FIGURES = {"pos_median_m": 0.03, "rot_median_deg": 1.0, "within_5cm_5deg": 0.5}


def _script(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, FOLDER / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_every_below_one_is_a_one_line_error(capsys: pytest.CaptureFixture[str]) -> None:
    run = _script("run")
    with pytest.raises(SystemExit):
        run.main(["--labels", "L", "--estimates", "E", "--every", "0"])
    assert "--every must be at least 1, got 0" in capsys.readouterr().err


@pytest.mark.parametrize("every, named", [(1, "chess"), (4, "chess (one test image in 4)")])
def test_the_table_names_a_scene_refined_on_every_kth_image(every: int, named: str) -> None:
    record = {
        "scene": "chess",
        "every": every,
        "start": FIGURES,
        "render_compare": FIGURES,
        "nefes50": FIGURES,
        "accepted_share": 0.5,
        "calibration": {},
        "ms_per_query": 300.0,
    }
    assert _script("table").row(record, recordings=False)[0] == named


def _scene_run(tmp_path: Path, every: int) -> tuple[Path, Path]:
    """A scene's run folder as run.py leaves it after refining each image of 4 test rows
    (every ``every``-th), without the recordings; and the source test label file."""
    import json

    import numpy as np

    from pae.data.labels import LabelTable, write_labels

    poses = np.tile([0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0], (4, 1))
    poses[:, 0] = np.arange(4)
    table = LabelTable(
        ["chess"] * 4, ["test"] * 4, ["seq-03"] * 4, [f"f{i}.png" for i in range(4)], poses
    )
    source = tmp_path / "chess_test.csv"
    write_labels(source, table)
    write_labels(tmp_path / "data" / "labels" / "all_test.csv", table)
    run_dir = tmp_path / "chess"
    (run_dir / ".hydra").mkdir(parents=True)
    (run_dir / ".hydra" / "data.yaml").write_text(f"root: {tmp_path / 'data'}\n")
    (run_dir / "metrics.json").write_text("{}")
    (run_dir / "truth_audit.json").write_text(json.dumps({"every": every}))
    for apr in ("DFNet", "PoseNet"):
        record = {"scene": "chess", "every": every, "accepted_share": 0.5}
        record |= {"start": FIGURES, "render_compare": FIGURES, "nefes50": FIGURES}
        (run_dir / f"real_starts_{apr}.json").write_text(json.dumps(record))
    return run_dir, source


def test_recordings_are_added_to_a_scene_refined_per_image_only(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import argparse
    import json

    import torch

    from pae.data.labels import read_labels

    run = _script("run")
    run_dir, source = _scene_run(tmp_path, every=2)
    called = []

    def localize(run_dir: Path, test: Path, starts: Path, tag: str, options: list) -> dict:
        called.append((tag, len(read_labels(test))))
        return {"poses": read_labels(test), "recordings": 1, "ms_per_query": 5.0}

    monkeypatch.setattr(run, "localize", localize)
    audited = []
    monkeypatch.setattr(run, "truth_audit", lambda run_dir, every: audited.append(every))
    matched = []

    def real_starts(folder: Path, scene: str, img_paths: list, truth: torch.Tensor) -> dict:
        matched.append(len(img_paths))
        start = truth.clone()
        start[:, 0] += 1.0  # 1 m along x, the orientation kept
        return {"start": start, "nefes50": truth}

    monkeypatch.setattr(run, "real_starts", real_starts)
    args = argparse.Namespace(estimates=tmp_path, every=2, recordings=(10, 5))
    run.refine_scene("7Scenes", "chess", run_dir, [source, source], args)
    assert called == [("per_recording_DFNet", 2), ("per_recording_PoseNet", 2)]
    assert matched == [4, 4]  # the estimate files hold every test image: all matched, then thinned
    starts = read_labels(run_dir / "starts_DFNet.csv")
    assert starts.poses[:, 0].tolist() == [1.0, 3.0]  # images 0 and 2, each its own start
    record = json.loads((run_dir / "real_starts_DFNet.json").read_text())
    assert record["render_compare"] == FIGURES  # the per-image figures kept as they were
    assert record["per_recording"]["pos_median_m"] == 0.0
    assert record["per_recording_worse_than_start_share"] == 0.0
    assert record["sequence_passes_window"] == [10, 5]
    assert audited == []  # the audit on the same test images is kept
    (run_dir / "truth_audit.json").write_text("{}")  # an audit of every test image
    run.refine_scene("7Scenes", "chess", run_dir, [source, source], args)
    assert audited == [2]
    args.every = 1
    with pytest.raises(SystemExit, match="one test image in 2, not one in 1: give --every 2"):
        run.refine_scene("7Scenes", "chess", run_dir, [source, source], args)


def test_both_aprs_are_refined_per_image_on_every_kth_image(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A scene with nothing refined yet: each APR's starts matched to all test images, thinned
    to every 2nd, refined and recorded with the calibration's figures (the second APR once
    failed on a name the first had rebound)."""
    import argparse
    import json

    import torch

    from pae.data.labels import read_labels

    run = _script("run")
    run_dir, source = _scene_run(tmp_path, every=2)
    for apr in ("DFNet", "PoseNet"):
        (run_dir / f"real_starts_{apr}.json").unlink()
    (run_dir / ".hydra" / "config.yaml").write_text("data:\n  size: 128\n")
    chosen = {"val_queries": 7, "scene_size_m": 3.0, "val": {"start": FIGURES}}
    (run_dir / run.CALIBRATION_FILE).write_text(json.dumps(chosen))

    def localize(run_dir: Path, test: Path, starts: Path, tag: str, options: list) -> dict:
        calibration = {"accept_margin": 0.0, "accept_score": 0.0, "steps": {"position": 0.1}}
        return {
            "poses": read_labels(test), "calibration": calibration, "accepted_share": 1.0,
            "calibrate_s": 2.0, "ms_per_query": 5.0,
        }  # fmt: skip

    monkeypatch.setattr(run, "localize", localize)
    monkeypatch.setattr(run, "truth_audit", lambda run_dir, every: None)

    def real_starts(folder: Path, scene: str, img_paths: list, truth: torch.Tensor) -> dict:
        start = truth.clone()
        start[:, 0] += 2.0 if "PoseNet" in str(folder) else 1.0
        return {"start": start, "nefes50": truth}

    monkeypatch.setattr(run, "real_starts", real_starts)
    args = argparse.Namespace(estimates=tmp_path, every=2, recordings=None)
    run.refine_scene("7Scenes", "chess", run_dir, [source, source], args)
    for apr, shift in (("DFNet", 1.0), ("PoseNet", 2.0)):
        starts = read_labels(run_dir / f"starts_{apr}.csv")
        assert starts.poses[:, 0].tolist() == [shift, 2.0 + shift]  # images 0 and 2
        record = json.loads((run_dir / f"real_starts_{apr}.json").read_text())
        assert record["queries"] == 2 and record["every"] == 2 and record["val_queries"] == 7
        assert record["start"]["pos_median_m"] == pytest.approx(shift)
        assert record["render_compare"]["pos_median_m"] == 0.0


def test_seeds_says_a_difference_beyond_the_larger_spread(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import json

    def folders(name: str, metres: list[float]) -> list[str]:
        made = []
        for seed, median in enumerate(metres):
            scene = tmp_path / f"{name}_{seed}" / "ShopFacade"
            scene.mkdir(parents=True)
            for apr, shift in (("DFNet", 0.0), ("PoseNet", 0.03)):
                record = {"render_compare": {"pos_median_m": median + shift}}
                (scene / f"real_starts_{apr}.json").write_text(json.dumps(record))
            made.append(str(scene.parent))
        return made

    without, with_ = folders("without", [0.06, 0.07, 0.08]), folders("with", [0.10, 0.11])
    _script("seeds").main(["ShopFacade", "--without", *without, "--with", *with_])
    rows = capsys.readouterr().out.splitlines()[2:]
    assert rows[0] == (
        "| DFNet | 6.0, 7.0, 8.0 | 10.0, 11.0 | 7.00 ± 1.00 | 10.50 ± 0.71 | +3.50 | yes |"
    )
    assert rows[1].startswith("| PoseNet | 9.0, 10.0, 11.0 | 13.0, 14.0 |")
    near = folders("near", [0.07, 0.075])
    _script("seeds").main(["ShopFacade", "--without", *without, "--with", *near])
    assert capsys.readouterr().out.splitlines()[2].endswith("| +0.25 | no |")


def test_a_finished_localize_pass_is_read_back_not_run_again(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A pass whose poses and summary are in the run, from the same starts file and images,
    is read back; a summary from other starts (or other images) runs pae-localize again."""
    import json
    import shutil

    from pae.data.labels import read_labels

    run = _script("run")
    run_dir, source = _scene_run(tmp_path, every=1)
    starts = run_dir / "starts_DFNet.csv"
    shutil.copy(source, starts)
    shutil.copy(source, run_dir / "render_compare_DFNet.csv")
    summary = {"init": str(starts), "images": 4, "ms_per_query": 7.0}
    (run_dir / "render_compare_DFNet.json").write_text(json.dumps(summary))
    commands = []
    monkeypatch.setattr(run.subprocess, "run", lambda command, **_: commands.append(command))
    found = run.localize(run_dir, source, starts, "render_compare_DFNet", [])
    assert commands == [] and found["ms_per_query"] == 7.0
    assert len(found["poses"].poses) == len(read_labels(source).poses)
    summary["init"] = str(run_dir / "other_starts.csv")
    (run_dir / "render_compare_DFNet.json").write_text(json.dumps(summary))
    run.localize(run_dir, source, starts, "render_compare_DFNet", [])
    assert len(commands) == 1 and "--init" in commands[0]
