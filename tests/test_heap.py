"""Returning freed heap memory to the system."""

from __future__ import annotations

import subprocess
import sys

import pytest

from pae.core.heap import _malloc_trim


@pytest.mark.skipif(
    not sys.platform.startswith("linux") or _malloc_trim() is None, reason="glibc's malloc_trim"
)
def test_freed_small_tensors_leave_the_resident_set_once_released() -> None:
    """In a fresh interpreter (the heap as no earlier test left it): 2,000 tensors of 100 kB
    (on the C heap, 200 MB) freed below a live one (so that freeing them cannot shrink the
    heap from its top) stay resident until ``release_free_heap`` returns most of them."""
    code = """
import torch
from pathlib import Path
from pae.core.heap import release_free_heap
def resident_kb():
    return int(Path("/proc/self/status").read_text().split("VmRSS:")[1].split()[0])
small = [torch.ones(25_000) for _ in range(2_000)]
joined = torch.cat(small)
pin = torch.ones(25_000)  # above the freed ones on the heap
del small
before = resident_kb()
released = release_free_heap()
print(released, before - resident_kb(), joined.sum().item(), pin.sum().item())
"""
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    released, returned_kb, joined_sum, _ = done.stdout.split()
    assert released == "True"
    assert int(returned_kb) > 100_000  # kB: most of the 200 MB given back
    assert float(joined_sum) == 50_000_000  # the live tensor is untouched
