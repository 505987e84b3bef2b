"""experiments/render_compare_real_starts' run.py and table.py: every K-th test image only,
said in the table."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

import pytest

FOLDER = Path(__file__).resolve().parents[1] / "experiments/render_compare_real_starts"
FIGURES = {"pos_median_m": 0.03, "rot_median_deg": 1.0, "within_5cm_5deg": 0.5}


def _script(name: str) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, FOLDER / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_every_below_one_is_a_one_line_error(capsys: pytest.CaptureFixture[str]) -> None:
    run = _script("run")
    with pytest.raises(SystemExit):
        run.main(["--labels", "L", "--estimates", "E", "--every", "0"])
    assert "--every must be at least 1, got 0" in capsys.readouterr().err


@pytest.mark.parametrize("every, named", [(1, "chess"), (4, "chess (every 4th test image)")])
def test_the_table_names_a_scene_refined_on_every_kth_image(every: int, named: str) -> None:
    record = {
        "scene": "chess",
        "every": every,
        "start": FIGURES,
        "render_compare": FIGURES,
        "nefes50": FIGURES,
        "accepted_share": 0.5,
        "calibration": {},
        "ms_per_query": 300.0,
    }
    assert _script("table").row(record, recordings=False)[0] == named
