"""What a run prints: each line once, without third-party advertisements or warnings known to
be harmless, and progress lines for long loops (rendering, training epochs)."""

from __future__ import annotations

import logging
import time
import warnings
from collections.abc import Callable

HARMLESS_WARNINGS = (
    # Lightning's own pytree helper still tests `isinstance(spec, LeafSpec)` (torch >= 2.9)
    (r"`isinstance\(treespec, LeafSpec\)` is deprecated", FutureWarning),
    # frozen teachers, PAEs and decoders stay in eval mode inside the modules that train on them
    (r".*module\(s\) in eval mode", UserWarning),
)
"""(message pattern, category) of the warnings a run never shows."""
ADVERTISEMENTS = ("💡 Tip:",)
"""How the lines begin that Lightning logs to advertise its services."""
REDUNDANT = (
    # each step's own summary line says it is done, and after how long
    "`Trainer.fit` stopped:",
    "Loading `train_dataloader` to estimate number of stepping batches",
)
"""How the lines begin that Lightning logs and a run's own lines already say."""


class _EachLineOnce(logging.Filter):
    """Drops Lightning's advertisements and REDUNDANT lines, and every line already logged
    since the run started (the GPU/TPU banner and the held-out split of each step)."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: set[str] = set()

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        if message.startswith(ADVERTISEMENTS + REDUNDANT) or message in self.seen:
            return False
        self.seen.add(message)
        return True


def quiet_third_party() -> None:
    """Silence HARMLESS_WARNINGS, Lightning's ADVERTISEMENTS and REDUNDANT lines, and log
    each line once from now on: a line repeated by every step (Lightning's GPU/TPU banner)
    is logged the first time only; and, under Hydra, which logs to the console and to the
    run's log file, Lightning's own console handler, which would print every line a second
    time, is removed."""
    for message, category in HARMLESS_WARNINGS:
        warnings.filterwarnings("ignore", message=message, category=category)
    for name in ("lightning.pytorch.utilities.rank_zero", "lightning.fabric.utilities.rank_zero"):
        logger = logging.getLogger(name)
        for old in [f for f in logger.filters if isinstance(f, _EachLineOnce)]:
            logger.removeFilter(old)
        logger.addFilter(_EachLineOnce())
    lightning = logging.getLogger("lightning")
    if logging.getLogger().handlers and lightning.propagate:
        for handler in list(lightning.handlers):
            if type(handler) is logging.StreamHandler:
                lightning.removeHandler(handler)


def say(line: str) -> None:
    """Print one line of a run's progress (on the first process only under DDP), through the
    `lightning.pytorch` logger: once on the console, and into Hydra's log file of the run."""
    from lightning.pytorch.utilities import rank_zero_info

    rank_zero_info(line)


def duration(seconds: float) -> str:
    """Seconds as `m:ss`, or `h:mm:ss` from an hour on."""
    minutes, secs = divmod(round(max(seconds, 0.0)), 60)
    hours, minutes = divmod(minutes, 60)
    return f"{hours}:{minutes:02d}:{secs:02d}" if hours else f"{minutes}:{secs:02d}"


class Progress:
    """``progress(done, total)`` for a long loop: a line ``{label}: done/total {unit} (p %),
    elapsed, ETA`` through ``emit`` at the first call, then at most every ``every_s`` seconds,
    and when the loop is done."""

    def __init__(
        self, label: str, unit: str, emit: Callable[[str], None], every_s: float = 10.0
    ) -> None:
        self.label, self.unit, self.emit, self.every_s = label, unit, emit, every_s
        self.started = time.perf_counter()
        self.shown_at: float | None = None

    def __call__(self, done: int, total: int) -> None:
        now = time.perf_counter()
        due = self.shown_at is None or now - self.shown_at >= self.every_s
        if not (due or done >= total):
            return
        self.shown_at = now
        elapsed = now - self.started
        eta = elapsed / done * (total - done) if 0 < done < total else None
        self.emit(
            f"{self.label}: {done}/{total} {self.unit} ({100 * done / max(total, 1):.0f} %), "
            f"{duration(elapsed)} elapsed" + (f", ETA {duration(eta)}" if eta is not None else "")
        )
