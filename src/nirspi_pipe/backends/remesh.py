"""Clean-up and isotropic remeshing's back ends: pymeshlab (reference) and the compiled twin,
fixtures and bounds (:data:`REMESH`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from nirspi_pipe.backends.harness import Backend, Family, Tolerance
from nirspi_pipe.mesh.remesh import clean_and_remesh, sample_spacing

__all__ = ["REMESH", "RemeshCase"]


# --- Clean-up and isotropic remeshing: pymeshlab (reference) and the compiled twin -------------


@dataclass(frozen=True)
class RemeshCase:
    """A power-crust sheet of a noisy spherical cap and the cloud's sample spacing (metres)."""

    vertices: np.ndarray
    faces: np.ndarray
    spacing: float
    iterations: int = 3


_REMESH_FIXTURES = ("cap18-seed3", "cap14-seed0")


def _remesh_fixture(name: str) -> RemeshCase:
    # start-up: loads scipy, numba, charset_normalizer (466 ms here)
    from nirspi_pipe.mesh.powercrust import (
        power_crust,
        trim_to_samples,
    )

    cap, seed = name.split("-")
    n = int(cap[3:])
    rng = np.random.default_rng(int(seed[4:]))
    u, v = np.meshgrid(np.linspace(-0.7, 0.7, n), np.linspace(-0.7, 0.7, n))
    keep = u**2 + v**2 < 0.6
    u, v = u[keep], v[keep]
    pts = 0.025 * np.column_stack([u, v, -np.sqrt(1.0 - u**2 - v**2)]) + [0.0, 0.0, 0.2]
    pts = pts + rng.normal(0.0, 2e-5, pts.shape)
    sp = sample_spacing(pts)
    vv, ff, _ = power_crust(pts, "view", 3.0, 0.25, sp)
    vv, ff = trim_to_samples(vv, ff, pts, 1.5, sp)
    return RemeshCase(vv, ff, sp)


def _remesh_pymeshlab(case: RemeshCase) -> Any:
    return clean_and_remesh(case.vertices, case.faces, case.spacing, case.iterations)


def _remesh_compiled(case: RemeshCase) -> Any:
    from nirspi_pipe.mesh.isotropic import clean_and_remesh_compiled  # start-up: loads scipy, numba, yaml (204 ms here)

    return clean_and_remesh_compiled(case.vertices, case.faces, case.spacing, case.iterations)


def _pymeshlab_unavailable() -> str | None:
    try:
        # start-up: loads pymeshlab (134 ms here)
        import pymeshlab  # noqa: F401 - only whether it imports
    except ImportError as exc:
        return f"pymeshlab does not import ({exc})"
    return None


def _compiled_unavailable() -> str | None:
    from nirspi_pipe.mesh.isotropic import warm_up  # start-up: loads scipy, numba, yaml (204 ms here)

    return None if warm_up() else "numba could not compile the compiled remesher here"


def _remesh_compare(case: RemeshCase, ref: Any, alt: Any) -> dict[str, float]:
    from scipy.spatial import cKDTree  # start-up: loads scipy, charset_normalizer (255 ms here)

    # start-up: loads PIL, charset_normalizer, cycler (525 ms here)
    from nirspi_pipe.mesh.metrics3d import (
        equiangle_skewness,
    )

    (pv, pf, pinfo), (cv, cf, cinfo) = ref, alt
    if len(cf) == 0 or len(pf) == 0:
        return {k: float("inf") for k in _REMESH_TOLERANCES}
    return {
        "face_deficit": 1.0 - len(cf) / len(pf),
        "skewness_excess": float(equiangle_skewness(cv, cf).mean() - equiangle_skewness(pv, pf).mean()),
        "median_distance_to_reference_spacings": float(np.median(cKDTree(pv).query(cv)[0])) / case.spacing,
        "median_distance_from_reference_spacings": float(np.median(cKDTree(cv).query(pv)[0])) / case.spacing,
        "info_face_count_mismatch": float(
            abs(pinfo["faces_after_remesh"] - len(pf)) + abs(cinfo["faces_after_remesh"] - len(cf))
        ),
    }


_REMESH_SOURCE = (
    "a design bound, not a rounding error: the two remeshers are different algorithms (no feature "
    "edges, no reprojection in the compiled one). Bounds of the former "
    "test_compiled_remesher_matches_pymeshlab_on_a_power_crust; measured on these 2 fixtures "
    "(pymeshlab 2025.7, numba 0.68)"
)

_REMESH_TOLERANCES = {
    "face_deficit": Tolerance(0.5, _REMESH_SOURCE + ": 0.06 and 0.14"),
    "skewness_excess": Tolerance(0.02, _REMESH_SOURCE + ": -0.10 and -0.12 (the compiled meshes are better)"),
    "median_distance_to_reference_spacings": Tolerance(0.5, _REMESH_SOURCE + ": 0.29 and 0.29"),
    "median_distance_from_reference_spacings": Tolerance(0.5, _REMESH_SOURCE + ": 0.30 and 0.31"),
    "info_face_count_mismatch": Tolerance(0, "both report the face count they return"),
}

REMESH = Family(
    name="remesh",
    reference=Backend("pymeshlab", _remesh_pymeshlab, _pymeshlab_unavailable),
    alternatives=(Backend("compiled", _remesh_compiled, _compiled_unavailable),),
    fixture_names=_REMESH_FIXTURES,
    make_fixture=_remesh_fixture,
    compare=_remesh_compare,
    tolerances=_REMESH_TOLERANCES,
)
