"""pae's work beside one busy process, side by side in one run: a teacher training epoch on
tiny synthetic data and a render-and-compare batch, each alone and with one CPU-bound process
(pure Python spinning, started and stopped here) on the same cores.

Each wait setting runs in its own process (the OpenMP runtimes read it when they load):
``sleep``, pae's default (``OMP_WAIT_POLICY=PASSIVE``, pae.core.threads), and ``spin``,
OpenMP's own default, which pae ran with before (``GOMP_SPINCOUNT=300000``: GNU OpenMP's
built-in spinning of about 3 ms; ``KMP_BLOCKTIME=200``: Intel's). Within a process the work
runs alone and beside the busy process in turn, ``repeats`` times each; each figure is the
median.

``python -m pae.bench.contention`` is that process: it prints one JSON object of seconds.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from pae.core.threads import WAIT_VARIABLES

WAITS: dict[str, dict[str, str]] = {
    "sleep": {},
    "spin": {"GOMP_SPINCOUNT": "300000", "KMP_BLOCKTIME": "200"},
}
"""The wait settings compared: the environment's wait variables of each ({}: pae's own)."""
WORKS = ("teacher_epoch", "render_compare")
"""The work measured, in the names of its figures."""
BUSY_PROCESS = "while True: pass"
"""The busy process's program: one core's worth of pure Python."""


def teacher_epoch(root: Path, train_frames: int = 320) -> Callable[[], None]:
    """One training epoch of the demo's teacher (conf/experiment/demo.yaml) on 2 synthetic
    scenes of ``train_frames`` 64 px frames each (written under ``root``): augmented 56 px
    crops, batches of 32, the learned pose loss and the scene classifier's, Adam."""
    import torch
    from hydra.utils import instantiate

    from pae.config.schemas import compose_config
    from pae.data.datamodule import PoseDataModule
    from pae.synthetic import write_synthetic_dataset

    write_synthetic_dataset(root, scenes=2, train_frames=train_frames, test_frames=4)
    cfg = compose_config("train", ["experiment=demo"])
    data = PoseDataModule(
        root=str(root),
        train_labels=str(root / "labels" / "all_train.csv"),
        test_labels=str(root / "labels" / "all_test.csv"),
        shorter_edge=64,
        crop=56,
        color_jitter=tuple(cfg.data.color_jitter),
        batch_size=32,
        cache_images=True,
    )
    data.setup()
    teacher = instantiate(cfg.teacher.model, n_scenes=data.n_scenes).train()
    loss = instantiate(cfg.teacher.loss)
    optimizer = torch.optim.Adam([*teacher.parameters(), *loss.parameters()], lr=1e-3)

    def epoch() -> None:
        for batch in data.train_dataloader():
            pred, latents = teacher(data.preprocess(batch["image"], train=True), batch["scene"])
            total = loss(pred, batch["pose"]).total
            if latents.scene_logits is not None:
                total = total + torch.nn.functional.cross_entropy(
                    latents.scene_logits, batch["scene"]
                )
            optimizer.zero_grad()
            total.backward()
            optimizer.step()

    return epoch


def render_compare_batch(queries: int = 96) -> Callable[[], None]:
    """The refiner at its default settings on ``queries`` queries of the render_compare
    benchmark's room (pae.bench.render_compare), batched as the callback runs it."""
    from pae.bench.render_compare import bench_queries, room_grid
    from pae.render_compare.refiner import RenderCompareRefiner

    model = room_grid(2)
    images, intrinsics, start, scene_ids = bench_queries(queries, 2, 56, seed=0)
    refiner = RenderCompareRefiner.configured(model)
    return lambda: refiner(images, intrinsics, start, scene_ids)


def _seconds(run: Callable[[], None]) -> float:
    start = time.perf_counter()
    run()
    return time.perf_counter() - start


def alone_and_beside_busy(run: Callable[[], None], repeats: int) -> dict[str, float]:
    """Median seconds of ``run`` alone and beside a busy process, in turn, ``repeats`` times
    each (after one run that compiles and warms up): ``alone_s``, ``busy_s``."""
    run()
    alone, busy = [], []
    for _ in range(repeats):
        alone.append(_seconds(run))
        spinner = subprocess.Popen([sys.executable, "-c", BUSY_PROCESS])
        try:
            time.sleep(0.3)  # the busy process running before the work starts
            busy.append(_seconds(run))
        finally:
            spinner.kill()
            spinner.wait()
    return {"alone_s": statistics.median(alone), "busy_s": statistics.median(busy)}


def measure(repeats: int) -> dict[str, dict[str, float]]:
    """Each of WORKS alone and beside a busy process (``alone_and_beside_busy``), in this
    process's wait setting, on the threads pae.core.threads gives it."""
    from pae.core.threads import configure_threads

    print(configure_threads().summary(), file=sys.stderr)
    with tempfile.TemporaryDirectory() as tmp:
        epoch = teacher_epoch(Path(tmp))
        batch = render_compare_batch()
        return {
            "teacher_epoch": alone_and_beside_busy(epoch, repeats),
            "render_compare": alone_and_beside_busy(batch, repeats),
        }


def wait_environment(wait: str) -> dict[str, str]:
    """This process's environment with the wait variables of ``wait`` (one of WAITS) only."""
    environ = {k: v for k, v in os.environ.items() if k not in WAIT_VARIABLES}
    return environ | WAITS[wait]


def bench_contention(repeats: int = 3) -> dict[str, float]:
    """`bench/contention/...`: for each work (WORKS) its seconds alone and beside a busy
    process and their ratio, ``{work}_slowdown`` (busy / alone) under pae's wait setting and
    ``spin/{work}_slowdown`` under OpenMP's default; ``{work}_busy_speedup`` (spin's busy
    seconds / sleep's) and ``{work}_alone_ratio`` (sleep's alone seconds / spin's: what
    sleeping costs on idle cores)."""
    seconds = {}
    for wait in WAITS:
        result = subprocess.run(
            [sys.executable, "-m", "pae.bench.contention", "--repeats", str(repeats)],
            env=wait_environment(wait),
            capture_output=True,
            text=True,
        )
        if result.returncode != 0:
            raise RuntimeError(f"pae.bench.contention ({wait}) failed: {result.stderr[-2000:]}")
        seconds[wait] = json.loads(result.stdout.splitlines()[-1])
    figures = {}
    for wait, prefix in (("sleep", "bench/contention"), ("spin", "bench/contention/spin")):
        for work in WORKS:
            alone, busy = seconds[wait][work]["alone_s"], seconds[wait][work]["busy_s"]
            figures[f"{prefix}/{work}_alone_s"] = alone
            figures[f"{prefix}/{work}_busy_s"] = busy
            figures[f"{prefix}/{work}_slowdown"] = busy / alone
    for work in WORKS:
        figures[f"bench/contention/{work}_busy_speedup"] = (
            seconds["spin"][work]["busy_s"] / seconds["sleep"][work]["busy_s"]
        )
        figures[f"bench/contention/{work}_alone_ratio"] = (
            seconds["sleep"][work]["alone_s"] / seconds["spin"][work]["alone_s"]
        )
    return figures


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pae.bench.contention", description=__doc__)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    print(json.dumps(measure(args.repeats)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
