"""What limits render-and-compare's precision: the refiner's floor on the validation images.

For a fitted real-starts run (``run.py``), the validation queries are refined with settings
variants (``--variant key=value,key=value`` over the run's refiner settings, those
pae-localize refines with; ``''``: those alone), the first steps, filter and surface share
that ``calibrate_any_start`` chose (``RUN/render_compare_any_start.json``) under every
variant (a key the variant sets overrides the chosen value), every refinement accepted,
from two kinds of starts: the true poses (the floor: where the scene model's best match
lies) and starts of a good APR's error scale (1 % of the scene's size and 1 deg, drawn as
:func:`pae.core.pose_sampling.perturb_poses` draws).
``--ladder``: also, under those settings, each rung of the any-start calibration's ladder
(:func:`pae.render_compare.calibration.ladder_starts`): the starts' and the refined poses'
medians and the share the refinement made worse. ``--oracle [BLUR_PX]``: the same with the
benchmark's own renderer instead of the fitted scene model, its renderings blurred by a
Gaussian of that sigma (a bound: how sharp a scene model must be for a given floor).
``--oracle-depth``: the fitted model's colours on the benchmark renderer's depth and opacity
(what the model's geometry costs). ``--window W``: also the refinements from the good starts
through each window fit of ``render_compare.sequence_fit`` over W frames along the val walk
(:func:`windowed`: the val split is one held-out recording per scene, in frame order).
``--explain N``: how well the model explains N val queries at their true poses, beside the
benchmark's own renderer (:func:`explained`; ``--explain-only``: that alone; ``--picture
PNG``: those queries, the renderer's and the model's images side by side, :func:`picture`). Only
validation labels are read. One row per variant, printed and written to
``RUN/floor_val.json`` (with ``--oracle``: ``RUN/floor_val_oracle.json``).

    python experiments/render_compare_real_starts/floor.py outputs/rs128/chess \\
        --variant final_reference_size=32 --variant '' --variant final_reference_size=96
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
from run import chosen_steps  # beside this script

from pae.apps.localization import (
    data_module,
    read_run,
    render_compare_settings,
    scene_model_path,
    split_queries,
)
from pae.core.atomic import atomic_write
from pae.core.checkpoints import load_scene_model
from pae.core.geometry import pose_errors
from pae.core.pose_sampling import perturb_poses
from pae.lit.eval_outputs import oracle_scenes
from pae.render_compare import ACCEPT_ALL, Calibration, Queries, refine
from pae.render_compare.calibration import LADDER, ladder_starts, scene_size
from pae.render_compare.images import band_pass, gaussian_blur, grey, zncc
from pae.render_compare.sequences import WINDOW_FITS, SequenceOptions, window_filter
from pae.render_compare.settings import RenderCompareSettings
from pae.scene_model.base import SceneRendering
from pae.scene_model.oracle import OracleSceneModel

GOOD_START_SHARE = 0.01
"""A good APR's position error as a share of the scene's size (DFNet: 3 cm in a 3 m room)."""
GOOD_START_DEG = 1.0


class BlurredOracle(OracleSceneModel):
    """The benchmark's own renderer, its images blurred by a Gaussian of ``blur_per_px`` ×
    the rendered width (px): how sharp a scene model must be for a given floor."""

    def __init__(self, scenes: list[Any] | None, blur_per_px: float) -> None:
        if scenes is None:
            raise SystemExit(
                "--oracle and --explain need the benchmark's true scenes; this run's data "
                "does not know them"
            )
        super().__init__(scenes)
        self.blur_per_px = blur_per_px

    def render(
        self, poses: torch.Tensor, scenes: torch.Tensor, intrinsics: torch.Tensor,
        width: int, height: int, surface_share: float = 0.0,
    ) -> SceneRendering:  # fmt: skip
        rendering = super().render(poses, scenes, intrinsics, width, height)
        rgb = gaussian_blur(rendering.rgb, self.blur_per_px * width)
        return rendering._replace(rgb=rgb)


class WithOracleDepth(torch.nn.Module):
    """The fitted scene model's colours on the benchmark renderer's geometry (its depth and
    opacity): what the model's own surfaces cost the floor."""

    has_depth = True

    def __init__(self, model: Any, oracle: OracleSceneModel) -> None:
        super().__init__()
        self.model, self.oracle = model, oracle

    def render(
        self, poses: torch.Tensor, scenes: torch.Tensor, intrinsics: torch.Tensor,
        width: int, height: int, surface_share: float = 0.0,
    ) -> SceneRendering:  # fmt: skip
        colours = self.model.render(poses, scenes, intrinsics, width, height)
        geometry = self.oracle.render(poses, scenes, intrinsics, width, height)
        return colours._replace(depth=geometry.depth, opacity=geometry.opacity)


