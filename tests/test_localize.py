"""pae-localize on a tiny teacher -> student -> scene-model run: the poses it writes for the
run's own test label file give the run's test figures."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from pae import CONFIG_DIR
from pae.core.errors import ConfigError
from pae.core.geometry import pose_errors
from pae.core.metrics import summarise_errors
from pae.data.labels import read_labels
from pae.localize import main
from tests.conftest import tiny_data_overrides, tiny_overrides

RENDER_COMPARE = [
    "render_compare.refiner.rounds=2",
    "render_compare.refiner.candidates=4",
    "render_compare.refiner.polish_steps=2",
    "render_compare.oracle=false",
    "render_compare.accept_margin=-4.0",  # keep every refinement: poses unlike the teacher's
]


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory: pytest.TempPathFactory, tiny_root: Path) -> Path:
    """A teacher, student and scene-model run over the tiny dataset, with its saved config."""
    from pae.train import run

    run_dir = tmp_path_factory.mktemp("localize") / "run"
    overrides = [
        *tiny_overrides(tiny_root),
        "student.max_epochs=1",
        "scene_model.max_epochs=2",  # enough for a surface the refiner sees
        "scene_model.batches_per_epoch=15",
        "scene_model.rays_per_batch=2048",
        "scene_model.model.num_voxels=8000",
        "scene_model.image_size=16",
        *RENDER_COMPARE,
        "stage=pipeline",
        "stage.steps=[teacher,student,scene_model]",
    ]
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("train", overrides=overrides)
    (run_dir / ".hydra").mkdir(parents=True)
    OmegaConf.save(cfg, run_dir / ".hydra" / "config.yaml")  # what Hydra saves
    run(cfg, run_dir)
    return run_dir


def _medians(path: Path, labels: Path, scenes: list[str]) -> tuple[float, float]:
    """Overall median errors (m, deg) of a written label file against the labels."""
    written, truth = read_labels(path), read_labels(labels)
    assert written.img_path == truth.img_path
    pos, rot = pose_errors(
        torch.as_tensor(written.poses, dtype=torch.float32),
        torch.as_tensor(truth.poses, dtype=torch.float32),
    )
    summary = summarise_errors(pos, rot, torch.as_tensor(truth.scene_ids(scenes)), scenes)
    return float(summary["pos_median_m"]), float(summary["rot_median_deg"])


@pytest.mark.parametrize("method", ["teacher", "render_compare", "refined"])
def test_localized_test_split_gives_the_runs_figures(
    finished_run: Path, tiny_root: Path, tmp_path: Path, method: str, capsys
) -> None:
    labels = tiny_root / "labels" / "all_test.csv"
    out = tmp_path / "poses.csv"
    argv = [str(finished_run), str(labels), "--out", str(out), "--refine", method]
    assert main(argv) == 0
    printed = capsys.readouterr()
    metrics = json.loads((finished_run / "metrics.json").read_text())
    pos, rot = _medians(out, labels, ["scene00", "scene01"])
    assert pos == pytest.approx(metrics[f"test/{method}/pos_median_m"], rel=1e-4, abs=1e-5)
    assert rot == pytest.approx(metrics[f"test/{method}/rot_median_deg"], rel=1e-4, abs=1e-4)
    if method != "teacher":  # not the teacher's poses passed through
        assert pos != pytest.approx(metrics["test/teacher/pos_median_m"], rel=1e-4)
    assert f"{method}: median {pos:.3f} m" in printed.out
    assert f"pae-localize: {method}: 24/24 images (100 %)" in printed.err
    written = read_labels(out)
    q = torch.as_tensor(written.poses[:, 3:])
    assert (q[:, 0] >= 0).all() and torch.allclose(q.norm(dim=1), torch.ones(len(q)).double())


def test_the_teacher_pass_takes_the_runs_eval_batch_size_unless_given(
    finished_run: Path, tiny_root: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from pae.apps import localization

    sizes: list[int] = []
    estimate = localization.estimate

    def recorded(model, queries, data, intrinsics, width, batch_size, *rest):
        sizes.append(batch_size)
        return estimate(model, queries, data, intrinsics, width, batch_size, *rest)

    monkeypatch.setattr(localization, "estimate", recorded)
    labels = str(tiny_root / "labels" / "all_test.csv")
    out = str(tmp_path / "poses.csv")
    assert main([str(finished_run), labels, "--out", out]) == 0
    assert main([str(finished_run), labels, "--out", out, "--batch-size", "5"]) == 0
    run_config = OmegaConf.load(finished_run / ".hydra" / "config.yaml")
    assert sizes == [run_config.data.eval_batch_size, 5]


def test_a_step_that_fitted_nothing_takes_the_checkpoint_it_was_given(tmp_path: Path) -> None:
    from pae.apps.localization import Run
    from pae.core.checkpoints import CheckpointError

    given = tmp_path / "fitted.ckpt"
    given.write_bytes(b"checkpoint")
    config = OmegaConf.create({"stage": {"steps": ["scene_model"]}, "scene_model_ckpt": None})
    run = Run(tmp_path / "run", config, {}, None)
    with pytest.raises(CheckpointError, match="no scene_model checkpoint"):
        run.checkpoint("scene_model", "render_compare")
    config.scene_model_ckpt = str(given)
    assert run.checkpoint("scene_model", "render_compare") == given
    own = tmp_path / "run" / "checkpoints" / "last.ckpt"
    own.parent.mkdir(parents=True)
    own.write_bytes(b"its own")
    assert run.checkpoint("scene_model", "render_compare") == own, "its own first"
    with pytest.raises(CheckpointError, match="no teacher checkpoint"):
        run.checkpoint("teacher", "teacher")


def test_pae_eval_of_the_runs_checkpoints_gives_the_same_figures(
    finished_run: Path, tiny_root: Path, tmp_path: Path
) -> None:
    """What pae-localize is compared with above: pae-eval's figures of the run's checkpoints."""
    from pae.apps.checkpoint_evaluation import evaluate_checkpoints

    overrides = [
        *tiny_data_overrides(tiny_root),
        *RENDER_COMPARE,
        f"student_ckpt={finished_run / 'student' / 'checkpoints' / 'last.ckpt'}",
        f"scene_model_ckpt={finished_run / 'scene_model' / 'checkpoints' / 'last.ckpt'}",
        "logger={}",
    ]
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("eval", overrides=overrides)
    evaluated = evaluate_checkpoints(cfg, tmp_path)
    metrics = json.loads((finished_run / "metrics.json").read_text())
    for method in ("teacher", "render_compare", "refined"):
        for figure in ("pos_median_m", "rot_median_deg"):
            key = f"test/{method}/{figure}"
            assert evaluated[key] == pytest.approx(metrics[key], rel=1e-5), key


def test_images_and_folders_get_the_teachers_scene_and_pose(
    finished_run: Path, tiny_root: Path, tmp_path: Path
) -> None:
    labels = read_labels(tiny_root / "labels" / "all_test.csv")
    folder = tiny_root / Path(labels.img_path[0]).parent
    single = tiny_root / labels.img_path[-1]
    out = tmp_path / "poses.csv"
    assert main([str(finished_run), str(folder), str(single), "--out", str(out)]) == 0
    written = read_labels(out)
    from_folder = sorted(p for p in folder.iterdir() if p.suffix == ".png")
    assert written.img_path == [str(p) for p in from_folder] + [str(single)]
    assert set(written.split) == {"query"} and set(written.scene) <= {"scene00", "scene01"}
    by_label = tmp_path / "by_label.csv"
    main([str(finished_run), str(tiny_root / "labels" / "all_test.csv"), "--out", str(by_label)])
    expected = dict(zip(labels.img_path, read_labels(by_label).poses.tolist(), strict=True))
    got, want = written.poses[-1].tolist(), expected[labels.img_path[-1]]
    assert all(math.isclose(a, b, abs_tol=1e-6) for a, b in zip(got, want, strict=True))


def test_render_compare_takes_the_gate_and_steps_the_run_applied_at_test(
    finished_run: Path,
) -> None:
    from pae.apps.localization import read_run, render_compare_settings
    from pae.render_compare.scene_decision import SceneRule

    run = read_run(finished_run)
    recorded = {
        "test/render_compare/accept_margin": 0.25,
        "test/render_compare/accept_score": 0.5,
        "test/render_compare/position_sigma_m": 0.125,
        "test/render_compare/rounds": 3.0,
        "test/render_compare/scene_check_below": 0.4,
        "test/render_compare/scene_probe_scale": 3.0,
        "test/render_compare/scene_prior_weight": 0.1,
        "test/render_compare/scene_move_margin": 0.05,
    }
    settings, calibration = render_compare_settings(run._replace(metrics=recorded))
    assert (calibration.accept_margin, calibration.accept_score) == (0.25, 0.5)
    assert calibration.scene == SceneRule(0.4, 3.0, 0.1, 0.05)
    assert settings["position_sigma_m"] == 0.125 and settings["rounds"] == 3
    assert isinstance(settings["rounds"], int) and settings["candidates"] == 4
    settings, calibration = render_compare_settings(run._replace(metrics={}))
    # as configured: accept every refinement; no scene recorded: none checked
    assert (calibration.accept_margin, calibration.accept_score) == (-4.0, -4.0)
    assert calibration.scene == SceneRule()


@pytest.mark.parametrize(
    ("case", "message"),
    [
        ("unreadable", "broken.png: missing or unreadable image"),
        ("no_step", "no scene_model checkpoint"),
        ("method", "--refine nope: unknown method; choose one of ['teacher', 'render_compare'"),
        ("not_a_run", "not a pae-train run directory (no .hydra/config.yaml)"),
    ],
)
def test_mistakes_are_one_line_errors(
    finished_run: Path, tmp_path: Path, capsys, case: str, message: str
) -> None:
    import shutil

    image = tmp_path / "broken.png"
    image.write_bytes(b"not a png")
    run_dir, refine = finished_run, "teacher"
    if case == "no_step":
        run_dir = tmp_path / "teacher_only"
        shutil.copytree(finished_run, run_dir, ignore=shutil.ignore_patterns("scene_model"))
        refine = "render_compare"
    elif case == "method":
        refine = "nope"
    elif case == "not_a_run":
        run_dir = tmp_path
    argv = [str(run_dir), str(image), "--out", str(tmp_path / "o.csv"), "--refine", refine]
    with pytest.raises(SystemExit) as stopped:
        main(argv)
    assert stopped.value.code == 1
    lines = [line for line in capsys.readouterr().err.splitlines() if "error:" in line]
    assert len(lines) == 1 and message in lines[0], lines
    assert not (tmp_path / "o.csv").exists()


def test_the_scene_model_step_logs_a_render_and_compare_gallery(finished_run: Path) -> None:
    """Per scene: rows of query | render at the teacher's estimate | at the refined pose."""
    import cv2
    import numpy as np
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(finished_run / "scene_model"), size_guidance={"images": 0})
    events.Reload()
    for scene in ("scene00", "scene01"):
        [image] = events.Images(f"test/render_compare/gallery/{scene}")
        decoded = cv2.imdecode(np.frombuffer(image.encoded_image_string, np.uint8), 1)
        assert decoded.shape[1] == 3 * (128 + 6)  # three panels of 128 px
        assert decoded.shape[0] > 4 * 128  # four queries
    assert "test/cumulative_errors" in events.Tags()["images"]


