"""Render-and-compare at the real-starts experiment's settings and 7-Scenes' size: the scene
model of ``conf/experiment/real_starts.yaml`` (460,000 voxels, 128 samples per ray) over a
room the size of a 7-Scenes scene's bounds, queries compared at 128 px with a 64-px final
reference, as experiments/render_compare_real_starts/run.py refines real APRs' starts, under
the settings its calibration chose on most 7-Scenes scenes (``CHOSEN``).

``bench/render_compare_real_starts/ms_per_query``: 250 queries in the bench's process;
``peak_rss_mb`` and ``child_ms_per_query``: a fresh process that holds the largest 7-Scenes
test split (redkitchen's 5,000 images) at 128 px, as run.py does, and refines it in one call
(its peak resident set, :func:`pae.bench.scale.run_measured`). ``stage_peak_rss_mb`` and
``stage_whole_peak_rss_mb``: two fresh processes that run the correspondence stage (keypoints
of ``STAGE_QUERIES`` 256-px queries against the grid's 256-px renderings, as
``experiment=real_starts_hard`` keeps it) ``MATCH_CHUNK`` queries at a time and all at once;
``stage_peak_rss_ratio`` the first over the second. The room's walls are opaque
and its inside empty (:func:`pae.bench.render_compare.room_grid`): a fitted grid's faint fog
makes its rays march further, so run.py's figures on fitted grids are the ones to compare
(experiments/bench/README.md).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import torch
from omegaconf import OmegaConf

from pae import CONFIG_DIR
from pae.bench.render_compare import bench_queries, room_grid
from pae.bench.scale import run_measured
from pae.core.threads import configure_threads
from pae.render_compare import ACCEPT_ALL, Calibration, Queries, refine
from pae.render_compare.correspondences import MATCH_CHUNK, MatchSettings, correspond
from pae.render_compare.settings import RenderCompareSettings

SIZE_PX = 128
"""The compare width (and the query images' size) of run.py's tables."""
LARGEST_TEST_SPLIT = 5000
"""redkitchen's test images, the most of any 7-Scenes scene."""
STAGE_QUERIES = 512
"""Queries of the correspondence stage's memory figures."""
STAGE_PX = 256
"""Their size and the renderings' width (``experiment=real_starts_hard``'s stage)."""
CHOSEN = {
    "position_sigma_m": 0.3,
    "orientation_sigma_deg": 5.0,
    "highpass_sigma_px": 4.0,
    "highpass_levels": 1,
    "surface_share": 0.7,
}
"""First steps, filter and surface share as run.py's calibration chose them on most 7-Scenes
scenes (each scene's ``real_starts_DFNet.json``)."""


def real_starts_grid() -> torch.nn.Module:
    """:func:`room_grid` with ``conf/experiment/real_starts.yaml``'s scene model."""
    path = Path(CONFIG_DIR) / "experiment" / "real_starts.yaml"
    model = OmegaConf.load(path).scene_model.model
    return room_grid(1, int(model.num_voxels), int(model.samples_per_ray)).eval()


def refine_queries(n: int) -> float:
    """Refine ``n`` queries of :func:`bench_queries` at ``SIZE_PX`` against
    :func:`real_starts_grid` in one call -> seconds."""
    model = real_starts_grid()
    images, intrinsics, starts, scenes = bench_queries(n, 1, SIZE_PX, seed=0)
    settings = RenderCompareSettings(resolution=SIZE_PX, final_reference_size=SIZE_PX // 2)
    calibration = Calibration(ACCEPT_ALL, ACCEPT_ALL, CHOSEN)
    few = Queries(images[:4], intrinsics[:4], scenes[:4])
    refine(model, few, starts[:4], calibration, settings=settings)
    begin = time.perf_counter()
    with torch.no_grad():
        refine(model, Queries(images, intrinsics, scenes), starts, calibration, settings=settings)
    return time.perf_counter() - begin


def stage_seconds(n: int, chunk: int) -> float:
    """The correspondence stage for ``n`` queries of :func:`bench_queries` at ``STAGE_PX``
    against :func:`real_starts_grid`, ``chunk`` queries at a time -> seconds."""
    model = real_starts_grid()
    images, intrinsics, starts, scenes = bench_queries(n, 1, STAGE_PX, seed=0)
    settings = MatchSettings(width=STAGE_PX, render_width=STAGE_PX, min_inliers=10, iterations=1)
    begin = time.perf_counter()
    correspond(model, images, intrinsics, starts, scenes, settings, chunk=chunk)
    return time.perf_counter() - begin


def _child(arguments: list[str], tmp: Path, name: str) -> tuple[dict[str, float], float]:
    """``python -m pae.bench.real_starts ARGUMENTS OUT`` in a fresh process -> its measured
    peak (:func:`run_measured`) and the seconds it reports."""
    out = tmp / f"{name}.json"
    command = [sys.executable, "-m", "pae.bench.real_starts", *arguments, str(out)]
    measured = run_measured(command, tmp / f"{name}.log")
    return measured, json.loads(out.read_text())["seconds"]


def bench_real_starts(
    queries: int = 250, held: int = LARGEST_TEST_SPLIT, matched: int = STAGE_QUERIES
) -> dict[str, float]:
    """``bench/render_compare_real_starts/...`` (the module's docstring): ``queries`` refined
    here, ``held`` in a fresh process; the stage on ``matched`` queries in two more."""
    prefix = "bench/render_compare_real_starts"
    figures = {f"{prefix}/ms_per_query": 1000 * refine_queries(queries) / queries}
    with tempfile.TemporaryDirectory() as tmp:
        measured, child_s = _child([str(held)], Path(tmp), "refine")
        chunked, chunked_s = _child(
            [str(matched), "--match-chunk", str(MATCH_CHUNK)], Path(tmp), "chunked"
        )
        whole, whole_s = _child([str(matched), "--match-chunk", str(matched)], Path(tmp), "whole")
    figures[f"{prefix}/peak_rss_mb"] = measured["rss_mb"]
    figures[f"{prefix}/child_ms_per_query"] = 1000 * child_s / held
    figures[f"{prefix}/stage_peak_rss_mb"] = chunked["rss_mb"]
    figures[f"{prefix}/stage_whole_peak_rss_mb"] = whole["rss_mb"]
    figures[f"{prefix}/stage_peak_rss_ratio"] = chunked["rss_mb"] / whole["rss_mb"]
    figures[f"{prefix}/stage_ms_per_query"] = 1000 * chunked_s / matched
    figures[f"{prefix}/stage_whole_ms_per_query"] = 1000 * whole_s / matched
    return figures


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description="refine N queries (or run the correspondence stage on them); seconds to OUT"
    )
    parser.add_argument("queries", type=int)
    parser.add_argument("out", type=Path)
    parser.add_argument(
        "--match-chunk", type=int, default=None, help="the stage, this many queries at a time"
    )
    args = parser.parse_args(argv)
    configure_threads()
    if args.match_chunk is None:
        seconds = refine_queries(args.queries)
    else:
        seconds = stage_seconds(args.queries, args.match_chunk)
    args.out.write_text(json.dumps({"seconds": seconds}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
