"""The benchmark harnesses (pae-bench): figures that agree with each other and with known sizes."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from pae.bench.refinement import (
    bench_first_layer_gain,
    bench_index,
    bench_refinement,
    mlp_flops_per_query,
)
from tests.test_refine import random_poses


def test_mlp_flops_per_query_on_known_sizes() -> None:
    # k=3, D=512: layers 1536 -> 192 -> 96 -> 48 -> 3, 318,096 multiply-adds per pass;
    # 3 iterations of forward + backward (3 passes) and a last forward: 10 passes, 2 FLOP each
    assert mlp_flops_per_query(3, 512, 3) == 2 * 318_096 * 10
    assert mlp_flops_per_query(1, 2, 0) == 2 * (2 * 64 + 64 * 32 + 32 * 16 + 16 * 1)


def test_matmul_speed_is_the_products_flops_over_its_time(monkeypatch: pytest.MonkeyPatch) -> None:
    """A 1024 x 1024 float32 product is 2 * 1024^3 FLOP: timed at 2 ms, 1073.74 GFLOP/s."""
    from pae.bench import refinement

    timed = []

    def two_milliseconds(run, repeats=1):
        timed.append(tuple(run().shape))
        return 0.002

    monkeypatch.setattr(refinement, "_seconds", two_milliseconds)
    assert refinement.matmul_gflops(size=1024) == pytest.approx(1073.741824)
    assert timed == [(1024, 1024)], "the product it times"


REFINE = "bench/refine/"
REFINEMENT_TIMES = (
    "batched",
    "tensor_ops",
    "per_query",
    "public_loop",
    "softmax_logits",
    "closed_form",
)


def test_bench_refinement_reports_times_work_and_their_direction() -> None:
    """Every figure is reported, finite and positive; the work counted is that of the sizes
    asked for; the batched path beats the loops; the arithmetic it does stays below what
    the measured matrix-product speed allows in its time (a figure in the wrong units would
    not)."""
    figures = bench_refinement(n_queries=40, public_queries=10)
    ratios = ("speedup", "speedup_vs_per_query", "roofline_fraction", "stored_weight_ratio")
    expected = {f"bench/refine/{name}_ms_per_query" for name in REFINEMENT_TIMES}
    expected |= {f"bench/refine/{name}" for name in ratios}
    expected |= {f"bench/refine/{name}" for name in ("mflop_per_query", "mflop_done_per_query")}
    assert set(figures) == expected | {"bench/refine/matmul_gflops"}
    for key, value in figures.items():
        assert math.isfinite(value) and value > 0, (key, value)
    assert figures["bench/refine/mflop_per_query"] == pytest.approx(6.36192)
    # the arithmetic done: the closed-form first layer and the skipped units do far less
    done = figures["bench/refine/mflop_done_per_query"]
    assert 0.01 < done < 6.36192 / 3
    # both ratios are arithmetic at the measured matrix-product speed over the batched time
    gflops, batched = (
        figures["bench/refine/matmul_gflops"],
        figures[f"{REFINE}batched_ms_per_query"],
    )
    for ratio, mflop in (("roofline_fraction", done), ("stored_weight_ratio", 6.36192)):
        at_matmul_speed_ms = mflop * 1e6 / (gflops * 1e9) * 1e3
        assert figures[f"{REFINE}{ratio}"] == pytest.approx(at_matmul_speed_ms / batched)
    assert figures["bench/refine/roofline_fraction"] < 1
    # one batched call against 40 optimiser loops or 10 public loops: faster under any load
    assert figures["bench/refine/speedup"] > 1 and figures["bench/refine/speedup_vs_per_query"] > 1
    batched = figures["bench/refine/batched_ms_per_query"]
    assert figures["bench/refine/per_query_ms_per_query"] > batched


def test_bench_index_on_label_files(tmp_path: Path) -> None:
    generator = torch.Generator().manual_seed(13)
    header = "scene,split,seq,img_path,t1,t2,t3,q1,q2,q3,q4\n"
    files = []
    for scene, n_train in (("alpha", 40), ("beta", 25)):
        for split, n in (("train", n_train), ("test", 10)):
            poses = random_poses(n, generator)
            poses[:, 3:] *= torch.where(poses[:, 3:4] < 0, -1.0, 1.0)
            rows = [
                f"{scene},{split},seq1,{scene}/seq1/frame{i:05d}.png,"
                + ",".join(f"{v:.9f}" for v in pose.tolist())
                for i, pose in enumerate(poses)
            ]
            path = tmp_path / f"{scene}_{split}.csv"
            path.write_text(header + "\n".join(rows) + "\n")
            if split == "train":
                files.append(path)
    figures = bench_index(files, n_queries=15, k=3)
    assert figures["bench/index/n_poses"] == 65
    assert figures["bench/index/memory_mb"] > 0 and figures["bench/index/ms_per_query"] > 0
    assert figures["bench/index/same_as_tensor_search"] == 1.0


def test_bench_first_layer_gain_figures() -> None:
    """The closed-form series beats the plain chunked sum it replaces."""
    figures = bench_first_layer_gain(batch=8, repeats=5)
    names = ("first_layer_series_ms", "first_layer_direct_ms", "first_layer_series_speedup")
    assert set(figures) == {f"bench/refine/{name}" for name in names}
    for key, value in figures.items():
        assert math.isfinite(value) and value > 0, (key, value)
    assert figures["bench/refine/first_layer_series_speedup"] > 1


def test_bench_sweep_splits_the_speedup_into_cache_and_parallel_shares(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    from pae.bench import cli

    commands: list[tuple[str, ...]] = []

    def fake_train(*overrides: str) -> float:
        commands.append(overrides)
        if "hydra/launcher=joblib" in overrides:
            return 5.0
        return 20.0 if "student.latent_cache_dir=null" in overrides else 8.0

    monkeypatch.setattr(cli, "_train", fake_train)
    figures = cli.bench_sweep(tmp_path, 2, 10, 2, 32)
    assert figures["bench/sweep/speedup"] == pytest.approx(20.0 / 5.0)
    assert figures["bench/sweep/cache_speedup"] == pytest.approx(20.0 / 8.0)
    assert figures["bench/sweep/parallel_speedup"] == pytest.approx(8.0 / 5.0)
    teacher, uncached, cached, parallel = commands
    assert "stage=teacher" in teacher
    for sweep in (uncached, cached, parallel):
        assert {"-m", "stage=student", "pae.L=0,3,6", "refine=none"} <= set(sweep)
    caches = [next(o for o in c if o.startswith("student.latent_cache_dir=")) for c in commands[2:]]
    assert len(set(caches)) == 2  # each cached sweep starts with its own empty cache
    assert "hydra/launcher=joblib" not in cached and "hydra.launcher.n_jobs=2" in parallel


def test_sequence_frames_share_out_7_scenes_size() -> None:
    from pae.bench.scale import SEVEN_SCENES_TEST, SEVEN_SCENES_TRAIN, sequence_frames

    assert (SEVEN_SCENES_TRAIN, SEVEN_SCENES_TEST) == (26_000, 17_000)
    full = sequence_frames(26_000, 17_000)
    assert sum(n for _, split, _, n in full if split == "train") == 26_000
    assert sum(n for _, split, _, n in full if split == "test") == 17_000
    assert ("stairs", "train", "seq-06", 500) in full and ("chess", "test", "seq-05", 1000) in full
    small = sequence_frames(61, 20, scenes=2)
    assert {name for name, *_ in small} == {"chess", "fire"}
    assert sum(n for _, split, _, n in small if split == "train") == 61
    assert min(n for *_, n in small) >= 1
    with pytest.raises(ValueError, match="frames for"):
        sequence_frames(3, 20, scenes=2)  # 6 train sequences


def test_write_scale_dataset_links_few_files_into_7_scenes_labels(tmp_path: Path) -> None:
    import cv2

    from pae.bench.scale import write_scale_dataset
    from pae.data.holdout import held_out_rows
    from pae.data.labels import read_labels

    counts = write_scale_dataset(tmp_path, 60, 20, 2, 64, 48, unique=8)
    assert counts == {"train": 60, "test": 20, "files": 2 * (8 + 2)}
    train = read_labels(tmp_path / "labels" / "all_train.csv")
    test = read_labels(tmp_path / "labels" / "all_test.csv")
    assert (len(train), len(test)) == (60, 20) and train.scene_names == ["chess", "fire"]
    inodes = {(tmp_path / p).stat().st_ino for p in train.img_path + test.img_path}
    assert len(inodes) == counts["files"]  # hard links to the unique files
    assert cv2.imread(str(tmp_path / train.img_path[0])).shape == (48, 64, 3)
    held, _ = held_out_rows(train, 1, 0.1)  # data=seven_scenes: one sequence per scene
    assert sorted({train.seq[i] for i in held.nonzero()[0]}) == ["seq-02", "seq-06"]
    spread = train.poses[:, :3].max(0) - train.poses[:, :3].min(0)
    assert (spread[:2] > 0.2).all() and (spread[:2] < 3.0 + 1e-9).all()


def test_run_measured_reads_the_childs_peak_rss(tmp_path: Path) -> None:
    import sys

    from pae.bench.scale import run_measured

    grow = (
        "import time; b = bytearray(300_000_000); b[::4096] = b'x' * len(b[::4096]); time.sleep(1)"
    )
    figures = run_measured([sys.executable, "-c", grow], tmp_path / "log")
    assert 300 < figures["rss_mb"] < 1000 and figures["s"] > 1
    with pytest.raises(RuntimeError, match="failed"):
        run_measured([sys.executable, "-c", "raise SystemExit(3)"], tmp_path / "log")


@pytest.mark.slow
def test_bench_render_compare_scale_at_tiny_size(tmp_path: Path) -> None:
    from pae.bench.scale import bench_render_compare_scale

    figures = bench_render_compare_scale(60, 20, 2, 64, 48, root=tmp_path, batches_per_epoch=2)
    prefix = "bench/render_compare"
    keys = ("peak_rss_mb", "scale_fit_s", "scale_refine_s", "scale_teacher_peak_rss_mb")
    for key in (*keys, "scale_store_s", "scale_store_peak_rss_mb"):
        assert figures[f"{prefix}/{key}"] > 0, key
    assert figures[f"{prefix}/scale_train_images"] == 60
    assert figures[f"{prefix}/scale_fit_images"] == 40  # one of 4 and 2 sequences held out
    assert figures[f"{prefix}/scale_test_images"] == 20
    assert list(tmp_path.iterdir()) == []  # everything removed


def test_pae_bench_runs_the_scale_bench_only_when_asked(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from pae.bench import cli

    calls = []
    monkeypatch.setattr(
        cli,
        "bench_render_compare_scale",
        lambda *args, **kwargs: calls.append((args, kwargs)) or {"bench/x": 1.0},
    )
    assert "render_compare_scale" in cli.BENCHMARKS
    assert "render_compare_scale" not in cli.DEFAULT_BENCHMARKS
    argv = ["--only", "render_compare_scale", "--scale-train", "60", "--scale-test", "20"]
    cli.main([*argv, "--scale-scenes", "2", "--scale-size", "64", "48"])
    assert calls == [((60, 20, 2, 64, 48), {"root": None})]
    assert '"bench/x": 1.0' in capsys.readouterr().out


def test_bench_fingerprint_measures_both_hashes_on_the_same_images(tiny_root: Path) -> None:
    from pae.bench.fingerprint import PREFIX, bench_fingerprint
    from pae.data.fingerprint import CACHE_NAME
    from pae.data.labels import read_labels

    cache = tiny_root / CACHE_NAME
    before = cache.read_bytes() if cache.exists() else None  # other tests' fingerprints
    figures = bench_fingerprint(tiny_root, repeats=2)
    names = ("images", "mb", "full_ms", "sampled_ms", "cached_first_ms", "cached_rerun_ms")
    names += ("full_over_sampled", "full_over_rerun", "full_mb_per_s")
    assert set(figures) == {f"{PREFIX}/{name}" for name in names}
    table = read_labels(tiny_root / "labels" / "all_train.csv")
    assert figures[f"{PREFIX}/images"] == len(table.img_path)
    size = sum((tiny_root / path).stat().st_size for path in table.img_path)
    assert figures[f"{PREFIX}/mb"] == size / 1e6
    ratio = figures[f"{PREFIX}/full_ms"] / figures[f"{PREFIX}/sampled_ms"]
    assert figures[f"{PREFIX}/full_over_sampled"] == pytest.approx(ratio)
    rerun = figures[f"{PREFIX}/full_ms"] / figures[f"{PREFIX}/cached_rerun_ms"]
    assert figures[f"{PREFIX}/full_over_rerun"] == pytest.approx(rerun)
    after = cache.read_bytes() if cache.exists() else None
    assert after == before, "the bench's cache is kept apart from the data"


def test_bench_fingerprint_at_seven_scenes_size_scales_the_per_image_cost(tmp_path: Path) -> None:
    from pae.bench.fingerprint import SEVEN_SCENES_IMAGES, bench_fingerprint_seven_scenes_size

    figures = bench_fingerprint_seven_scenes_size(tmp_path, count=4)
    prefix = "bench/fingerprint_7scenes_size"
    assert figures[f"{prefix}/images"] == 4
    assert figures[f"{prefix}/mb"] > 4 * 0.3  # photograph-like PNGs, not flat ones
    per_image_s = figures[f"{prefix}/full_ms"] / 4 / 1000
    expected = per_image_s * SEVEN_SCENES_IMAGES
    assert figures[f"{prefix}/full_s_for_7scenes"] == pytest.approx(expected)
    rerun_s = figures[f"{prefix}/cached_rerun_ms"] / 4 / 1000 * SEVEN_SCENES_IMAGES
    assert figures[f"{prefix}/cached_rerun_s_for_7scenes"] == pytest.approx(rerun_s)


def test_contention_runs_the_work_alone_then_beside_a_busy_process_it_stops(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import subprocess

    from pae.bench import contention

    started: list[subprocess.Popen] = []
    popen = subprocess.Popen

    def start(*args, **kwargs) -> subprocess.Popen:
        started.append(popen(*args, **kwargs))
        return started[-1]

    monkeypatch.setattr(contention.subprocess, "Popen", start)
    busy_while_running = []
    figures = contention.alone_and_beside_busy(
        lambda: busy_while_running.append([p.poll() is None for p in started]), repeats=2
    )
    assert set(figures) == {"alone_s", "busy_s"}
    # warm-up and first alone run: none; beside: one running; alone again: stopped
    assert busy_while_running == [[], [], [True], [False], [False, True]]
    assert all(p.poll() is not None for p in started)


def test_contention_compares_pae_wait_with_openmp_default(monkeypatch: pytest.MonkeyPatch) -> None:
    import json
    import subprocess

    from pae.bench import contention
    from pae.core.threads import WAIT_VARIABLES

    monkeypatch.setenv("OMP_WAIT_POLICY", "ACTIVE")
    sleep, spin = contention.wait_environment("sleep"), contention.wait_environment("spin")
    assert not set(WAIT_VARIABLES) & sleep.keys()  # pae's own setting in the child
    assert spin["GOMP_SPINCOUNT"] == "300000" and "OMP_WAIT_POLICY" not in spin
    seconds = {
        "300000": {"teacher_epoch": {"alone_s": 2.0, "busy_s": 40.0}},
        None: {"teacher_epoch": {"alone_s": 2.5, "busy_s": 4.0}},
    }

    def run(command, env, **kwargs) -> subprocess.CompletedProcess:
        result = seconds[env.get("GOMP_SPINCOUNT")]
        result["render_compare"] = {"alone_s": 1.0, "busy_s": 1.5}
        return subprocess.CompletedProcess(command, 0, "the threads line\n" + json.dumps(result))

    monkeypatch.setattr(contention.subprocess, "run", run)
    figures = contention.bench_contention(repeats=1)
    assert figures["bench/contention/teacher_epoch_slowdown"] == pytest.approx(1.6)
    assert figures["bench/contention/spin/teacher_epoch_slowdown"] == pytest.approx(20.0)
    assert figures["bench/contention/teacher_epoch_busy_speedup"] == pytest.approx(10.0)
    assert figures["bench/contention/teacher_epoch_alone_ratio"] == pytest.approx(1.25)
    assert figures["bench/contention/render_compare_slowdown"] == pytest.approx(1.5)


def test_pae_bench_runs_the_contention_bench_only_when_asked(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from pae.bench import cli

    monkeypatch.setattr(cli, "bench_contention", lambda: {"bench/contention/x": 1.0})
    assert "contention" in cli.BENCHMARKS
    assert "contention" not in cli.DEFAULT_BENCHMARKS
    cli.main(["--only", "contention"])
    printed = capsys.readouterr()
    assert '"bench/contention/x": 1.0' in printed.out
    assert printed.err.startswith("threads: ")


@pytest.mark.slow
def test_contention_measures_both_works_in_this_process() -> None:
    from pae.bench.contention import WORKS, measure

    figures = measure(repeats=1)
    assert set(figures) == set(WORKS)
    assert all(f["alone_s"] > 0 and f["busy_s"] > 0 for f in figures.values())


def test_bench_real_starts_measures_the_experiment_s_scene_model_in_a_fresh_process() -> None:
    """The refiner against conf/experiment/real_starts.yaml's scene model: its time per query
    here, and a child process's peak memory and time per query; the correspondence stage's
    peak memory in chunks and all at once, each in a child, and their ratio."""
    from omegaconf import OmegaConf

    from pae import CONFIG_DIR
    from pae.bench.real_starts import bench_real_starts, real_starts_grid

    model = OmegaConf.load(Path(CONFIG_DIR) / "experiment" / "real_starts.yaml").scene_model.model
    grid = real_starts_grid()
    assert grid.samples_per_ray == model.samples_per_ray
    assert 0.9 * model.num_voxels <= grid.grids[0].grid[0, 0].numel() <= 1.1 * model.num_voxels
    figures = bench_real_starts(queries=4, held=6, matched=3)
    prefix = "bench/render_compare_real_starts"
    stage = ("stage_peak_rss_mb", "stage_whole_peak_rss_mb", "stage_peak_rss_ratio")
    stage += ("stage_ms_per_query", "stage_whole_ms_per_query")
    assert set(figures) == {
        f"{prefix}/{k}" for k in ("ms_per_query", "peak_rss_mb", "child_ms_per_query", *stage)
    }
    assert all(value > 0 for value in figures.values())
    assert 200 < figures[f"{prefix}/peak_rss_mb"] < 4000
    ratio = figures[f"{prefix}/stage_peak_rss_mb"] / figures[f"{prefix}/stage_whole_peak_rss_mb"]
    assert figures[f"{prefix}/stage_peak_rss_ratio"] == pytest.approx(ratio)


def test_bench_export_times_both_engines_on_the_same_images() -> None:
    """Both engines' figures at both batch sizes, finite and positive, and the ratio is the
    quotient of the times it reports."""
    pytest.importorskip("onnxruntime")
    from pae.bench.export import bench_export

    name = "posenet_small_cnn_56px"
    figures = bench_export((name,), batch=3, repeats=1, seconds=0.01)
    assert figures["bench/export/threads"] == torch.get_num_threads()
    for size in (1, 3):
        key = f"bench/export/{name}/batch_{size}"
        times = [figures[f"{key}/{engine}_ms_per_image"] for engine in ("torch", "onnxruntime")]
        assert all(math.isfinite(t) and t > 0 for t in times)
        assert figures[f"{key}/torch_over_onnxruntime"] == pytest.approx(times[0] / times[1])
    assert len(figures) == 1 + 2 * 3