def test_the_scene_model_step_logs_trajectories_with_render_compare(finished_run: Path) -> None:
    """Per scene a trajectory figure of the scene-model step: the teacher's estimates in the
    first method colour and render_compare's in the second (the legend and the dots)."""
    import cv2
    import numpy as np
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from pae.callbacks.trajectory import METHOD_RGB

    events = EventAccumulator(str(finished_run / "scene_model"), size_guidance={"images": 0})
    events.Reload()
    for scene in ("scene00", "scene01"):
        [image] = events.Images(f"test/trajectory/{scene}")
        rgb = cv2.imdecode(np.frombuffer(image.encoded_image_string, np.uint8), 1)[..., ::-1]
        for colour in METHOD_RGB[:2]:
            assert (rgb == np.array(colour, np.uint8)).all(-1).sum() > 20, colour


def test_render_compare_from_a_file_of_the_teachers_estimates_is_the_runs(
    finished_run: Path, tiny_root: Path, tmp_path: Path, capsys
) -> None:
    """--init with the teacher's own estimates as result-file lines gives the poses of the
    run's own render_compare; a file missing an image names it."""
    labels = tiny_root / "labels" / "all_test.csv"

    def localize(out: Path, *extra: str) -> torch.Tensor:
        argv = [str(finished_run), str(labels), "--out", str(out), *extra]
        assert main(argv) == 0
        return torch.as_tensor(read_labels(out).poses)

    teacher = localize(tmp_path / "teacher.csv", "--refine", "teacher")
    refined = localize(tmp_path / "rc.csv", "--refine", "render_compare")
    table = read_labels(tmp_path / "teacher.csv")
    lines = [
        f"{name} {' '.join(f'{v:.9f}' for v in pose)}"
        for name, pose in zip(table.img_path, table.poses, strict=True)
    ]
    results = tmp_path / "results.txt"
    results.write_text("\n".join(lines) + "\n")
    init = ["--init", str(results), "--init-format", "lines"]
    from_lines = localize(tmp_path / "b.csv", "--refine", "render_compare", *init)
    # starts as a label file rounds them (3e-8): the same refinement, but for a query or two of
    # this barely trained run, whose float32 search can tip into another basin
    same = (from_lines - refined).abs().amax(1) < 2e-3
    assert same.float().mean() >= 0.9, same
    # a label file's scene column is each image's scene: here the labels' true scenes
    from_labels = localize(
        tmp_path / "a.csv", "--refine", "render_compare", "--init", str(tmp_path / "teacher.csv")
    )
    assert from_labels.shape == refined.shape
    assert not torch.allclose(refined, teacher, atol=2e-2)
    capsys.readouterr()
    results.write_text("\n".join(lines[1:]) + "\n")
    with pytest.raises(SystemExit):
        localize(tmp_path / "c.csv", "--refine", "render_compare", *init)
    errors = [line for line in capsys.readouterr().err.splitlines() if "error:" in line]
    assert len(errors) == 1 and "no start for 1 of 24 images" in errors[0], errors
    assert Path(table.img_path[0]).name in errors[0]
    assert not (tmp_path / "c.csv").exists()


