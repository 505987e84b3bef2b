"""Torch's large CPU tensors with and without transparent huge pages, side by side.

    PYTHONPATH=src python experiments/bench/huge_pages.py

Runs the same work in two fresh processes, ``THP_MEM_ALLOC_ENABLE=0`` then ``=1`` (torch
reads it at its first allocation): the demo's small CNN (``backbone=small_cnn``) forward on
a batch of 64 images of 224 px, three times after a warm-up, ms per image and the minor page
faults and system seconds of those three; and the machine's float32 matmul rate (ten
2048 × 2048 products on pae's threads, GFLOP/s) to say how fast the day's cores were.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

WORK = """
import json, resource, time
import pae
from pae.core.threads import configure_threads
configure_threads()
import torch
from pae.models.backbones import _small_cnn
a = torch.randn(2048, 2048)
a @ a
start = time.perf_counter()
for _ in range(10):
    a @ a
gflops = 10 * 2 * 2048**3 / (time.perf_counter() - start) / 1e9
net, _ = _small_cnn()
net.eval()
images = torch.rand(64, 3, 224, 224)
with torch.inference_mode():
    net(images)
    before = resource.getrusage(resource.RUSAGE_SELF)
    start = time.perf_counter()
    for _ in range(3):
        net(images)
    seconds = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_SELF)
print(json.dumps({
    "matmul_gflops": round(gflops, 1),
    "cnn_ms_per_image": round(1000 * seconds / 192, 2),
    "cnn_minor_faults": after.ru_minflt - before.ru_minflt,
    "cnn_system_s": round(after.ru_stime - before.ru_stime, 2),
}))
"""


def main() -> None:
    results = {}
    for setting in ("0", "1"):
        environ = {**os.environ, "THP_MEM_ALLOC_ENABLE": setting}
        done = subprocess.run(
            [sys.executable, "-c", WORK], env=environ, capture_output=True, text=True, check=True
        )
        results[f"THP_MEM_ALLOC_ENABLE={setting}"] = json.loads(done.stdout.splitlines()[-1])
    print(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
