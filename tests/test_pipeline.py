"""Short teacher -> student -> evaluation runs on the tiny synthetic dataset."""

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import open_dict

from pae.apps.checkpoint_evaluation import evaluate_checkpoints
from pae.core.checkpoints import load_pae, load_teacher
from pae.core.errors import CheckpointError, ConfigError
from pae.train import run
from tests.figures import (
    MAX_ANGLE_DEG,
    WORSE_THAN_MEAN_POSE,
    assert_error_figure,
    label_reference,
)

EXPECTED_METHODS = (
    "teacher",
    "student",
    "student_gt",
    "mean_pose",
    "refined",
    "knn_mean",
    "refined_test_store",
    "knn_mean_test_store",
    "closed_form_k10",
    "latent_knn",
    "pose_descent",
    "guess_initial",
    "guess_refined",
    "guess_refined_test_store",
)
TRUE_ORIENTATION = ("guess_initial", "guess_refined", "guess_refined_test_store")
"""Methods whose queries keep the ground-truth orientation (the random-guess check)."""
MEAN_POSE_FIGURES = ("pos_median_m", "rot_median_deg", "pos_mean_m", "rot_mean_deg")


@pytest.fixture(scope="module")
def pipeline_run(tmp_path_factory: pytest.TempPathFactory, tiny_root: Path) -> Path:
    from hydra import compose, initialize_config_dir
    from omegaconf import open_dict

    from pae import CONFIG_DIR
    from tests.conftest import tiny_overrides

    run_dir = tmp_path_factory.mktemp("pipeline")
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose(
            "train",
            overrides=[*tiny_overrides(tiny_root), "stage=full"],
            return_hydra_config=True,
        )
    with open_dict(cfg):
        cfg.hydra.runtime.output_dir = str(run_dir)
    run(cfg, run_dir)
    return run_dir


def test_pipeline_writes_metrics_checkpoints_and_events(
    pipeline_run: Path, tiny_root: Path
) -> None:
    """The mean-pose baseline and the distance to the store are what the label files give (in
    metres and degrees); every method's error is finite, not 0, and its position error within
    a few times the mean pose's; the random guesses keep the true orientation."""
    metrics = json.loads((pipeline_run / "metrics.json").read_text())
    reference = label_reference(tiny_root, "test")
    for figure in MEAN_POSE_FIGURES:
        assert metrics[f"test/mean_pose/{figure}"] == pytest.approx(reference[figure], rel=1e-5)
    for method in EXPECTED_METHODS:
        for figure in ("pos_median_m", "pos_mean_m"):
            upper = WORSE_THAN_MEAN_POSE * reference[figure]
            assert_error_figure(metrics, f"test/{method}/{figure}", upper)
        for figure in ("rot_median_deg", "rot_mean_deg"):
            if method in TRUE_ORIENTATION:
                assert metrics[f"test/{method}/{figure}"] == pytest.approx(0, abs=1e-3)
            else:
                assert_error_figure(metrics, f"test/{method}/{figure}", MAX_ANGLE_DEG)
        assert f"test/{method}/scene00/pos_median_m" in metrics
    assert metrics["bench/teacher/fit_s"] > 0 and metrics["bench/student/fit_s"] > 0
    assert metrics["test/diagnostics/gt_to_train_m"] == pytest.approx(
        reference["gt_to_train_m"], rel=1e-5
    )
    upper = WORSE_THAN_MEAN_POSE * reference["pos_median_m"]
    assert_error_figure(metrics, "test/diagnostics/estimate_to_train_m", upper)
    assert metrics["test/diagnostics/gt_to_train_per_error"] == pytest.approx(
        metrics["test/diagnostics/gt_to_train_m"] / metrics["test/teacher/pos_median_m"], rel=1e-5
    )
    assert metrics["test/decoder/l1"] > 0
    assert_error_figure(metrics, "test/vrpr/pos_median_m", upper)
    assert metrics["test/vrpr/rot_median_deg"] == pytest.approx(
        metrics["test/teacher/rot_median_deg"]
    )
    for step in ("teacher", "student", "decoder", "rpr"):
        assert (pipeline_run / step / "checkpoints" / "last.ckpt").is_file()
        assert list((pipeline_run / step).glob("events.out.tfevents.*"))