def test_another_apr_s_starts_get_the_gate_chosen_for_any_start(
    finished_run: Path, tiny_root: Path, tmp_path: Path, capsys
) -> None:
    """--init with starts that are not the teacher's takes the gate chosen on the run's
    validation split for starts of any scale (--init-gate auto -> any); --init-gate run keeps
    the run's own."""
    import numpy as np

    labels = tiny_root / "labels" / "all_test.csv"
    teacher = tmp_path / "teacher.csv"
    assert main([str(finished_run), str(labels), "--out", str(teacher)]) == 0
    table = read_labels(teacher)
    moved = table.poses.copy()
    moved[:, :3] += np.random.default_rng(0).normal(0.0, 0.05, (len(moved), 3))
    starts = tmp_path / "other.txt"
    starts.write_text(
        "".join(
            f"{name} {' '.join(f'{v:.9f}' for v in pose)}\n"
            for name, pose in zip(table.img_path, moved, strict=True)
        )
    )
    capsys.readouterr()
    for gate, expected in (("auto", "any"), ("run", "run")):
        out = tmp_path / f"{gate}.csv"
        argv = [str(finished_run), str(labels), "--out", str(out), "--refine", "render_compare"]
        init = ["--init", str(starts), "--init-format", "lines", "--init-gate", gate]
        assert main([*argv, *init]) == 0
        assert f"(render_compare gate: {expected})" in capsys.readouterr().err
        assert read_labels(out).poses.shape == moved.shape


