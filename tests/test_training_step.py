"""What every training step shares: its figures reach the loggers on the steps Lightning
writes on-step figures, and its random draws are seeded per batch."""

from __future__ import annotations

import csv
import warnings
from pathlib import Path

import lightning as L
import pytest
import torch
from lightning.pytorch.loggers import CSVLogger
from torch import Tensor, nn
from torch.utils.data import DataLoader, TensorDataset

from pae.core.streams import derived_seed, seed_global_for_batch
from pae.lit.base import PaeModule


class _Line(PaeModule):
    """A linear fit whose step logs its loss and weight, through ``log_train`` or, with
    ``every_step``, through Lightning's own ``log_dict`` on every step."""

    def __init__(self, every_step: bool) -> None:
        super().__init__(lambda params: torch.optim.SGD(params, lr=0.1))
        self.line = nn.Linear(1, 1)
        self.every_step = every_step

    def training_step(self, batch: list[Tensor], batch_idx: int) -> Tensor:
        x, y = batch
        loss = ((self.line(x) - y) ** 2).mean()
        figures = {"train/loss": loss, "train/weight": self.line.weight[0, 0]}
        if self.every_step:
            self.log_dict(figures)
        else:
            self.log_train(figures)
        return loss

    def trainable_parameters(self) -> list[nn.Parameter]:
        return list(self.parameters())


def _logged_rows(tmp_path: Path, every_step: bool) -> list[dict[str, str]]:
    torch.manual_seed(0)
    x = torch.linspace(-1, 1, 46)[:, None]
    data = DataLoader(TensorDataset(x, 3 * x + 1), batch_size=2)
    logger = CSVLogger(tmp_path, name=str(every_step), version=0)
    trainer = L.Trainer(
        max_epochs=3,
        log_every_n_steps=10,
        logger=logger,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        limit_val_batches=0,
    )
    trainer.fit(_Line(every_step), data)
    with open(Path(logger.log_dir) / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_training_figures_reach_the_loggers_as_if_logged_every_step(tmp_path: Path) -> None:
    logged = _logged_rows(tmp_path, every_step=False)
    assert logged == _logged_rows(tmp_path, every_step=True)
    assert [int(row["step"]) for row in logged] == list(range(9, 69, 10)), "69 steps, every 10th"
    weights = [float(row["train/weight"]) for row in logged]
    losses = [float(row["train/loss"]) for row in logged]
    assert abs(weights[-1] - 3) < abs(weights[0] - 3) and losses[-1] < losses[0], (
        "it fits y = 3x + 1"
    )


def test_log_train_outside_a_trainer_logs_nothing() -> None:
    """Lightning's own ``log_dict`` warns outside a Trainer; ``log_train`` does not call it,
    and the step still returns its loss: (2 * 1 + 0 - 1)^2 = 1 for the line y = 2x."""
    module = _Line(every_step=False)
    with torch.no_grad():
        module.line.weight.fill_(2.0)
        module.line.bias.zero_()
    logged: list[dict] = []
    module.log_dict = lambda figures, **_: logged.append(figures)  # type: ignore[method-assign]
    batch = [torch.ones(2, 1), torch.ones(2, 1)]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert module.training_step(batch, 0).item() == 1.0
        assert logged == []
        with pytest.raises(UserWarning, match="trainer"):
            _Line(every_step=True).training_step(batch, 0)


def test_a_batch_draws_what_torch_manual_seed_of_its_derived_seed_draws() -> None:
    seed_global_for_batch(7, "teacher", 2, 5)
    drawn = torch.rand(4)
    torch.manual_seed(derived_seed(7, "teacher/rank0/epoch2", 5))
    assert torch.equal(drawn, torch.rand(4))
    seed_global_for_batch(7, "teacher", 2, 6)
    assert not torch.equal(drawn, torch.rand(4))
