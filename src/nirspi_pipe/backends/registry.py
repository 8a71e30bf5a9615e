"""Every stage family with more than one back end, by name (:data:`REGISTRY`)."""

from __future__ import annotations

from nirspi_pipe.backends.fsrcnn import FSRCNN
from nirspi_pipe.backends.harness import Family
from nirspi_pipe.backends.omp import OMP
from nirspi_pipe.backends.remesh import REMESH
from nirspi_pipe.backends.sfs import SFS

__all__ = ["REGISTRY"]

#: Every stage family with more than one back end, by name.
REGISTRY: dict[str, Family] = {f.name: f for f in (SFS, OMP, FSRCNN, REMESH)}
