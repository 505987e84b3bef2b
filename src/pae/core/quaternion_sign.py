"""The sign convention of stored quaternions, for numpy arrays and torch tensors alike (this
module imports neither, so label files are read without loading torch)."""

from __future__ import annotations

from typing import Any, TypeVar

QuaternionArray = TypeVar("QuaternionArray", bound=Any)


def canonical_sign(q: QuaternionArray) -> QuaternionArray:
    """``q`` or ``−q``, whichever has ``qw >= 0``, for quaternions ``[..., 4]`` (numpy arrays or
    torch tensors); the norm is left as it is (a sign flip, exact). The one place that fixes
    the sign of stored quaternions: ``pae.core.geometry.canonicalize_quaternion``, the label readers
    and the raw converters use it."""
    return q * (1 - 2 * (q[..., :1] < 0))