def test_val_figures_come_from_held_out_train_sequences(
    pipeline_run: Path, tiny_root: Path
) -> None:
    import hashlib

    from pae.core.checkpoints import DATA_FINGERPRINT_KEY, read_checkpoint
    from pae.data.labels import read_labels

    metrics = json.loads((pipeline_run / "metrics.json").read_text())
    reference = label_reference(tiny_root, "val")  # a leak of val rows into the store moves it
    for figure in MEAN_POSE_FIGURES:
        assert metrics[f"val/mean_pose/{figure}"] == pytest.approx(reference[figure], rel=1e-5)
    assert metrics["val/diagnostics/gt_to_train_m"] == pytest.approx(
        reference["gt_to_train_m"], rel=1e-5
    )
    upper = WORSE_THAN_MEAN_POSE * reference["pos_median_m"]
    for method in (*EXPECTED_METHODS, "vrpr", "rpr_image", "iapr_1"):
        assert_error_figure(metrics, f"val/{method}/pos_median_m", upper)
    assert metrics["val/teacher/pos_median_m"] != metrics["test/teacher/pos_median_m"]
    table = read_labels(tiny_root / "labels" / "all_train.csv")
    kept = np.ascontiguousarray(table.poses[np.asarray(table.seq) != "seq-06"])
    for step in ("teacher", "student"):  # trained, and stored for retrieval, without seq-06
        checkpoint = read_checkpoint(pipeline_run / step / "checkpoints" / "last.ckpt")
        fingerprint = checkpoint[DATA_FINGERPRINT_KEY]["train_poses_sha256"]
        assert fingerprint == hashlib.sha256(kept.tobytes()).hexdigest()


def test_full_stage_reports_the_relative_regressors(pipeline_run: Path, tiny_root: Path) -> None:
    metrics = json.loads((pipeline_run / "metrics.json").read_text())
    upper = WORSE_THAN_MEAN_POSE * label_reference(tiny_root, "test")["pos_median_m"]
    teacher_rot = metrics["test/teacher/rot_median_deg"]
    for method in ("rpr_image", "rpr_image_test_store", "vrpr"):  # position only
        assert_error_figure(metrics, f"test/{method}/pos_median_m", upper)
        assert metrics[f"test/{method}/rot_median_deg"] == pytest.approx(teacher_rot, rel=1e-4)
    for method in ("rpr_reference", "rpr_reference_test_store", "iapr_1", "iapr_2", "iapr_3"):
        assert_error_figure(metrics, f"test/{method}/pos_median_m", upper)
        assert_error_figure(metrics, f"test/{method}/rot_median_deg", MAX_ANGLE_DEG)
    assert "test/iapr_4/pos_median_m" not in metrics
    assert metrics["test/decoder/psnr_db"] > 0 and metrics["test/decoder/psnr_mean_image_db"] > 0
    for step in ("rpr_image", "iapr"):
        assert (pipeline_run / step / "checkpoints" / "last.ckpt").is_file()


def _events(folder: Path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(folder), size_guidance={"images": 0, "tensors": 0})
    events.Reload()
    return events


def _hparams_experiment(events):
    from tensorboard.plugins.hparams import plugin_data_pb2

    for blob in events.PluginTagToContent("hparams").values():
        data = plugin_data_pb2.HParamsPluginData.FromString(blob)
        if data.HasField("experiment"):
            return data.experiment
    raise AssertionError("no HParams experiment in the event files")


