"""A non-editable install works: the wheel carries the Hydra configs, and its commands compose
every stage with nothing but the installed package."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
SOURCES = ("pyproject.toml", "setup.py", "README.md", "LICENSE", "src", "conf")
# drop every other copy of pae from the path (this checkout's src, an editable install), so
# that only the installed one can be imported
ONLY_INSTALLED = (
    "import sys, pathlib; site = pathlib.Path(sys.argv.pop(1)); "
    "sys.path[:] = [p for p in sys.path if pathlib.Path(p or '.').resolve() == site "
    "or not (pathlib.Path(p or '.') / 'pae').is_dir()]; "
    "sys.meta_path[:] = [f for f in sys.meta_path if 'editable' not in type(f).__module__]; "
)


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The wheel of this checkout, built from a copy of its sources, installed in a folder."""
    tmp = tmp_path_factory.mktemp("packaging")
    tree = tmp / "tree"
    for name in SOURCES:
        source = ROOT / name
        if source.is_dir():
            shutil.copytree(source, tree / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            tree.mkdir(exist_ok=True)
            shutil.copy(source, tree / name)
    pip = [sys.executable, "-m", "pip", "-q"]
    build = [*pip, "wheel", "--no-deps", "--no-build-isolation", "-w", str(tmp / "dist"), "."]
    subprocess.run(build, cwd=tree, check=True, timeout=600)
    (wheel,) = (tmp / "dist").glob("pae-*.whl")
    site = tmp / "site"
    subprocess.run([*pip, "install", "--no-deps", "--target", str(site), str(wheel)], check=True)
    return site


def _python(site: Path, code: str, *args: str) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    env |= {"PYTHONPATH": str(site), "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, "-c", ONLY_INSTALLED + code, str(site), *args],
        capture_output=True,
        text=True,
        env=env,
        cwd=site.parent,
        timeout=300,
    )


def _command(site: Path, name: str, *args: str) -> subprocess.CompletedProcess[str]:
    """An installed console script (site/bin/NAME), run by this interpreter."""
    script = str(site / "bin" / name)
    code = f"import runpy; sys.argv[0] = {name!r}; runpy.run_path({script!r}, run_name='__main__')"
    return _python(site, code, *args)


def test_the_wheel_holds_every_module_and_config(installed: Path) -> None:
    modules = {p.relative_to(ROOT / "src") for p in (ROOT / "src").rglob("*.py")}
    assert modules <= {p.relative_to(installed) for p in installed.rglob("*.py")}
    configs = {p.relative_to(ROOT / "conf") for p in (ROOT / "conf").rglob("*.yaml")}
    assert configs == {p.relative_to(installed / "pae" / "conf") for p in installed.rglob("*.yaml")}


def test_installed_package_composes_every_stage(installed: Path) -> None:
    code = """
from pathlib import Path
from hydra import compose, initialize_config_dir
import pae
from pae.config.schemas import register_schemas
register_schemas()  # as a script composing pae's configs does (docs/configuration.md)
assert Path(pae.__file__).resolve().is_relative_to(site.resolve()), pae.__file__
assert Path(pae.CONFIG_DIR).resolve() == (site / "pae" / "conf").resolve(), pae.CONFIG_DIR
assert not any(Path(p).name == "src" for p in sys.path), sys.path
stages = sorted(p.stem for p in (Path(pae.CONFIG_DIR) / "stage").glob("*.yaml"))
with initialize_config_dir(config_dir=pae.CONFIG_DIR, version_base="1.3"):
    for stage in stages:
        assert compose("train", overrides=[f"stage={stage}"]).stage.name == stage
    assert compose("eval", overrides=["student_ckpt=x.ckpt"]).refine.k == 3
print(" ".join(stages))
"""
    result = _python(installed, code)
    assert result.returncode == 0, result.stderr[-3000:]
    # every stage of the checkout's conf/, found in the installed package
    checkout_stages = sorted(p.stem for p in (ROOT / "conf" / "stage").glob("*.yaml"))
    assert result.stdout.split() == checkout_stages
    assert {"teacher", "student", "pipeline", "full", "iapr"} <= set(checkout_stages)


@pytest.mark.parametrize("stage", ["teacher", "student", "pipeline", "decoder", "rpr", "full"])
def test_installed_pae_train_composes(installed: Path, stage: str) -> None:
    result = _command(installed, "pae-train", f"stage={stage}", "--cfg", "job")
    assert result.returncode == 0, result.stderr[-3000:]
    assert f"name: {stage}" in result.stdout


def test_installed_pae_eval_and_pae_data_run(installed: Path, tmp_path: Path) -> None:
    result = _command(installed, "pae-eval", "student_ckpt=x.ckpt", "--cfg", "job")
    assert result.returncode == 0, result.stderr[-3000:]
    assert "student_ckpt: x.ckpt" in result.stdout
    out = tmp_path / "synth"
    small = ["--scenes", "1", "--train-frames", "3", "--test-frames", "2", "--size", "16"]
    result = _command(installed, "pae-data", "synth", str(out), *small)
    assert result.returncode == 0, result.stderr[-3000:]
    result = _command(
        installed, "pae-data", "check", str(out / "labels" / "all_train.csv"), str(out)
    )
    assert result.returncode == 0 and result.stdout.startswith("OK: 3 rows"), result.stderr
