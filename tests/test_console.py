"""What runs print: progress lines, each log line once, no third-party noise; --help."""

from __future__ import annotations

import logging
import warnings
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

import pae.callbacks.progress as progress_module
from pae.callbacks.progress import EpochProgress
from pae.core.console import Progress, duration, quiet_third_party
from tests.test_faults import pae_command


def test_duration_and_throttled_progress(monkeypatch: pytest.MonkeyPatch) -> None:
    assert (duration(5), duration(65.4), duration(3725)) == ("0:05", "1:05", "1:02:05")
    now = [100.0]
    monkeypatch.setattr("pae.core.console.time.perf_counter", lambda: now[0])
    lines: list[str] = []
    progress = Progress("rendering out", "frames", lines.append, every_s=10)
    for done, at in ((10, 102.0), (20, 104.0), (30, 113.0), (40, 114.0)):
        now[0] = at
        progress(done, 40)
    assert lines == [
        "rendering out: 10/40 frames (25 %), 0:02 elapsed, ETA 0:06",  # the first call
        "rendering out: 30/40 frames (75 %), 0:13 elapsed, ETA 0:04",  # 10 s later
        "rendering out: 40/40 frames (100 %), 0:14 elapsed",  # done
    ]


def _trainer(epoch: int, bar: object | None = None, **metrics: float) -> SimpleNamespace:
    return SimpleNamespace(
        progress_bar_callback=bar,
        sanity_checking=False,
        current_epoch=epoch,
        max_epochs=4,
        num_training_batches=2,
        callback_metrics={k.replace("__", "/"): torch.tensor(v) for k, v in metrics.items()},
    )


def test_epoch_progress_says_step_epoch_loss_validation_and_eta(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    lines: list[str] = []
    monkeypatch.setattr(progress_module, "say", lines.append)
    now = [0.0]
    monkeypatch.setattr(progress_module.time, "perf_counter", lambda: now[0])
    callback = EpochProgress(step="teacher", every_s=30)
    callback.on_train_start(_trainer(0), None)
    for epoch, losses in ((0, (3.0, 1.0)), (1, (1.0, 0.5))):
        trainer = _trainer(epoch, val__teacher__pos_median_m=0.5, val__teacher__rot_median_deg=9.25)
        callback.on_train_epoch_start(trainer, None)
        for batch, loss in enumerate(losses):
            now[0] += 15
            callback.on_train_batch_end(trainer, None, {"loss": torch.tensor(loss)}, None, batch)
        if epoch == 1:
            callback.on_validation_end(trainer, None)
        callback.on_train_epoch_end(trainer, None)
    assert lines == [
        "teacher: training 4 epochs of 2 batches",
        "teacher: epoch 1/4, loss 2, 0:30 elapsed, ETA 1:30",
        "teacher: epoch 2/4, loss 0.75, val teacher 0.500 m / 9.25°, 1:00 elapsed, ETA 1:00",
    ]
    lines.clear()
    slow = _trainer(2)
    slow.num_training_batches = 4
    callback.on_train_epoch_start(slow, None)
    for batch in range(3):  # 40 s a batch: a line within the epoch after each
        now[0] += 40
        callback.on_train_batch_end(slow, None, {"loss": torch.tensor(1.0)}, None, batch)
    # 2.25 of 4 epochs in 100 s: 1.75 epochs left take 78 s
    assert lines[0] == "teacher: epoch 3/4, batch 1/4, loss 1, 1:40 elapsed, ETA 1:18"
    assert len(lines) == 3 and lines[2].startswith("teacher: epoch 3/4, batch 3/4,")
    lines.clear()
    with_bar = _trainer(0, bar=object())
    callback.on_train_start(with_bar, None)
    now[0] += 100
    callback.on_train_batch_end(with_bar, None, {"loss": torch.tensor(1.0)}, None, 0)
    callback.on_train_epoch_end(with_bar, None)
    assert lines == [], "a progress bar is shown: no lines"


def test_third_party_noise_is_silenced_and_lightning_lines_print_once(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import lightning  # noqa: F401  (adds its console handler)

    root = logging.getLogger()
    monkeypatch.setattr(root, "handlers", [logging.NullHandler()])  # as under Hydra
    lightning_logger = logging.getLogger("lightning")
    monkeypatch.setattr(lightning_logger, "handlers", list(lightning_logger.handlers))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        quiet_third_party()
        warnings.warn(
            "`isinstance(treespec, LeafSpec)` is deprecated, use ...", FutureWarning, stacklevel=1
        )
    assert not caught
    assert not [h for h in lightning_logger.handlers if type(h) is logging.StreamHandler]
    tip = logging.LogRecord("x", logging.INFO, "", 0, "💡 Tip: try litlogger", None, None)
    line = logging.LogRecord("x", logging.INFO, "", 0, "GPU available: False", None, None)
    rank_zero = logging.getLogger("lightning.pytorch.utilities.rank_zero")
    assert not rank_zero.filter(tip) and rank_zero.filter(line)


@pytest.mark.parametrize("program", ["train", "evaluate"])
def test_help_shows_stages_examples_outputs_and_groups_without_the_config(
    program: str, tmp_path: Path
) -> None:
    result = pae_command(program, "--help", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    text = result.stdout
    name = "pae-train" if program == "train" else "pae-eval"
    examples = text.split("Examples:\n")[1].split("\n\n")[0].splitlines()
    assert len(examples) == 5 and all(f"{name} " in line for line in examples)
    assert "Outputs: outputs/" in text and "metrics.json" in text
    assert "refine: knn_affine, knn_closed_form, none" in text  # a group's options
    assert f"{name} --cfg job --package GROUP" in text
    assert "_target_" not in text, "no config dump"
    assert len(text.splitlines()) < 70
    if program == "train":
        stages = text.split("Stages (stage=NAME, default teacher):\n")[1].split("\n\n")[0]
        names = [line.split()[0] for line in stages.splitlines()]
        conf = Path(__file__).resolve().parents[1] / "conf" / "stage"
        assert sorted(names) == sorted(p.stem for p in conf.glob("*.yaml"))