def test_tensorboard_tells_the_story(pipeline_run: Path) -> None:
    """Rendered from the event files: a trajectory figure per scene, the results as TEXT,
    HParams over the val curves with the headline figures first and no per-scene keys, no
    one-point scalar charts of final figures, reconstructions from the step that trains a
    decoder."""
    import cv2

    from pae.callbacks.trajectory import GROUND_TRUTH_RGB, METHOD_RGB

    events = _events(pipeline_run / "student")
    tags = events.Tags()
    for split in ("val", "test"):
        assert {f"{split}/trajectory/scene00", f"{split}/trajectory/scene01"} <= set(tags["images"])
    encoded = events.Images("test/trajectory/scene01")[-1].encoded_image_string
    image = cv2.imdecode(np.frombuffer(encoded, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
    colours = {tuple(c) for c in image.reshape(-1, 3)}
    assert {GROUND_TRUTH_RGB, METHOD_RGB[0], METHOD_RGB[1]} <= colours  # truth, teacher, refined
    assert {"refinement/protocols/text_summary", "results/text_summary"} <= set(tags["tensors"])
    results = events.Tensors("results/text_summary")[-1].tensor_proto.string_val[0].decode()
    assert "refined_test_store *" in results and "scene01" in results

    scalars = tags["scalars"]
    assert "val/refined/pos_median_m" in scalars and "train/loss" in scalars
    assert not [t for t in scalars if t.startswith(("test/", "bench/"))], "one-point charts"
    assert not [t for t in scalars if t.startswith("hparams/")], "copies of the curves"
    experiment = _hparams_experiment(events)
    metrics = [m.name.tag for m in experiment.metric_infos]
    assert set(metrics) <= set(scalars), "HParams metrics are the val curves"
    assert not [t for t in metrics if "/scene0" in t], "per-scene keys in HParams"
    assert metrics[:4] == [
        f"val/{method}/{figure}"
        for method in ("teacher", "student")
        for figure in ("pos_median_m", "rot_median_deg")
    ]
    columns = [h.name for h in experiment.hparam_infos]
    assert columns[:3] == ["stage", "experiment", "data"] and "best_refinement" in columns
    assert "teacher.max_epochs" in columns and "seed" in columns and len(columns) < 30

    decoder_tags = _events(pipeline_run / "decoder").Tags()
    assert "test/reconstructions" in decoder_tags["images"]
    assert "val/decoder/psnr_db" in decoder_tags["scalars"]


def test_every_run_records_its_dataset(pipeline_run: Path, tiny_root: Path) -> None:
    import hashlib

    from omegaconf import OmegaConf

    metrics = json.loads((pipeline_run / "metrics.json").read_text())
    labels = tiny_root.resolve() / "labels" / "all_train.csv"
    assert metrics["data/root"] == str(tiny_root.resolve())
    assert metrics["data/scenes"] == "scene00,scene01"
    assert metrics["data/train/labels"] == str(labels)
    assert metrics["data/train/frames"] == 48 and metrics["data/test/frames"] == 24
    assert metrics["data/train/labels_sha256"] == hashlib.sha256(labels.read_bytes()).hexdigest()
    record = OmegaConf.load(pipeline_run / ".hydra" / "data.yaml")
    assert record.splits.test.sha256 == metrics["data/test/labels_sha256"]


def test_max_epochs_zero_tests_and_saves_the_untrained_model_in_every_stage(
    compose_train, tiny_root: Path, tmp_path: Path
) -> None:
    groups = ("teacher", "student", "decoder", "rpr", "iapr", "scene_model")
    small_scene_model = (
        "scene_model.model.num_voxels=8000",
        "render_compare.refiner.rounds=2",
        "render_compare.refiner.candidates=4",
    )
    overrides = [f"{group}.max_epochs=0" for group in groups]
    metrics = run(
        compose_train("stage=full", *overrides, *small_scene_model, run_dir=tmp_path), tmp_path
    )
    for step in ("teacher", "student", "decoder", "rpr", "rpr_image", "iapr", "scene_model"):
        assert (tmp_path / step / "checkpoints" / "last.ckpt").is_file(), step
    load_teacher(tmp_path / "teacher" / "checkpoints" / "last.ckpt")
    upper = WORSE_THAN_MEAN_POSE * label_reference(tiny_root, "test")["pos_median_m"]
    methods = ("teacher", "student", "refined", "vrpr", "rpr_image", "iapr_3", "render_compare")
    for method in methods:
        assert_error_figure(metrics, f"test/{method}/pos_median_m", upper)
    assert "bench/teacher/fit_s" in metrics


def test_checkpoints_reload_with_weights_only(pipeline_run: Path) -> None:
    teacher = load_teacher(pipeline_run / "teacher" / "checkpoints" / "last.ckpt")
    pae = load_pae(pipeline_run / "student" / "checkpoints" / "last.ckpt")
    assert teacher.scene_names == ["scene00", "scene01"] == pae.scene_names
    assert pae.model.latent_dim == teacher.model.latent_dim
    poses = torch.zeros(2, 7)
    poses[:, 3] = 1
    assert teacher.model.regress(pae.model(poses, torch.tensor([0, 1]))).shape == (2, 7)


def test_bad_checkpoints_give_clear_errors(pipeline_run: Path, tmp_path: Path) -> None:
    teacher_ckpt = pipeline_run / "teacher" / "checkpoints" / "last.ckpt"
    with pytest.raises(CheckpointError, match="not a student checkpoint"):
        load_pae(teacher_ckpt)
    with pytest.raises(CheckpointError, match="checkpoint not found"):
        load_teacher(tmp_path / "nope.ckpt")
    corrupt = tmp_path / "corrupt.ckpt"
    corrupt.write_bytes(b"not a checkpoint at all")
    with pytest.raises(CheckpointError, match=r"corrupt\.ckpt: not a readable checkpoint"):
        load_teacher(corrupt)


def _refined_by_hand(cfg, student_ckpt: Path, weight_model: str) -> dict[str, float]:
    """The test split refined without pae-eval's modules and callback: the checkpoint's
    teacher estimates every test image, a PositionRefiner over the train poses refines them
    (markley orientation), and the errors are summarised."""
    from pae.core.geometry import pose_errors
    from pae.core.metrics import summarise_errors
    from pae.models.base import Latents
    from pae.refine import PoseIndex, PositionRefiner
    from pae.runs.inputs import build_data

    teacher, pae = load_teacher(student_ckpt).model, load_pae(student_ckpt).model
    data = build_data(cfg, augment=False)
    index = PoseIndex(*data.train_poses(), distance="normalized")
    answers, poses, scenes = [], [], []
    with torch.no_grad():
        for batch in data.test_dataloader():
            answers.append(teacher.estimate(data.preprocess(batch["image"], False), batch["scene"]))
            poses.append(batch["pose"])
            scenes.append(batch["scene"])
    estimate = torch.cat([a.pose for a in answers])
    latents = Latents(*(torch.cat([getattr(a.latents, f) for a in answers]) for f in "xq"))
    refiner = PositionRefiner(index, pae, weight_model=weight_model, orientation="markley")
    refined = refiner(latents, estimate, torch.cat([a.scene for a in answers])).poses
    errors = pose_errors(refined, torch.cat(poses))
    figures = summarise_errors(*errors, torch.cat(scenes), data.scene_names)
    return {key: float(value) for key, value in figures.items()}


def test_evaluate_checkpoints_with_each_weight_model(
    pipeline_run: Path, compose_train, tmp_path: Path
) -> None:
    from hydra import compose, initialize_config_dir

    from pae import CONFIG_DIR
    from tests.conftest import tiny_data_overrides

    student_ckpt = pipeline_run / "student" / "checkpoints" / "last.ckpt"
    root = compose_train().data.root
    refined = {}
    for weight_model in ("softmax_logits", "closed_form"):
        with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
            cfg = compose(
                "eval",
                overrides=[
                    f"student_ckpt={student_ckpt}",
                    *tiny_data_overrides(root),
                    f"refine.weight_model={weight_model}",
                    "refine.orientation=markley",
                    "+trainer.enable_progress_bar=false",
                ],
            )
        metrics = evaluate_checkpoints(cfg, tmp_path / weight_model)
        expected = _refined_by_hand(cfg, student_ckpt, weight_model)
        for key, value in expected.items():
            assert metrics[f"test/refined/{key}"] == pytest.approx(value, rel=1e-4, abs=1e-6)
        # markley averages the neighbours' orientations: not the teacher's any more
        assert metrics["test/refined/rot_median_deg"] != metrics["test/teacher/rot_median_deg"]
        refined[weight_model] = metrics["test/refined/pos_median_m"]
    assert refined["softmax_logits"] != refined["closed_form"]


def test_student_without_teacher_checkpoint_is_a_config_error(
    compose_train, tmp_path: Path
) -> None:
    cfg = compose_train("stage=student", run_dir=tmp_path)
    with pytest.raises(ConfigError, match=r"teacher_ckpt=PATH"):
        run(cfg, tmp_path)


def test_student_on_other_scenes_is_rejected(
    pipeline_run: Path, compose_train, tmp_path: Path, tiny_root: Path
) -> None:
    one_scene = tmp_path / "one"
    shutil.copytree(tiny_root, one_scene)
    for split in ("train", "test"):
        shutil.copy(
            one_scene / "labels" / f"scene00_{split}.csv", one_scene / "labels" / f"all_{split}.csv"
        )
    teacher_ckpt = pipeline_run / "teacher" / "checkpoints" / "last.ckpt"
    cfg = compose_train(
        "stage=student", f"teacher_ckpt={teacher_ckpt}", f"data.root={one_scene}", run_dir=tmp_path
    )
    with pytest.raises(CheckpointError, match="trained on scenes"):
        run(cfg, tmp_path / "run")


def test_report_tables_a_run_and_rejects_an_empty_directory(
    pipeline_run: Path, tmp_path: Path, capsys
) -> None:
    from pae.report.tables import main as report

    assert report([str(pipeline_run)]) == 0
    table = capsys.readouterr().out.splitlines()
    assert table[0].startswith("| job | teacher | student | student_gt | refined")
    assert len(table) == 3 and table[2].count("/") >= 7
    assert report([str(tmp_path)]) == 1
    assert "no metrics.json" in capsys.readouterr().err


@pytest.mark.slow
def test_multirun_sweep_writes_one_metrics_file_per_job(
    pipeline_run: Path, tiny_root: Path, tmp_path: Path
) -> None:
    import subprocess
    import sys

    from tests.conftest import tiny_overrides

    teacher_ckpt = pipeline_run / "teacher" / "checkpoints" / "last.ckpt"
    command = [
        sys.executable,
        "-m",
        "pae.train",
        "-m",
        "stage=student",
        f"teacher_ckpt={teacher_ckpt}",
        "pae.L=0,3",
        "student.max_epochs=1",
        f"hydra.sweep.dir={tmp_path}",
        *tiny_overrides(tiny_root),
    ]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-2000:]
    files = sorted(tmp_path.glob("*/metrics.json"))
    assert len(files) == 2
    upper = WORSE_THAN_MEAN_POSE * label_reference(tiny_root, "test")["pos_median_m"]
    figures = [json.loads(f.read_text()) for f in files]
    medians = [assert_error_figure(f, "test/student/pos_median_m", upper) for f in figures]
    assert medians[0] != medians[1], "pae.L=0 and pae.L=3 train different students"


def _raw_seven_scenes_copy(synthetic_root: Path, raw_root: Path) -> None:
    """Rewrite a synthetic dataset in the raw 7-Scenes layout (colour PNG + 4x4 pose file)."""
    from pae.core.geometry import quaternion_to_matrix
    from pae.data.labels import read_labels

    for split, split_file in (("train", "TrainSplit.txt"), ("test", "TestSplit.txt")):
        table = read_labels(synthetic_root / "labels" / f"all_{split}.csv")
        rotations = quaternion_to_matrix(torch.from_numpy(table.poses[:, 3:])).numpy()
        sequences: dict[tuple[str, str], int] = {}
        for i, (scene, seq) in enumerate(zip(table.scene, table.seq, strict=True)):
            frame = sequences.setdefault((scene, seq), 0)
            sequences[(scene, seq)] += 1
            folder = raw_root / scene / seq
            folder.mkdir(parents=True, exist_ok=True)
            shutil.copy(synthetic_root / table.img_path[i], folder / f"frame-{frame:06d}.color.png")
            matrix = torch.eye(4, dtype=torch.float64).numpy()
            matrix[:3, :3], matrix[:3, 3] = rotations[i], table.poses[i, :3]
            lines = "\n".join(" ".join(f"{v:.9e}" for v in row) for row in matrix)
            (folder / f"frame-{frame:06d}.pose.txt").write_text(lines + "\n")
        for scene in {s for s, _ in sequences}:
            numbers = sorted(int(q.split("-")[1]) for s, q in sequences if s == scene)
            (raw_root / scene / split_file).write_text("".join(f"sequence{n}\n" for n in numbers))


def test_real_data_layout_trains_end_to_end(tiny_root: Path, tmp_path: Path) -> None:
    from hydra import compose, initialize_config_dir
    from omegaconf import open_dict

    from pae import CONFIG_DIR
    from pae.data_cli import main as pae_data

    raw = tmp_path / "7Scenes"
    _raw_seven_scenes_copy(tiny_root, raw)
    assert pae_data(["convert", "7scenes", str(raw), str(raw / "labels")]) == 0
    overrides = [
        "data=seven_scenes",
        f"data.root={raw}",
        "data.scenes=[scene01]",
        "data.shorter_edge=32",
        "data.crop=28",
        "data.batch_size=8",
        "data.num_workers=0",
        "teacher.max_epochs=1",
        "trainer.check_val_every_n_epoch=1",
        "callbacks=minimal",
        "logger=csv",
        "+trainer.enable_progress_bar=false",
    ]
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose("train", overrides=overrides, return_hydra_config=True)
    with open_dict(cfg):
        cfg.hydra.runtime.output_dir = str(tmp_path / "run")
    metrics = run(cfg, tmp_path / "run")
    assert "test/teacher/scene00/pos_median_m" not in metrics, "only the chosen scene is used"
    assert (tmp_path / "run" / "metrics.csv").is_file()
    # the converted labels hold the synthetic poses, and the run measured on them
    from pae.data.labels import read_labels

    converted = read_labels(raw / "labels" / "scene01_test.csv")
    original = read_labels(tiny_root / "labels" / "all_test.csv")
    original = original.select([i for i, s in enumerate(original.scene) if s == "scene01"])
    np.testing.assert_allclose(converted.poses, original.poses, atol=1e-6)
    train_table = read_labels(raw / "labels" / "scene01_train.csv")
    held_out = np.asarray(train_table.seq) == max(train_table.seq)  # the validation sequence
    train = train_table.poses[~held_out]  # the mean pose is the remaining train rows' mean
    distances = np.linalg.norm(converted.poses[:, :3] - train[:, :3].mean(axis=0), axis=1)
    assert metrics["test/mean_pose/pos_median_m"] == pytest.approx(np.median(distances), rel=1e-5)
    teacher = load_teacher(tmp_path / "run" / "checkpoints" / "last.ckpt")
    assert teacher.scene_names == ["scene01"]


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("refine.weight_model=lstsq", "unknown refine.weight_model 'lstsq'"),
        ("refine.orientation=slerp", "unknown refine.orientation 'slerp'"),
        ("refine.distance=cosine", "unknown refine.distance 'cosine'"),
        (
            "refine.alternatives.latent_knn._target_=pae.refine.Nope",
            "refine.alternatives.latent_knn: Error loading 'pae.refine.Nope'",
        ),
        ("refine._target_=pae.nowhere.Refiner", "refine: Error loading 'pae.nowhere.Refiner'"),
    ],
)
def test_bad_refine_options_name_the_key(compose_train, override: str, message: str) -> None:
    from pae.runs.trainer import refinement_callbacks

    with pytest.raises(ConfigError, match=message):
        refinement_callbacks(compose_train(override))


