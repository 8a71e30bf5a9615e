"""Shape from shading (sfs stage): fast-sweeping solvers of the image irradiance equation.

Stages in :mod:`nirspi_pipe.sfs.models`; numpy solvers in :mod:`nirspi_pipe.sfs.sweeping`
(first order) and :mod:`nirspi_pipe.sfs.second_order` (``scheme: second_order``); the OpenCL
back end in :mod:`nirspi_pipe.sfs.opencl`. See ``docs/sfs.md``.
"""

from nirspi_pipe.sfs.models import LaxFriedrichsSFS, OrenNayarSFS, PerspectiveSFS, PhongSFS

__all__ = ["LaxFriedrichsSFS", "PerspectiveSFS", "OrenNayarSFS", "PhongSFS"]
