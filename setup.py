"""Only computes the package list; all metadata lives in pyproject.toml."""

from setuptools import find_packages, setup

setup(
    packages=sorted(
        set(find_packages("src"))
        | {"nirspi_pipe.conf", "nirspi_pipe.experiments", "hydra_plugins.nirspi_pipe_sweeper"}
    )
)
