"""Only computes the package list; all metadata lives in pyproject.toml."""

from setuptools import find_packages, setup

setup(packages=find_packages("src") + ["nirspi_pipe.conf", "nirspi_pipe.experiments"])
