"""pae-localize from another APR's starts on a run without a teacher (a scene_fit run, as
``experiment=real_starts`` writes), the calibration for any start kept in the run, and
``--sequences``: each recording's frames in order."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from pae import CONFIG_DIR
from pae.apps.any_start import CALIBRATION_FILE
from pae.apps.recordings import recordings_of
from pae.core.errors import ConfigError, LabelError
from pae.data.labels import read_labels
from pae.data.starts import read_starts
from pae.localize import main, parser
from pae.render_compare.sequences import WINDOW_FITS, hampel_filter
from tests.conftest import TINY_SCENE_MODEL, tiny_overrides


@pytest.fixture(scope="module")
def fitted_run(tmp_path_factory: pytest.TempPathFactory, tiny_root: Path) -> Path:
    """A scene_fit run over the tiny dataset (no teacher), with its saved config."""
    from pae.train import run

    run_dir = tmp_path_factory.mktemp("scene_fit") / "run"
    overrides = [
        *tiny_overrides(tiny_root),
        *TINY_SCENE_MODEL,
        "scene_model.max_epochs=2",  # enough for a surface the refiner sees
        "scene_model.batches_per_epoch=15",
        "scene_model.rays_per_batch=2048",
        "scene_model.image_size=16",
        "stage.steps=[scene_fit]",
    ]
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("train", overrides=overrides)
    (run_dir / ".hydra").mkdir(parents=True)
    OmegaConf.save(cfg, run_dir / ".hydra" / "config.yaml")
    run(cfg, run_dir)
    return run_dir


def _starts(labels: Path, out: Path, seqs: list[str] | None = None) -> Path:
    """A pae label file of the labels' poses moved by 5 cm (``seq`` replaced where given)."""
    table = read_labels(labels)
    moved = table.poses.copy()
    moved[:, :3] += np.random.default_rng(0).normal(0.0, 0.05, (len(moved), 3))
    seq = table.seq if seqs is None else seqs
    lines = ["scene,split,seq,img_path,t1,t2,t3,q1,q2,q3,q4"]
    for row in range(len(table)):
        numbers = ",".join(f"{v:.9f}" for v in moved[row])
        lines.append(f"{table.scene[row]},test,{seq[row]},{table.img_path[row]},{numbers}")
    out.write_text("\n".join(lines) + "\n")
    return out


def test_a_run_without_a_teacher_refines_another_apr_s_starts(
    fitted_run: Path, tiny_root: Path, tmp_path: Path, capsys
) -> None:
    """On a scene_fit run, render_compare from --init works without a teacher; the
    calibration chosen on val is written to the run once and read back by the next call,
    which then gives the same poses; --summary records what was applied."""
    labels = tiny_root / "labels" / "all_test.csv"
    starts = _starts(labels, tmp_path / "starts.csv")
    argv = [str(fitted_run), str(labels), "--refine", "render_compare", "--init", str(starts)]
    first, second = tmp_path / "first.csv", tmp_path / "second.csv"
    assert main([*argv, "--out", str(first), "--summary", str(tmp_path / "s.json")]) == 0
    err = capsys.readouterr().err
    assert "(render_compare gate: any)" in err and "chosen on val" in err
    kept = json.loads((fitted_run / CALIBRATION_FILE).read_text())
    summary = json.loads((tmp_path / "s.json").read_text())
    assert summary["gate"] == "any" and summary["calibration"] == kept["calibration"]
    assert summary["calibrate_s"] > 0 and summary["ms_per_query"] > 0
    assert 0.0 <= summary["accepted_share"] <= 1.0 and summary["images"] == len(read_labels(labels))
    assert main([*argv, "--out", str(second)]) == 0
    assert f"the calibration for any start from {fitted_run / CALIBRATION_FILE}" in (
        capsys.readouterr().err
    )
    refined = read_labels(first).poses
    np.testing.assert_allclose(refined, read_labels(second).poses, atol=1e-6)
    moved = np.abs(refined[:, :3] - read_starts(starts).poses[:, :3]).max(1) > 1e-5
    assert summary["accepted_share"] == pytest.approx(moved.mean())