def compared(rgb: torch.Tensor, settings: dict) -> torch.Tensor:
    """Images [B, 3, H, W] -> the grey images [B, H, W] band-passed as ``settings`` compare
    at the finest level (blur, high-pass, local contrast)."""
    return band_pass(
        grey(rgb), settings["blur_sigma_px"], settings["highpass_sigma_px"],
        settings.get("contrast_sigma_px", 0.0),
    )  # fmt: skip


def explained(
    model: Any, oracle: OracleSceneModel, queries: dict[str, torch.Tensor], settings: dict
) -> dict[str, float]:
    """How well ``model`` explains ``queries`` (``image``, ``pose``, ``intrinsics``,
    ``scene``) at their true poses, beside the benchmark's own renderer ``oracle``: the mean
    ZNCC of the grey images band-passed as ``settings`` compare at the finest level (blur,
    high-pass, local contrast) between each query and each rendering, the model's mean opacity
    and the median of its depth minus the oracle's (m; negative: the model's surfaces lie
    nearer the camera); and at the surface share the refiner projects (``surface_share`` of
    ``settings``), the median |log| of the model's depth over the oracle's and the share of
    pixels within 10 % of it."""
    height, width = queries["image"].shape[-2:]
    args = (queries["pose"], queries["scene"], queries["intrinsics"], width, height)
    with torch.no_grad():
        ours, truth = model.render(*args), oracle.render(*args)
        surface = model.render(*args, surface_share=settings.get("surface_share", 0.0)).depth
    ratio = (surface.clamp_min(1e-6) / truth.depth.clamp_min(1e-6)).log().abs()
    query = compared(queries["image"], settings).flatten(1)
    ones = torch.ones_like(query)

    def score(rgb: torch.Tensor) -> float:
        return float(zncc(query, compared(rgb, settings).flatten(1), ones).mean())

    return {
        "zncc_model": score(ours.rgb),
        "zncc_oracle": score(truth.rgb),
        "opacity_model": float(ours.opacity.mean()),
        "depth_minus_oracle_median_m": float((ours.depth - truth.depth).median()),
        "surface_log_ratio_median": float(ratio.median()),
        "surface_within_10pc": float((ratio < math.log(1.1)).float().mean()),
    }