def test_pae_eval_refines_another_apr_s_starts_beside_the_teachers(
    finished_run: Path, tiny_root: Path, tmp_path: Path
) -> None:
    """pae-eval render_compare.init=FILE: the file's starts of the test images (here the
    teacher's own estimates, as pae-localize writes them) get their own method,
    test/render_compare_from_<stem>/..., and the starts' figures, test/start_from_<stem>/...,
    equal to the teacher's; the gate comes from val (val/<method>/accept_margin)."""
    from pae.apps.checkpoint_evaluation import evaluate_checkpoints

    starts = tmp_path / "apr.csv"
    labels = tiny_root / "labels" / "all_test.csv"
    assert main([str(finished_run), str(labels), "--out", str(starts)]) == 0
    overrides = [
        *tiny_data_overrides(tiny_root),
        *RENDER_COMPARE,
        f"student_ckpt={finished_run / 'student' / 'checkpoints' / 'last.ckpt'}",
        f"scene_model_ckpt={finished_run / 'scene_model' / 'checkpoints' / 'last.ckpt'}",
        f"render_compare.init={starts}",
        "logger={}",
    ]
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("eval", overrides=overrides)
    evaluated = evaluate_checkpoints(cfg, tmp_path / "eval")
    assert evaluated["test/start_from_apr/pos_median_m"] == pytest.approx(
        evaluated["test/teacher/pos_median_m"], abs=2e-3
    )
    # the gate keeps a rejected query's start: only accepted queries can end worse than it
    accepted = evaluated["test/render_compare_from_apr/accepted_share"] * 24
    assert accepted == pytest.approx(round(accepted), abs=1e-4), "a share of the 24 queries"
    worse = evaluated["test/render_compare_from_apr/worse_than_start_share"] * 24
    assert worse <= accepted + 1e-4
    assert "val/render_compare_from_apr/accept_margin" in evaluated
    assert evaluated["val/render_compare_from_apr/match_width"] == 0  # no stage configured
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("eval", overrides=[*overrides[:-2], "render_compare.init=/no/such.txt"])
    with pytest.raises(ConfigError, match=r"render_compare.init=/no/such.txt: no such starts"):
        evaluate_checkpoints(cfg, tmp_path / "missing")
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("eval", overrides=[*overrides, "render_compare.init_axes=gl"])
    with pytest.raises(ConfigError, match=r"render_compare.init_axes=gl: choose"):
        evaluate_checkpoints(cfg, tmp_path / "axes")
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("eval", overrides=[*overrides, "render_compare.init_format=hloc"])
    message = rf"^{starts}: render_compare.init_format=hloc, but its header states the pae"
    with pytest.raises(ConfigError, match=message):
        evaluate_checkpoints(cfg, tmp_path / "format")


