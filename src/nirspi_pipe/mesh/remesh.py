"""Mesh clean-up and isotropic remeshing (pymeshlab), applied by the surface stages (issue 14).

:func:`clean_and_remesh` runs, on a mesh in metres:

1. **Clean-up** (pymeshlab): merge duplicate vertices, drop duplicate and zero-area faces, repair
   non-manifold edges and vertices, drop unreferenced vertices, then close holes of at most
   ``max_hole_edges`` boundary edges (small holes inside the visible sheet; the sheet's own
   outer border is far longer and stays open) and drop isolated pieces with fewer than
   ``min_component_faces`` faces.
2. **Isotropic explicit remeshing** (Botsch & Kobbelt 2004, pymeshlab
   ``meshing_isotropic_explicit_remeshing``): ``iterations`` rounds of edge splits, collapses,
   flips towards valence 6, and tangential relaxation with reprojection onto the input
   surface, towards a target edge length ``edge_factor`` × the cloud's median sample spacing.
   This is what brings the equiangle skewness of a power crust (fans of slivers around each
   sample) down; the reprojection keeps the surface where it was.

Two implementations (the surface stages' ``remesher`` key): ``compiled``
(:mod:`nirspi_pipe.mesh.isotropic`, numba; the default through ``auto``) and ``pymeshlab`` (the
filters named above). Remeshing is an option with a price: see docs/mesh.md (``nirspi-bench
mesh3d`` prints it).
"""

from __future__ import annotations

from functools import lru_cache
from typing import Annotated

import numpy as np

from nirspi_pipe.errors import ConfigError, NirspiError
from nirspi_pipe.ranges import OneOf, Range

__all__ = [
    "REMESHERS",
    "RemeshIterations",
    "RemeshEdgeFactor",
    "MaxHoleEdges",
    "Remesher",
    "load_meshlab",
    "clean_and_remesh",
    "remesh_to_cloud",
    "resolve_remesher",
    "sample_spacing",
]

#: Values of the surface stages' ``remesher`` key.
REMESHERS = ("auto", "compiled", "pymeshlab")
#: The remeshing keys the surface stages share, with their declared ranges (:mod:`nirspi_pipe.ranges`).
RemeshIterations = Annotated[int, Range(0, 50, "an integer", integer=True, note="0: off")]
RemeshEdgeFactor = Annotated[float, Range(0.1, 20.0, "a factor of the sample spacing")]
MaxHoleEdges = Annotated[int, Range(0, 10_000, "an integer", integer=True, note="0: keep holes")]
Remesher = Annotated[str, OneOf(REMESHERS)]


@lru_cache(maxsize=1)
def _compiled_ok() -> bool:
    from nirspi_pipe.mesh.isotropic import warm_up  # start-up: loads scipy and numba (1122 ms here)

    return warm_up()


def resolve_remesher(remesher: str) -> str:
    """The implementation a surface stage's ``remesher`` key names, made ready (compiled or
    imported) now, outside any timed stage: ``auto`` is ``compiled`` where numba compiles it (or
    loads it from its on-disk cache), else ``pymeshlab``. One-line error for any other value."""
    if remesher not in REMESHERS:
        raise ConfigError("remesher", remesher, ", ".join(REMESHERS))
    if remesher != "pymeshlab" and _compiled_ok():
        return "compiled"
    if remesher == "compiled":
        raise ConfigError(
            "remesher", remesher, "auto or pymeshlab (numba could not compile the compiled remesher here)"
        )
    load_meshlab()
    return "pymeshlab"


def load_meshlab() -> None:
    """Import pymeshlab (about 0.3 s, measured with ``python -X importtime -c "import pymeshlab"``).
    The surface stages call it when they are built, so that the import is not counted in the
    ``surface`` stage time of the first mesh a process makes (Table 6; every sweep job is one)."""
    # start-up: loads pymeshlab (84 ms here)
    import pymeshlab  # noqa: F401 - imported for its side effect: loaded once per process


def sample_spacing(points_m: np.ndarray) -> float:
    """Median nearest-neighbour distance of a ``(k, 3)`` cloud, metres (0 for fewer than 2 points)."""
    from scipy.spatial import cKDTree  # start-up: loads scipy and numpy (1291 ms here)

    pts = np.asarray(points_m, dtype=np.float64)
    return float(np.median(cKDTree(pts).query(pts, k=2)[0][:, 1])) if len(pts) > 1 else 0.0