def picture(
    model: Any,
    oracle: OracleSceneModel,
    queries: dict[str, torch.Tensor],
    settings: dict,
    path: Path,
) -> None:
    """A PNG at ``path``: one row per query of ``queries`` at its true pose, the query, the
    benchmark's own renderer and the scene model, then the three grey images band-passed as
    ``settings`` compare at the finest level (each scaled to ±3 standard deviations)."""
    height, width = queries["image"].shape[-2:]
    args = (queries["pose"], queries["scene"], queries["intrinsics"], width, height)
    with torch.no_grad():
        images = (queries["image"], oracle.render(*args).rgb, model.render(*args).rgb)

    def filtered(rgb: torch.Tensor) -> torch.Tensor:
        g = compared(rgb, settings).reshape(len(rgb), 1, height, width)
        g = (g - g.mean((2, 3), keepdim=True)) / g.std((2, 3), keepdim=True).clamp_min(1e-6)
        return ((g.clamp(-3, 3) + 3) / 6).expand(-1, 3, -1, -1)

    tiles = [rgb.clamp(0, 1) for rgb in images] + [filtered(rgb) for rgb in images]
    grid = torch.cat([torch.cat(list(row), 2) for row in zip(*tiles, strict=True)], 1)
    pixels = (grid.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    if not cv2.imwrite(str(path), cv2.cvtColor(pixels, cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write {path}")


def overridden(calibration: Calibration, variant: dict[str, Any]) -> Calibration:
    """The calibration without the chosen steps that ``variant`` sets: its values stand."""
    steps = {key: value for key, value in calibration.steps.items() if key not in variant}
    return dataclasses.replace(calibration, steps=steps)


def parse_variant(text: str) -> dict[str, Any]:
    """``key=value,key=value`` -> settings (numbers as int or float); a malformed item or an
    unknown setting is a one-line error."""
    known = {field.name for field in dataclasses.fields(RenderCompareSettings)}
    variant: dict[str, Any] = {}
    for item in filter(None, text.split(",")):
        key, _, value = item.partition("=")
        if key not in known:
            raise SystemExit(f"--variant {text!r}: {key!r} is not a render-and-compare setting")
        try:
            number = float(value)
        except ValueError:
            raise SystemExit(f"--variant {text!r}: {item!r} is not key=number") from None
        variant[key] = int(number) if number.is_integer() and "." not in value else number
    return variant


def medians(poses: torch.Tensor, truth: torch.Tensor) -> dict[str, float]:
    """Median position (m) and orientation (deg) errors of poses [N, 7]."""
    pos, rot = pose_errors(poses.float(), truth.float())
    return {"pos_median_m": float(pos.median()), "rot_median_deg": float(rot.median())}


def windowed(
    poses: torch.Tensor, truth: torch.Tensor, scenes: torch.Tensor, window: int
) -> dict[str, dict[str, float]]:
    """Medians of refined poses [N, 7] of val walks (one per scene, scenes [N], frames in row
    order) through each window fit over ``window`` frames (:data:`WINDOW_FITS`), against
    the true poses [N, 7]."""
    options = [SequenceOptions(window=window, fit=fit) for fit in WINDOW_FITS]
    return {o.fit: medians(window_filter(poses, scenes, scenes, o), truth) for o in options}


def ladder_rows(refined: torch.Tensor, starts: torch.Tensor, truth: torch.Tensor) -> list[dict]:
    """Per rung of the ladder (query i on rung i mod K): its share of the scene's size, the
    starts' and the refined poses' median position errors (m), the share made worse."""
    start_pos, _ = pose_errors(starts.float(), truth.float())
    refined_pos, _ = pose_errors(refined.float(), truth.float())
    rung = torch.arange(len(truth)) % len(LADDER)
    return [
        {
            "share": share,
            "start_pos_median_m": float(start_pos[rung == k].median()),
            "refined_pos_median_m": float(refined_pos[rung == k].median()),
            "worse_share": float((refined_pos > start_pos)[rung == k].float().mean()),
        }
        for k, share in enumerate(LADDER)
    ]


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path)
    parser.add_argument("--variant", action="append", default=[], help="key=value,...")
    parser.add_argument("--queries", type=int, default=400, help="val queries (evenly spaced)")
    parser.add_argument("--ladder", action="store_true", help="every val query, ladder starts")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--window",
        type=int,
        default=0,
        metavar="W",
        help="also the refinements from the good starts through each window fit over W "
        "frames along the val walk (odd)",
    )
    parser.add_argument(
        "--explain",
        type=int,
        default=0,
        metavar="N",
        help="also, for N val queries at their true poses, how well the scene model and the "
        "benchmark's own renderer explain them (explained())",
    )
    parser.add_argument(
        "--oracle",
        type=float,
        nargs="?",
        const=0.0,
        metavar="BLUR_PX",
        help="the benchmark's own renderer instead of the fitted scene model (a bound), its "
        "renderings blurred by a Gaussian of this sigma (px at the run's image size; default "
        "0); rows written to floor_val_oracle.json",
    )
    parser.add_argument(
        "--oracle-depth",
        action="store_true",
        help="the fitted model's colours on the benchmark renderer's depth and opacity (what "
        "the model's geometry costs); rows keyed 'oracle depth: ...'",
    )
    parser.add_argument(
        "--picture",
        type=Path,
        metavar="PNG",
        help="with --explain N: the N val queries at their true poses beside the benchmark's "
        "renderer and the scene model, raw and filtered (picture())",
    )
    parser.add_argument(
        "--explain-only",
        action="store_true",
        help="with --explain: only how well the model explains the val queries, no refinement",
    )
    args = parser.parse_args(argv)
    if args.window < 0 or (args.window > 1 and args.window % 2 == 0):
        parser.error(f"--window must be odd, got {args.window}")
    if (args.explain_only or args.picture) and not args.explain:
        parser.error("--explain-only and --picture need --explain N")
    if args.picture and (args.picture.suffix.lower() != ".png" or not args.picture.parent.is_dir()):
        parser.error(f"--picture {args.picture}: a .png file in an existing folder")
    if args.oracle is not None and args.oracle_depth:
        parser.error("--oracle already renders the benchmark's depth; drop --oracle-depth")
    if args.oracle is not None and args.oracle < 0:
        parser.error("--oracle takes a blur sigma (px) >= 0")
    if args.explain < 0:
        parser.error("--explain takes a number of val queries >= 0")
    variants = [parse_variant(text) for text in args.variant or [""]]
    run = read_run(args.run)
    size = int(run.config.data.size)
    data = data_module(run, cache_images=False, crop=size)
    data.setup()
    if args.oracle is not None:
        model = BlurredOracle(oracle_scenes(data), args.oracle / size)
    else:
        model = load_scene_model(scene_model_path(run), "scene_model_ckpt").model.eval()
    if args.oracle_depth:
        model = WithOracleDepth(model, BlurredOracle(oracle_scenes(data), 0.0))
    every = split_queries(data, "val", size)
    count = min(args.queries, len(every["pose"]))
    rows = torch.linspace(0, len(every["pose"]) - 1, count).long()
    val = {key: value[rows] for key, value in every.items()}
    truth = val["pose"]
    train_positions, _ = data.train_poses()
    extent = scene_size(train_positions[:, :3].double())
    calibration = Calibration(ACCEPT_ALL, ACCEPT_ALL, chosen_steps(args.run))
    base, _ = render_compare_settings(run)  # as pae-localize refines with the run
    good = perturb_poses(
        truth.double(),
        torch.full((count,), GOOD_START_SHARE * extent, dtype=torch.float64),
        torch.full((count,), GOOD_START_DEG, dtype=torch.float64),
        torch.Generator().manual_seed(args.seed),
    ).to(truth)
    oracle = args.oracle is not None
    out_path = args.run / ("floor_val_oracle.json" if oracle else "floor_val.json")
    results = json.loads(out_path.read_text()) if out_path.is_file() else {}
    print(f"{args.run.name}: {count} val queries, scene {extent:.2f} m, {calibration.steps}")
    print(f"start (1 % / 1 deg): {medians(good, truth)}")
    measured = list(zip(args.variant or [""], variants, strict=True))
    for text, variant in [] if args.explain_only else measured:
        row: dict[str, Any] = {}
        for name, starts in (("from_truth", truth), ("from_good", good)):
            begin = time.perf_counter()
            refined = refine(
                model, Queries(val["image"], val["intrinsics"], val["scene"]), starts,
                overridden(calibration, variant), settings=base | variant,
            )  # fmt: skip
            row[name] = medians(refined.poses, truth)
            row[f"{name}_ms_per_query"] = 1000 * (time.perf_counter() - begin) / count
        if args.window > 1:
            row["from_good_windows"] = windowed(refined.poses, truth, val["scene"], args.window)
            print(f"  window {args.window}: {row['from_good_windows']}")
        key = text or "(run.py's)"
        key = f"oracle depth: {key}" if args.oracle_depth else key
        results[f"blur {args.oracle:g} px: {key}" if oracle else key] = row
        print(
            f"{text or '(run.py settings)':60s} truth {100 * row['from_truth']['pos_median_m']:.2f}"
            f" cm / {row['from_truth']['rot_median_deg']:.2f} deg, good "
            f"{100 * row['from_good']['pos_median_m']:.2f} cm / "
            f"{row['from_good']['rot_median_deg']:.2f} deg, "
            f"{row['from_good_ms_per_query']:.1f} ms/query",
            flush=True,
        )
    if args.explain:
        picks = torch.linspace(0, count - 1, min(args.explain, count)).long()
        chosen = base | calibration.steps
        picked = {key: value[picks] for key, value in val.items()}
        renderer = BlurredOracle(oracle_scenes(data), 0.0)
        results["explain"] = explained(model, renderer, picked, chosen)
        print("explained at the true val poses:", results["explain"])
        if args.picture:
            picture(model, renderer, picked, chosen, args.picture)
            print(f"picture: {args.picture}")
    if args.ladder:
        truth = every["pose"]
        starts = ladder_starts(truth, extent, torch.Generator().manual_seed(args.seed))
        queries = Queries(every["image"], every["intrinsics"], every["scene"])
        refined = refine(model, queries, starts, calibration, settings=base)
        results["ladder"] = ladder_rows(refined.poses, starts, truth)
        for rung in results["ladder"]:
            print(
                f"rung {100 * rung['share']:.2f} % of the size: start "
                f"{100 * rung['start_pos_median_m']:.1f} cm -> "
                f"{100 * rung['refined_pos_median_m']:.1f} cm, worse {rung['worse_share']:.2f}"
            )
    with atomic_write(out_path) as handle:
        json.dump(results, handle, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