def test_an_unwritable_out_is_one_line_before_any_work(
    finished_run: Path, tiny_root: Path, tmp_path: Path, capsys
) -> None:
    """--out under a file (a file where a folder should be) or naming a folder: one line
    naming it, before the teacher runs, and nothing written."""
    blocker = tmp_path / "some_file"
    blocker.write_text("not a folder\n")
    labels = tiny_root / "labels" / "all_test.csv"
    for out, says in ((blocker / "out.csv", "is a file, not a folder"), (tmp_path, "is a folder")):
        capsys.readouterr()
        with pytest.raises(SystemExit):
            main([str(finished_run), str(labels), "--out", str(out)])
        err = capsys.readouterr().err
        errors = [line for line in err.splitlines() if "error:" in line]
        assert len(errors) == 1 and says in errors[0] and "--out" in errors[0], err
        assert "Traceback" not in err and "pae-localize: teacher" not in err
    assert blocker.read_text() == "not a folder\n"


def test_a_bad_starts_file_is_one_line_before_any_work(
    finished_run: Path, tiny_root: Path, tmp_path: Path, capsys
) -> None:
    """--init FILE with an image named twice, or lines of 7 numbers without a stated
    convention: one line naming the file's line, before the teacher runs, and nothing
    written."""
    labels = tiny_root / "labels" / "all_test.csv"
    table = read_labels(labels)
    rows = [f"{name} 0 0 0 1 0 0 0" for name in [*table.img_path, table.img_path[0]]]
    starts = tmp_path / "starts.txt"
    starts.write_text("\n".join(rows) + "\n")
    out = tmp_path / "out.csv"
    argv = [str(finished_run), str(labels), "--out", str(out), "--refine", "render_compare"]
    unstated = f"{starts}:1: 7 numbers a line and no header stating their convention: give "
    for init, message in (
        (["--init-format", "lines"], f"{starts}:{len(rows)}: image {table.img_path[0]} repeats"),
        ([], unstated + "--init-format lines (NAME x y z qw qx qy qz, camera-to-world) or "),
    ):
        capsys.readouterr()
        with pytest.raises(SystemExit):
            main([*argv, "--init", str(starts), *init])
        err = capsys.readouterr().err
        errors = [line for line in err.splitlines() if "error:" in line]
        assert len(errors) == 1 and errors[0].startswith(f"pae-localize: error: {message}"), err
        assert "pae-localize: render_compare" not in err and not out.exists()