def test_refine_groups_instantiate_their_callback(compose_train) -> None:
    from pae.callbacks.refinement import TestTimeRefinement
    from pae.runs.trainer import refinement_callbacks

    assert refinement_callbacks(compose_train("refine=none")) == []
    (callback,) = refinement_callbacks(compose_train("refine=knn_closed_form", "refine.k=5"))
    assert isinstance(callback, TestTimeRefinement)
    assert callback.protocols.weight_model == "closed_form" and callback.protocols.k == 5
    assert sorted(callback.alternatives) == ["closed_form_k10", "latent_knn", "pose_descent"]


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("student.input=image", "unknown student.input 'image'"),
        ("student.latent_loss=cosine", "unknown student.latent_loss 'cosine'"),
        ("pae.latent_dim=64", "pae.latent_dim=64 does not match the teacher's latent size 256"),
    ],
)
def test_bad_student_options_name_the_key(
    pipeline_run: Path, compose_train, tmp_path: Path, override: str, message: str
) -> None:
    teacher_ckpt = pipeline_run / "teacher" / "checkpoints" / "last.ckpt"
    cfg = compose_train("stage=student", f"teacher_ckpt={teacher_ckpt}", override, run_dir=tmp_path)
    with pytest.raises(ConfigError, match=message):
        run(cfg, tmp_path)


