"""The calibration for any start on a scene's val images with and without the filters of
``experiment=demo_hard`` offered (``AnyStartOptions.filters``), no correspondence stage: each
one's kept filter and objective (the mean log error ratio over the ladder's starts), and the
val audit under it (the val images refined from their true poses, every refinement accepted:
how far the scene model lets a true pose drift; no calibration reads it).

    python experiments/render_compare_real_starts/filters_val.py OUT/ShopFacade
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from omegaconf import OmegaConf

from pae.apps.any_start import val_figures
from pae.apps.localization import (
    compare_width,
    data_module,
    read_run,
    render_compare_settings,
    scene_model_path,
    split_queries,
)
from pae.core.checkpoints import load_scene_model
from pae.render_compare import (
    ACCEPT_ALL,
    AnyStartOptions,
    Calibration,
    Queries,
    calibrate_any_start,
    refine,
)
from pae.render_compare.calibration import objective_value, scene_size

DEMO_HARD = Path(__file__).resolve().parents[2] / "conf" / "experiment" / "demo_hard.yaml"


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a scene's run folder (OUT/<scene>)")
    run = read_run(parser.parse_args(argv).run)
    data = data_module(run, cache_images=False)
    data.setup()
    model = load_scene_model(scene_model_path(run), "scene_model_ckpt").model.eval()
    settings, _ = render_compare_settings(run)  # as pae-localize refines with the run
    val = split_queries(data, "val", compare_width(settings))
    queries = Queries(val["image"], val["intrinsics"], val["scene"])
    positions, _ = data.train_poses()
    size_m = scene_size(positions[:, :3].double())
    listed = OmegaConf.to_container(OmegaConf.load(DEMO_HARD).render_compare.filters_from_val)
    assert isinstance(listed, list)
    for name, options in (
        ("its own grid", AnyStartOptions()),
        ("and demo_hard's filters", AnyStartOptions(filters=listed)),
    ):
        calibration, refined, starts = calibrate_any_start(
            model, queries, val["pose"], size_m, settings, options
        )
        objective = objective_value(refined.poses, starts, val["pose"], "log_ratio")
        audit = refine(
            model, queries, val["pose"], Calibration(ACCEPT_ALL, ACCEPT_ALL, calibration.steps),
            settings=settings,
        )  # fmt: skip
        floor = val_figures(audit.poses, val["pose"])
        print(
            f"{name}: kept {dict(calibration.steps)}, objective {objective:.3f}, val audit "
            f"{100 * floor['pos_median_m']:.1f} cm / {floor['rot_median_deg']:.2f} deg "
            f"({len(val['pose'])} val images)",
            flush=True,
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
