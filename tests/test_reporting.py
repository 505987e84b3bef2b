import json
from pathlib import Path

import pytest

from pae.core.atomic import write_json_atomic
from pae.core.error_reporting import reporting_errors
from pae.core.errors import ConfigError, ImageError
from pae.report.tables import format_results_table


def test_user_errors_become_one_line_and_exit_1(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info, reporting_errors("pae-train"):
        raise ConfigError("unknown refine.method 'icp'")
    assert exit_info.value.code == 1
    assert capsys.readouterr().err == "pae-train: error: unknown refine.method 'icp'\n"


def test_worker_errors_show_the_original_message(capsys: pytest.CaptureFixture[str]) -> None:
    message = (
        "Caught ImageError in DataLoader worker process 0.\n"
        "Original Traceback (most recent call last):\n"
        '  File "worker.py", line 375, in _worker_loop\n'
        "    data = fetcher.fetch(index)\n"
        "pae.data.transforms.ImageError: /data/a.png: missing or unreadable image\n"
    )
    with pytest.raises(SystemExit), reporting_errors("pae-train"):
        raise ImageError(message)
    assert capsys.readouterr().err == "pae-train: error: /data/a.png: missing or unreadable image\n"


def test_other_errors_are_not_swallowed() -> None:
    with pytest.raises(ZeroDivisionError), reporting_errors("pae-train"):
        _ = 1 / 0


def test_metrics_json_is_replaced_atomically(tmp_path: Path) -> None:
    path = tmp_path / "run" / "metrics.json"
    write_json_atomic(path, {"test/teacher/pos_median_m": 1.5})
    write_json_atomic(path, {"test/teacher/pos_median_m": 0.5})
    assert json.loads(path.read_text()) == {"test/teacher/pos_median_m": 0.5}
    assert [p.name for p in path.parent.iterdir()] == ["metrics.json"]


def test_results_table_lists_methods_in_order_with_scenes() -> None:
    metrics = {
        f"test/{method}/{scene}pos_median_m": value
        for method, value in (("teacher", 0.5), ("refined", 0.4))
        for scene in ("", "a/", "b/")
    } | {
        f"test/{method}/{scene}rot_median_deg": 3.0
        for method in ("teacher", "refined")
        for scene in ("", "a/", "b/")
    }
    lines = format_results_table(metrics).splitlines()
    assert lines[1].split() == ["method", "overall", "a", "b"]
    assert lines[3].startswith("teacher") and lines[4].startswith("refined")
    assert lines[3].count("0.500 / 3.00") == 3


def _metrics(teacher: float, refined: float) -> dict[str, float]:
    figures = {}
    for method, pos in (("teacher", teacher), ("refined", refined), ("refined_test_store", 0.1)):
        figures[f"test/{method}/pos_median_m"] = pos
        figures[f"test/{method}/rot_median_deg"] = 5.0
    figures["test/latent_knn/pos_median_m"] = teacher
    figures["test/latent_knn/rot_median_deg"] = 5.0
    figures["test/diagnostics/gt_to_train_per_error"] = 0.7
    return figures


def test_results_table_marks_test_store_rows_and_prints_the_ratio() -> None:
    table = format_results_table(_metrics(0.5, 0.45))
    rows = [line.split()[0] for line in table.splitlines()[3:6]]
    assert rows == ["teacher", "refined", "latent_knn"]
    assert "refined_test_store *" in table and "uses test labels" in table
    assert "teacher median error: 0.70" in table


def test_results_table_gives_the_scene_accuracy_before_and_after_render_compare() -> None:
    metrics = _metrics(0.5, 0.45) | {"test/teacher/scene_accuracy": 0.9}
    assert "teacher scene accuracy: 90.0 %\n" in format_results_table(metrics) + "\n"
    metrics["test/render_compare/scene_accuracy"] = 0.975
    line = "teacher scene accuracy: 90.0 %; after render_compare: 97.5 %"
    assert line in format_results_table(metrics)


def test_compare_table_has_a_column_per_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from pae.report.tables import main

    for name, refined in (("a", 0.45), ("b", 0.6)):
        write_json_atomic(tmp_path / name / "metrics.json", _metrics(0.5, refined))
    args = ["--compare", str(tmp_path / "a"), str(tmp_path / "b"), "--names", "room,street"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "| method | room | street |" in out
    assert "| refined | 0.450 / 5.00 (-10.0%) | 0.600 / 5.00 (+20.0%) |" in out
    assert (
        "| refined_test_store * |" in out and "| the same ÷ teacher's median error | 0.70 |" in out
    )
    assert main([*args[:-1], "one"]) == 1


def test_the_best_refinement_is_chosen_on_validation_and_reported_on_test() -> None:
    from pae.report.tables import best_refinement

    metrics = {
        "test/teacher/pos_median_m": 1.0,
        "test/refined/pos_median_m": 0.5,
        "test/render_compare/pos_median_m": 0.6,
        "val/refined/pos_median_m": 0.9,
        "val/render_compare/pos_median_m": 0.4,
    }
    assert best_refinement(metrics) == "render_compare"
    without_val = {k: v for k, v in metrics.items() if k.startswith("test/")}
    assert best_refinement(without_val) == "refined"
    # never a method worse than the teacher where it is chosen
    assert best_refinement(metrics | {"val/teacher/pos_median_m": 0.5}) == "render_compare"
    assert best_refinement(metrics | {"val/teacher/pos_median_m": 0.3}) is None


def test_report_out_is_checked_before_any_work_and_written_whole(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from pae.report import tables

    write_json_atomic(tmp_path / "run" / "metrics.json", _metrics(0.5, 0.45))
    blocker = tmp_path / "file"
    blocker.write_text("in the way\n")
    with monkeypatch.context() as patched:
        patched.setattr(tables, "seed_report", lambda *a, **k: pytest.fail("read the runs"))
        for out, says in ((blocker / "out.md", "is a file, not a folder"), (tmp_path, "folder")):
            assert tables.main([str(tmp_path / "run"), "--out", str(out)]) == 1
            captured = capsys.readouterr()
            assert captured.out == ""
            assert captured.err.startswith(f"pae-report: error: --out {out}: ")
            assert says in captured.err and captured.err.count("\n") == 1
    out = tmp_path / "reports" / "run.md"
    out.parent.mkdir()
    out.write_text("an older report\n")
    assert tables.main([str(tmp_path / "run"), "--out", str(out)]) == 0
    assert out.read_text() == capsys.readouterr().out
    assert "| 0.500 / 5.00 | 0.450 / 5.00 |" in out.read_text()
    assert [p.name for p in out.parent.iterdir()] == ["run.md"]