def test_resume_continues_an_interrupted_run(
    compose_train, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import lightning as L

    import pae.runs.trainer
    from pae.core.checkpoints import read_checkpoint

    class Interrupt(L.Callback):
        def on_train_epoch_start(self, trainer: L.Trainer, pl_module: L.LightningModule) -> None:
            if trainer.current_epoch == 1:
                raise RuntimeError("interrupted")

    build_trainer = pae.runs.trainer.build_trainer
    with monkeypatch.context() as patch:
        patch.setattr(
            pae.runs.trainer,
            "build_trainer",
            lambda cfg, step_dir, epochs, callbacks, **kw: build_trainer(
                cfg, step_dir, epochs, [*callbacks, Interrupt()], **kw
            ),
        )
        with pytest.raises(RuntimeError, match="interrupted"):
            run(compose_train(run_dir=tmp_path), tmp_path)
    last = tmp_path / "checkpoints" / "last.ckpt"
    steps_per_epoch = read_checkpoint(last)["global_step"]
    assert steps_per_epoch > 0 and not (tmp_path / "metrics.json").exists()
    metrics = run(compose_train("resume=true", run_dir=tmp_path), tmp_path)
    assert read_checkpoint(last)["global_step"] == 2 * steps_per_epoch
    assert json.loads((tmp_path / "metrics.json").read_text()) == pytest.approx(metrics)


@pytest.mark.parametrize(
    "options",
    [("student.input=teacher",), ("student.cache_latents=false", "student.latent_loss=mse")],
)
def test_student_variants_train(
    pipeline_run: Path, compose_train, tmp_path: Path, options: tuple[str, ...]
) -> None:
    from pae.core.checkpoints import read_checkpoint

    teacher_ckpt = pipeline_run / "teacher" / "checkpoints" / "last.ckpt"
    cfg = compose_train(
        "stage=student", f"teacher_ckpt={teacher_ckpt}", "refine=none", *options, run_dir=tmp_path
    )
    metrics = run(cfg, tmp_path)
    assert "test/refined/pos_median_m" not in metrics
    hparams = read_checkpoint(tmp_path / "checkpoints" / "last.ckpt")["hyper_parameters"]
    chosen = dict(option.split("=") for option in options)
    assert hparams["pae_input"] == chosen.get("student.input", "gt")
    assert hparams["latent_loss"] == chosen.get("student.latent_loss", "l2")
    cached = chosen.get("student.cache_latents", "true") == "true"
    assert ("bench/student/latent_cache_hit" in metrics) == cached


def test_pae_eval_runs_the_image_methods_of_their_checkpoints(
    pipeline_run: Path, compose_train, tmp_path: Path
) -> None:
    """vRPR, image RPR and iAPR from their checkpoints give the figures their training run
    tested (same teacher, networks, data and store)."""
    from hydra import compose, initialize_config_dir

    from pae import CONFIG_DIR
    from pae.apps.checkpoint_evaluation import evaluate_methods
    from pae.config.validation import validate_eval_config
    from tests.conftest import tiny_data_overrides

    paths = [
        pipeline_run / step / "checkpoints" / "last.ckpt" for step in ("rpr", "rpr_image", "iapr")
    ]
    root = compose_train().data.root
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cfg = compose(
            "eval",
            overrides=[
                f"student_ckpt={pipeline_run / 'student' / 'checkpoints' / 'last.ckpt'}",
                *tiny_data_overrides(root),
                f"method_ckpts=[{','.join(map(str, paths))}]",
                "+trainer.enable_progress_bar=false",
            ],
        )
    validate_eval_config(cfg)
    metrics = evaluate_methods(cfg, tmp_path)
    trained = json.loads((pipeline_run / "metrics.json").read_text())
    for method in ("vrpr", "rpr_image", "iapr_3"):
        for figure in ("pos_median_m", "rot_median_deg"):
            key = f"test/{method}/{figure}"
            assert metrics[key] == pytest.approx(trained[key], rel=1e-5, abs=1e-6), key
    with pytest.raises(
        CheckpointError,
        match="a stage=student checkpoint, but method_ckpts takes checkpoints of stage=rpr",
    ):
        with open_dict(cfg):
            cfg.method_ckpts = [str(pipeline_run / "student" / "checkpoints" / "last.ckpt")]
        evaluate_methods(cfg, tmp_path / "wrong")