@pytest.mark.parametrize(
    "extra, message",
    [
        ([], "has no teacher (its steps are ['scene_fit']): only --refine render_compare --init"),
        (["--sequences"], "--sequences: RUN uses no sequence passes or window: give"),
        (["--sequence-passes", "3"], "--sequence-passes, --sequence-window and --sequence-fit"),
        (["--sequence-fit", "hampel"], "--sequence-fit apply with --sequences only"),
    ],
)
def test_mistakes_on_a_run_without_a_teacher_are_one_line(
    fitted_run: Path, tiny_root: Path, tmp_path: Path, capsys, extra: list[str], message: str
) -> None:
    labels = tiny_root / "labels" / "all_test.csv"
    if extra:
        extra = [*extra, "--init", str(_starts(labels, tmp_path / "starts.csv"))]
    out = tmp_path / "o.csv"
    with pytest.raises(SystemExit) as stopped:
        main(
            [str(fitted_run), str(labels), "--refine", "render_compare", "--out", str(out), *extra]
        )
    assert stopped.value.code == 1
    lines = [line for line in capsys.readouterr().err.splitlines() if "error:" in line]
    assert len(lines) == 1 and message.replace("RUN", str(fitted_run)) in lines[0], lines
    assert not out.exists()


def test_sequences_refine_each_recording_in_frame_order(
    fitted_run: Path, tiny_root: Path, tmp_path: Path, capsys
) -> None:
    """--sequences with a median window over 3 frames: each output row is the median of its
    recording's neighbours in frame order, written back in the queries' own order; with
    --sequence-fit hampel, the Hampel filter of the same poses in that order."""
    labels = tiny_root / "labels" / "all_test.csv"
    starts = _starts(labels, tmp_path / "starts.csv")
    argv = [str(fitted_run), str(labels), "--refine", "render_compare", "--init", str(starts)]
    alone, walked = tmp_path / "alone.csv", tmp_path / "walked.csv"
    assert main([*argv, "--out", str(alone)]) == 0
    summary = tmp_path / "s.json"
    window = ["--sequences", "--sequence-window", "3", "--summary", str(summary)]
    assert main([*argv, "--out", str(walked), *window]) == 0
    table = read_labels(labels)
    recordings = recordings_of(table.img_path, "folders")
    assert json.loads(summary.read_text())["recordings"] == len(recordings.names) > 1
    per_image = torch.as_tensor(read_labels(alone).poses)
    smoothed = torch.as_tensor(read_labels(walked).poses)
    assert read_labels(walked).img_path == table.img_path
    ordered = recordings.order.tolist()
    ids = recordings.ids.tolist()
    middle = [k for k in range(1, len(ordered) - 1) if ids[k - 1] == ids[k] == ids[k + 1]]
    assert middle
    for k in middle:
        row = ordered[k]
        expected = per_image[[ordered[k - 1], row, ordered[k + 1]], :3].median(0).values
        torch.testing.assert_close(smoothed[row, :3], expected, atol=1e-5, rtol=0)
    kept = tmp_path / "kept.csv"
    assert main([*argv, "--out", str(kept), *window[:3], "--sequence-fit", "hampel"]) == 0
    in_order = per_image[recordings.order].float()
    scenes = torch.zeros(len(ordered), dtype=torch.long)
    expected = hampel_filter(in_order, recordings.ids, scenes, 3)[torch.argsort(recordings.order)]
    found = torch.as_tensor(read_labels(kept).poses).float()
    torch.testing.assert_close(found[:, :3], expected[:, :3], atol=1e-5, rtol=0)
    assert parser()._option_string_actions["--sequence-fit"].choices == WINDOW_FITS


def test_recordings_put_each_recording_s_frames_together_by_name() -> None:
    images = ["b/seq-02/frame-2.png", "a/seq-01/frame-1.png", "b/seq-02/frame-1.png"]
    found = recordings_of(images, "folders")
    assert found.names == ["b/seq-02", "a/seq-01"]
    assert found.order.tolist() == [2, 0, 1] and found.ids.tolist() == [0, 0, 1]
    values = torch.tensor([10.0, 20.0, 30.0])
    assert found.restore(values[found.order]).tolist() == values.tolist()


def test_a_recording_column_naming_some_frames_only_is_one_line(
    tiny_root: Path, tmp_path: Path
) -> None:
    labels = tiny_root / "labels" / "all_test.csv"
    table = read_labels(labels)
    seqs = list(table.seq)
    seqs[3] = ""
    starts = _starts(labels, tmp_path / "starts.csv", seqs)
    with pytest.raises(
        LabelError, match=rf"starts.csv:5: image {table.img_path[3]} has no recording"
    ):
        recordings_of(table.img_path, "column", read_starts(starts), str(starts))
    lines = tmp_path / "lines.txt"
    lines.write_text("# format: lines\nx.png 0 0 0 1 0 0 0\n")
    with pytest.raises(ConfigError, match="has no recording column"):
        recordings_of(["x.png"], "column", read_starts(lines, form="lines"), str(lines))


