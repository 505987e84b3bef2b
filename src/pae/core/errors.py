"""The errors a user can cause, in one place: each message is one line naming the file, row or
key. Entry points print them as ``<program>: error: <message>`` (``pae.report.tables``) instead of
a traceback; anything else is a bug and keeps its traceback."""

from __future__ import annotations

import os


class ConfigError(ValueError):
    """A configuration value that cannot work; the message names the key."""


class LabelError(ValueError):
    """A problem in a label or raw pose file; ``str()`` is one line ``FILE:LINE: problem``."""

    def __init__(self, path: str | os.PathLike[str], line: int | None, problem: str) -> None:
        self.path = str(path)
        self.line = line
        self.problem = " ".join(problem.split())
        where = self.path if line is None else f"{self.path}:{line}"
        super().__init__(f"{where}: {self.problem}")


class LabelWarning(UserWarning):
    """Label values that were repaired while reading (e.g. quaternions normalised)."""


class OrientationWarning(LabelWarning):
    """A label file without an orientation column whose orientations look world-to-camera."""


class RepeatedImageWarning(LabelWarning):
    """Label file rows whose image an earlier row already has."""


class ImageError(OSError):
    """A missing or unreadable image; the message names the file."""


class CheckpointError(RuntimeError):
    """A missing, unreadable, wrong-kind or mismatched checkpoint; the message names the file."""


class BackboneError(RuntimeError):
    """A backbone that cannot be built as configured (unknown name, weights unavailable)."""


class ExportError(RuntimeError):
    """A model that cannot be written as ONNX; the message names the model and its layer."""


class DivergenceError(RuntimeError):
    """A non-finite training loss, or non-finite figures: nothing of it is a result."""


class DiskFullError(OSError):
    """No space left on a device while writing a file; the message names both."""


class RunDirInUseError(RuntimeError):
    """Another live process holds the run directory's lock; the message names its pid."""