def test_each_output_format_round_trips_the_same_poses(
    finished_run: Path, tiny_root: Path, tmp_path: Path
) -> None:
    """--format lines and --format hloc are read back by --init's reader and --format ace
    holds each image's 4x4 matrix: all give the poses of the label file written by --format
    csv."""
    import numpy as np

    from pae.core.geometry import quaternion_to_matrix
    from pae.data.pose_files import LINES_HEADER, ace_pose_name
    from pae.data.starts import read_starts

    labels = tiny_root / "labels" / "all_test.csv"
    written = {}
    outs = (("csv", "poses.csv"), ("lines", "poses.txt"), ("hloc", "hloc.txt"), ("ace", "ace"))
    for form, out in outs:
        written[form] = tmp_path / out
        argv = [str(finished_run), str(labels), "--out", str(tmp_path / out), "--format", form]
        assert main(argv) == 0
    table = read_labels(written["csv"])
    assert written["lines"].read_text().startswith(LINES_HEADER)
    lines = read_starts(written["lines"])
    assert lines.names == table.img_path
    np.testing.assert_allclose(lines.poses, table.poses, atol=1e-12)
    hloc = read_starts(written["hloc"], form="hloc")
    assert hloc.names == table.img_path
    np.testing.assert_allclose(hloc.poses, table.poses, atol=1e-9)
    rotations = quaternion_to_matrix(torch.from_numpy(table.poses[:, 3:])).numpy()
    for row, image in enumerate(table.img_path):
        matrix = np.loadtxt(written["ace"] / "poses" / ace_pose_name(image))
        np.testing.assert_allclose(matrix[:3, :3], rotations[row], atol=1e-12)
        np.testing.assert_allclose(matrix[:3, 3], table.poses[row, :3], atol=1e-12)
        assert matrix[3].tolist() == [0.0, 0.0, 0.0, 1.0]
    assert len(list((written["ace"] / "poses").iterdir())) == len(table.img_path)


