"""What one run remembers while it runs: the warnings it has already given and the inputs it
has already judged, so each is said once per run. A run starts a fresh context
(:func:`start_run`); code that says something once asks :func:`current_run`. The context is a
``contextvars`` variable, so runs in other threads or tasks do not share it."""

from __future__ import annotations

import contextvars
import dataclasses


@dataclasses.dataclass
class RunContext:
    """said: the once-per-run messages already given (by key); other_data: checkpoints read
    that were trained on other data -> what differs (``allow_other_data=true``)."""

    said: set[str] = dataclasses.field(default_factory=set)
    other_data: dict[str, str] = dataclasses.field(default_factory=dict)

    def first_time(self, key: str) -> bool:
        """Whether ``key`` is said for the first time in this run (and mark it said)."""
        if key in self.said:
            return False
        self.said.add(key)
        return True


_CURRENT: contextvars.ContextVar[RunContext] = contextvars.ContextVar("pae_run")


def start_run() -> RunContext:
    """A fresh context for the run that starts now."""
    context = RunContext()
    _CURRENT.set(context)
    return context


def current_run() -> RunContext:
    """The running run's context (a fresh one where no run started it)."""
    try:
        return _CURRENT.get()
    except LookupError:
        return start_run()