def remesh_to_cloud(
    vertices_m: np.ndarray,
    faces: np.ndarray,
    points_m: np.ndarray,
    iterations: int,
    edge_factor: float,
    max_hole_edges: int,
    spacing_m: float | None = None,
    remesher: str = "pymeshlab",
) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
    """:func:`clean_and_remesh` (``remesher="pymeshlab"``) or its compiled twin
    :func:`~nirspi_pipe.mesh.isotropic.clean_and_remesh_compiled` (``"compiled"``; resolve
    ``auto`` first with :func:`resolve_remesher`) at the cloud's own :func:`sample_spacing`, as
    the surface stages call it on their reconstruction of ``points_m``; an empty mesh is returned
    unchanged. ``spacing_m``: that spacing (metres) when the caller has it; None computes it."""
    if len(faces) == 0:
        return vertices_m, faces, {}
    spacing = sample_spacing(points_m) if spacing_m is None else float(spacing_m)
    if remesher == "compiled":
        from nirspi_pipe.mesh.isotropic import (  # start-up: loads scipy, numba, yaml (188 ms here)
            clean_and_remesh_compiled,  # start-up: loads scipy and numba (1122 ms here)
        )

        return clean_and_remesh_compiled(
            vertices_m, faces, spacing, int(iterations), float(edge_factor), int(max_hole_edges)
        )
    return clean_and_remesh(vertices_m, faces, spacing, int(iterations), float(edge_factor), int(max_hole_edges))


def clean_and_remesh(
    vertices_m: np.ndarray,
    faces: np.ndarray,
    spacing_m: float,
    iterations: int = 3,
    edge_factor: float = 1.0,
    max_hole_edges: int = 30,
    min_component_faces: int = 10,
) -> tuple[np.ndarray, np.ndarray, dict[str, float]]:
    """Clean a triangle mesh and remesh it isotropically (module docstring).

    Args:
        vertices_m: ``(v, 3)`` vertices, metres.
        faces: ``(f, 3)`` vertex indices.
        spacing_m: median sample spacing of the cloud the mesh came from, metres (> 0).
        iterations: remeshing rounds (0: clean-up only).
        edge_factor: target edge length in units of ``spacing_m``.
        max_hole_edges: close holes bounded by at most this many edges (0: none).
        min_component_faces: drop connected pieces with fewer faces.

    Returns ``(vertices_m, faces, info)``; an empty or tiny mesh is returned unchanged.
    """
    import pymeshlab  # start-up: loads pymeshlab (208 ms here)

    v = np.asarray(vertices_m, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    info: dict[str, float] = {"faces_before_remesh": int(len(f))}
    if len(f) < 4 or not spacing_m > 0:
        return v, f, info
    # refused before pymeshlab sees them: it crashes the process on an infinite coordinate
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise NirspiError(
            f"mesh clean-up (pymeshlab): vertices {v.shape} and faces {f.shape}; allowed: (v, 3) and (f, 3)"
        )
    if not np.all(np.isfinite(v)):
        bad = int(np.count_nonzero(~np.all(np.isfinite(v), axis=1)))
        raise NirspiError(
            f"mesh clean-up (pymeshlab): {bad} vertices with non-finite coordinates; allowed: finite ones"
        )
    if f.min() < 0 or f.max() >= len(v):
        raise NirspiError(f"mesh clean-up (pymeshlab): face indices outside 0..{len(v) - 1}")
    ms = pymeshlab.MeshSet()
    # millimetres inside: pymeshlab's absolute tolerances assume model-sized units
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v * 1e3, face_matrix=f.astype(np.int32)))
    ms.meshing_remove_duplicate_vertices()
    ms.meshing_remove_duplicate_faces()
    ms.meshing_remove_null_faces()
    ms.meshing_repair_non_manifold_edges()
    ms.meshing_repair_non_manifold_vertices()
    ms.meshing_remove_unreferenced_vertices()
    if max_hole_edges > 0 and ms.current_mesh().face_number() > 0:
        try:
            ms.meshing_close_holes(maxholesize=int(max_hole_edges), newfaceselected=False)
        except pymeshlab.PyMeshLabException:  # non-manifold leftovers: keep the holes
            info["holes_not_closed"] = 1
    if min_component_faces > 0:
        ms.meshing_remove_connected_component_by_face_number(mincomponentsize=int(min_component_faces))
        ms.meshing_remove_unreferenced_vertices()
    if iterations > 0 and ms.current_mesh().face_number() > 0:
        ms.meshing_isotropic_explicit_remeshing(
            iterations=int(iterations),
            targetlen=pymeshlab.PureValue(float(spacing_m * edge_factor * 1e3)),
            featuredeg=60.0,
            checksurfdist=False,  # reprojection keeps the surface; the check made it 3x slower
            reprojectflag=True,
        )
    m = ms.current_mesh()
    out_v = np.asarray(m.vertex_matrix(), dtype=np.float64) * 1e-3
    out_f = np.asarray(m.face_matrix(), dtype=np.int64)
    info["faces_after_remesh"] = int(len(out_f))
    return out_v, out_f, info