def test_the_correspondence_stage_the_run_chose_is_read_back_and_fed_as_in_the_run(
    finished_run: Path, tiny_root: Path
) -> None:
    """The stage val chose, recorded in metrics.json, is what pae-localize applies; its
    queries are the files at the match width with the intrinsics the run's data gives them,
    and the run's train views; a run whose metrics record none runs none."""
    from pae.apps import localization as loc
    from pae.apps.match_inputs import match_queries
    from pae.apps.queries import gather_queries
    from pae.render_compare.correspondences import MatchSettings
    from pae.render_compare.queries import match_figures

    run = loc.read_run(finished_run)
    chosen = MatchSettings(width=32, start_views=3, below_score=0.5, render_width=0)
    recorded = {f"test/render_compare/{k}": v for k, v in match_figures(chosen).items()}
    run = run._replace(metrics=recorded)
    assert loc.render_compare_settings(run)[1].match == chosen
    data = loc.data_module(run)
    data.setup()
    queries = gather_queries([tiny_root / "labels" / "all_test.csv"], run.data_root)
    from pae.core.checkpoints import load_teacher

    teacher = load_teacher(run.checkpoint("teacher", "test")).model.eval()

    def uncropped(size: tuple[int, int], focal: object, shorter: int) -> torch.Tensor:
        return loc.query_intrinsics(data.camera, size, shorter, None, focal)

    stated = (run.folder, run.config)
    matching = match_queries(stated, queries, data, teacher, uncropped, chosen)
    images, intrinsics = data.images_at("test", 32)
    torch.testing.assert_close(matching.images, images)  # held as uint8: a quarter of float32
    torch.testing.assert_close(matching.intrinsics, intrinsics)
    assert len(matching.train.poses) == len(data.datasets["train"])
    unrecorded = loc.render_compare_settings(run._replace(metrics={}))[1].match
    assert match_queries(stated, queries, data, teacher, uncropped, unrecorded) is None


def test_pae_eval_tries_the_configured_stages_for_another_apr_s_starts(
    finished_run: Path, tiny_root: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """pae-eval render_compare.init=FILE with render_compare.matches_from_val: the calibration
    for any start tries those stages on the val queries at their match width (and the
    shares of the queries of render_compare.match_shares_from_val), and the stage it keeps
    is recorded (val/<method>/match_*) and applied to the test queries."""
    from pae.apps.checkpoint_evaluation import evaluate_checkpoints
    from pae.callbacks import render_compare_init

    starts = tmp_path / "apr.csv"
    labels = tiny_root / "labels" / "all_test.csv"
    assert main([str(finished_run), str(labels), "--out", str(starts)]) == 0
    stage = {"width": 32, "render_width": 0, "near_start_views": 2}
    tried, refined = [], []
    calibrate, refine = render_compare_init.calibrate_any_start, render_compare_init.refine

    def forced(model, queries, *args):
        tried.append((queries.matching, args[-1].stages(), list(args[-1].stage_shares)))
        chosen, refinement, ladder = calibrate(model, queries, *args)
        return dataclasses.replace(chosen, match=args[-1].stages()[-1]), refinement, ladder

    def spy(model, queries, *args, **kwargs):
        refined.append(queries.matching)
        return refine(model, queries, *args, **kwargs)

    monkeypatch.setattr(render_compare_init, "calibrate_any_start", forced)
    monkeypatch.setattr(render_compare_init, "refine", spy)
    overrides = [
        *tiny_data_overrides(tiny_root),
        *RENDER_COMPARE,
        f"student_ckpt={finished_run / 'student' / 'checkpoints' / 'last.ckpt'}",
        f"scene_model_ckpt={finished_run / 'scene_model' / 'checkpoints' / 'last.ckpt'}",
        f"render_compare.init={starts}",
        f"render_compare.matches_from_val=[{{}},{stage}]".replace("'", "").replace(" ", ""),
        "render_compare.match_shares_from_val=[0.5]",
        "render_compare.oracle=false",
        "logger={}",
    ]
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("eval", overrides=overrides)
    evaluated = evaluate_checkpoints(cfg, tmp_path / "eval")
    matching, stages, shares = tried[-1]
    assert matching is not None and matching.images.shape[-1] == 32
    assert [s.near_start_views for s in stages] == [0, 2] and shares == [0.5]
    assert evaluated["val/render_compare_from_apr/match_width"] == 32
    assert evaluated["val/render_compare_from_apr/match_near_start_views"] == 2
    assert refined[-1] is not None and refined[-1].images.shape[-1] == 32
    assert "test/render_compare_from_apr/match_kept_share" in evaluated