def test_the_calibration_for_any_start_chooses_among_the_run_s_stages_and_applies_it(
    fitted_run: Path, tiny_root: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With ``render_compare.matches_from_val`` in the run's config, --init-gate any tries
    those stages on val (retrieving train views by the thumbnail descriptor: the run has no
    teacher); the stage chosen (here forced: the tiny scene decides nothing) is kept in the
    run's record and read back, and the test queries reach refine() at its match width with
    the train views read for val, not read twice; the shares of the queries the stage may
    go to (``match_shares_from_val``) reach the calibration and are part of its record's
    key."""
    import shutil

    from pae.apps import any_start, localization, match_inputs
    from pae.render_compare import calibrate_any_start

    run = tmp_path / "run"
    shutil.copytree(fitted_run, run, ignore=shutil.ignore_patterns(CALIBRATION_FILE))
    config = OmegaConf.load(run / ".hydra" / "config.yaml")
    stage = {"width": 32, "render_width": 0, "near_start_views": 2}
    config.render_compare.matches_from_val = [{}, stage]
    config.render_compare.match_descriptor = "thumbnail"
    config.render_compare.match_shares_from_val = [0.5]
    OmegaConf.save(config, run / ".hydra" / "config.yaml")
    tried, shares = [], []

    def forced(*args, **kwargs):
        tried.extend(args[-1].stages())
        shares.append(list(args[-1].stage_shares))
        chosen, refined, starts = calibrate_any_start(*args, **kwargs)
        return chosen.__class__(**{**chosen.__dict__, "match": tried[-1]}), refined, starts

    seen = []

    def spy(model, queries, *rest, **kwargs):
        seen.append(queries.matching)
        return refine(model, queries, *rest, **kwargs)

    reads = []

    def train_images(*args, **kwargs):
        reads.append(args[1])
        return read_train(*args, **kwargs)

    refine, read_train = localization.refine, match_inputs.train_images
    monkeypatch.setattr(match_inputs, "train_images", train_images)
    monkeypatch.setattr(any_start, "calibrate_any_start", forced)
    monkeypatch.setattr(localization, "refine", spy)
    labels = tiny_root / "labels" / "all_test.csv"
    starts = _starts(labels, tmp_path / "starts.csv")
    argv = [str(run), str(labels), "--refine", "render_compare", "--init", str(starts)]
    written = ["--out", str(tmp_path / "a.csv"), "--summary", str(tmp_path / "a.json")]
    assert main([*argv, *written]) == 0
    assert tried[-1].width == 32 and tried[-1].near_start_views == 2
    kept = json.loads((run / CALIBRATION_FILE).read_text())
    assert kept["calibration"]["match"]["near_start_views"] == 2
    matching = seen[-1]
    assert matching is not None and matching.images.shape[-1] == 32
    assert matching.train is not None and matching.train.describe is None
    assert len(matching.train.poses) > 0 and len(matching.images) == len(read_labels(labels))
    assert reads == [32]
    summary = json.loads((tmp_path / "a.json").read_text())
    assert summary["calibration"]["match"]["near_start_views"] == 2
    assert 0.0 <= summary["other_start_kept_share"] <= 1.0
    assert summary["keypoints_found_share"] == 0.0  # no keypoints in this stage
    tried.clear()
    assert main([*argv, "--out", str(tmp_path / "b.csv")]) == 0
    assert not tried  # read back from the run's record
    assert seen[-1] is not None and seen[-1].images.shape[-1] == 32
    np.testing.assert_allclose(
        read_labels(tmp_path / "a.csv").poses, read_labels(tmp_path / "b.csv").poses, atol=1e-6
    )
    assert shares == [[0.5]]
    config.render_compare.match_shares_from_val = [0.25]  # another calibration's key
    OmegaConf.save(config, run / ".hydra" / "config.yaml")
    assert main([*argv, "--out", str(tmp_path / "c.csv")]) == 0
    assert tried and shares[-1] == [0.25]
