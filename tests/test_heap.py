"""Returning freed heap memory to the system."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

from pae.core.heap import _malloc_trim, release_free_heap


def _resident_kb() -> int:
    return int(Path("/proc/self/status").read_text().split("VmRSS:")[1].split()[0])


@pytest.mark.skipif(
    not sys.platform.startswith("linux") or _malloc_trim() is None, reason="glibc's malloc_trim"
)
def test_freed_small_tensors_leave_the_resident_set_once_released() -> None:
    small = [torch.ones(25_000) for _ in range(2_000)]  # 100 kB each: on the C heap, 200 MB
    joined = torch.cat(small)
    del small
    before = _resident_kb()
    assert release_free_heap()
    assert before - _resident_kb() > 100_000  # kB: most of the 200 MB given back
    assert joined.sum().item() == 50_000_000  # the live tensor is untouched
