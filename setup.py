"""Packaging beyond pyproject.toml: the Hydra configs, edited in conf/ at the top of the
repository, ship inside the package as pae.conf (each folder of conf/ a package of pae.conf),
so that a non-editable install runs pae-train, pae-eval and pae-data (pae.CONFIG_DIR); pae's
Hydra sweeper ships in Hydra's plugin namespace, hydra_plugins (no __init__.py: other plugins
share it)."""

from setuptools import find_namespace_packages, find_packages, setup

CONFIG_PACKAGES = ["pae.conf", *(f"pae.conf.{name}" for name in find_namespace_packages("conf"))]

setup(
    package_dir={"": "src", "pae.conf": "conf"},
    packages=[*find_packages("src"), "hydra_plugins", *CONFIG_PACKAGES],
    package_data={package: ["*.yaml"] for package in CONFIG_PACKAGES},
)
