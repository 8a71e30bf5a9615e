"""Surface ``view``: the fused cloud triangulated as the camera sees it (issue 44).

A single-pixel camera's cloud is one-sided: every point was seen along its own ray from the
camera at the origin. This stage triangulates the points where the camera sees them, the
Delaunay triangulation of their normalised image coordinates ``(x/z, y/z)``, and keeps a
triangle only where its three edges join points of one surface:

* the **jump rule** of the true surface (:func:`nirspi_pipe.mesh.truthsurface.same_surface`):
  ``|Δz| ≤ MAX_SLOPE · min(z) · |Δ(x/z, y/z)|``, a surface tilted less than 80° from facing the
  camera, so no face bridges a silhouette or a depth jump;
* an **edge limit**: at most ``max_edge_factor`` times the cloud's median spacing in the image
  (each point's nearest neighbour there), so no face spans a hole, a gap between two objects or
  the empty inside of a ring.

Every face's vertices are cloud points, so the mesh cannot lose what the cloud holds: with the
exact depth the power crust kept 35-41 % of the plate's cloud and 8 % of the bowl's
(docs/mesh.md), this stage all of both. What it cannot do is close what the camera did not see
(a back, a hole): it is the mesh of a depth map, not of a solid. Optional isotropic remeshing
(:func:`~nirspi_pipe.mesh.remesh.remesh_to_cloud`) evens out the triangles' shapes, which
follow the fused points' spacing.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated, Any

import numpy as np
from scipy.spatial import Delaunay, QhullError, cKDTree

from nirspi_pipe.errors import NirspiError
from nirspi_pipe.mesh.outputs import warm_up as warm_up_outputs
from nirspi_pipe.mesh.powercrust import cloud_coverage
from nirspi_pipe.mesh.remesh import (
    MaxHoleEdges,
    RemeshEdgeFactor,
    Remesher,
    RemeshIterations,
    load_meshlab,
    remesh_to_cloud,
    resolve_remesher,
    sample_spacing,
)
from nirspi_pipe.mesh.truthsurface import MAX_SLOPE
from nirspi_pipe.ranges import Range, check_ranges
from nirspi_pipe.types import Mesh, PointCloud

__all__ = ["ViewTriangulation", "view_faces"]

#: Normalised image coordinates are rounded to this before the triangulation (radians at the
#: camera; about 1e-6 pixel at the project's focal lengths of 100-2000 px). Assumed, as the 3D
#: metrics' own snap (issue 12): the Delaunay diagonal of co-circular points (a fused cloud of
#: back-projected pixels has many) then sees the same input on every CPU kernel set, while the
#: rounding is ten orders of magnitude above the last bit of ``x/z``.
SNAP_RAD = 1e-9


def view_faces(points_m: np.ndarray, max_edge_factor: float) -> tuple[np.ndarray, np.ndarray, dict[str, int]]:
    """The triangulation of the module docstring: ``(vertices (v, 3), faces (f, 3), counts)``,
    where the vertices are the usable points (finite, ``z > 0``; one point per snapped image
    position, the nearest kept) that some kept face uses, and the faces are oriented towards the
    camera. Raises
    :class:`NirspiError` in one line where no triangle can be made."""
    p = np.asarray(points_m, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise NirspiError(f"surface view: needs points of shape (n, 3), got {p.shape}")
    p = p[np.isfinite(p).all(axis=1) & (p[:, 2] > 0)]
    uv = np.round(p[:, :2] / p[:, 2:3] / SNAP_RAD) * SNAP_RAD
    order = np.lexsort((p[:, 2], uv[:, 1], uv[:, 0]))  # the nearest of points on one ray first
    uv, p = uv[order], p[order]
    uv, first = np.unique(uv, axis=0, return_index=True)
    p = p[first]
    if len(p) < 3:
        raise NirspiError(
            f"surface view: needs at least 3 points in front of the camera on distinct rays, got {len(p)}"
        )
    try:
        tri = Delaunay(uv).simplices
    except QhullError as exc:  # all on one line through the image
        raise NirspiError(
            f"surface view: the points' image positions admit no triangle ({str(exc).splitlines()[0]})"
        ) from None
    spacing = float(np.median(cKDTree(uv).query(uv, k=2)[0][:, 1]))
    z = p[:, 2]
    keep_jump = np.ones(len(tri), dtype=bool)
    keep_edge = np.ones(len(tri), dtype=bool)
    for a, b in ((0, 1), (1, 2), (0, 2)):
        i, j = tri[:, a], tri[:, b]
        d = np.linalg.norm(uv[i] - uv[j], axis=1)
        keep_jump &= np.abs(z[i] - z[j]) <= MAX_SLOPE * np.minimum(z[i], z[j]) * d
        keep_edge &= d <= max_edge_factor * spacing
    faces = tri[keep_jump & keep_edge]
    normal = np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]])
    away = np.einsum("ij,ij->i", normal, p[faces].mean(axis=1)) > 0  # normal along the ray: away
    faces[away] = faces[away][:, [0, 2, 1]]
    used, faces = np.unique(faces, return_inverse=True)  # a point in no kept face is no vertex
    faces = faces.reshape(-1, 3)
    counts = {
        "points": int(len(p)),
        "vertices": int(len(used)),
        "triangles": int(len(tri)),
        "dropped_jump": int((~keep_jump).sum()),
        "dropped_long": int((keep_jump & ~keep_edge).sum()),
    }
    return p[used], faces.astype(np.int64), counts


@dataclass(frozen=True)
class ViewTriangulation:
    """Surface ``view``: the cloud triangulated in the image, without faces across depth jumps
    or holes (module docstring).

    Attributes:
        max_edge_factor: the longest edge kept, × the median distance between neighbouring points
            in the image. Assumed 2.5: it keeps the diagonal (√2) of points on a pixel grid with
            room for the fusion's irregular spacing, and drops a face across two or more missing
            samples.
        remesh_iterations: rounds of isotropic remeshing after clean-up
            (:func:`~nirspi_pipe.mesh.remesh.clean_and_remesh`); 0 (default) = the triangulation
            as it is, after clean-up.
        remesh_edge_factor: target edge length, × the cloud's median sample spacing.
        max_hole_edges: clean-up closes holes bounded by at most this many edges (0, default:
            none; a hole here is usually one the camera saw).
        remesher: ``auto``, ``compiled`` or ``pymeshlab``
            (:func:`~nirspi_pipe.mesh.remesh.resolve_remesher`).
    """

    max_edge_factor: Annotated[float, Range(1.0, 100.0, "a factor of the image spacing")] = 2.5
    remesh_iterations: RemeshIterations = 0
    remesh_edge_factor: RemeshEdgeFactor = 1.0
    max_hole_edges: MaxHoleEdges = 0
    remesher: Remesher = "auto"

    @classmethod
    def warm_up(cls, params: Mapping[str, Any]) -> None:
        """Load the remesher and the mesh writers (:class:`nirspi_pipe.stages.WarmsUp`)."""
        if int(params.get("remesh_iterations", cls.remesh_iterations) or 0) > 0:
            resolve_remesher(str(params.get("remesher", cls.remesher)))
            load_meshlab()
        warm_up_outputs()

    def __post_init__(self) -> None:
        check_ranges(self)
        if self.remesh_iterations > 0:
            object.__setattr__(self, "_remesher", resolve_remesher(self.remesher))

    def reconstruct(self, cloud: PointCloud) -> Mesh:
        """The view triangulation of ``cloud.points_m`` (metres)."""
        verts, faces, info = view_faces(cloud.points_m, self.max_edge_factor)
        if len(faces) == 0:
            raise NirspiError(
                f"surface view: every one of the {info['triangles']} triangles of the {info['points']} points "
                f"crosses a depth jump or is longer than surface.max_edge_factor={self.max_edge_factor:g} spacings"
            )
        out: dict[str, Any] = dict(info)
        if self.remesh_iterations > 0:
            remesher = self._remesher  # type: ignore[attr-defined]
            verts, faces, rinfo = remesh_to_cloud(
                verts,
                faces,
                verts,
                self.remesh_iterations,
                self.remesh_edge_factor,
                self.max_hole_edges,
                sample_spacing(verts),
                remesher,
            )
            if len(faces) == 0:
                raise NirspiError(f"surface view: the clean-up left no face of the {info['points']} points")
            out.update(rinfo)
            out["remesher"] = remesher
        out["faces"] = int(len(faces))
        pts = np.asarray(cloud.points_m, dtype=np.float64)
        pts = pts[np.isfinite(pts).all(axis=1) & (pts[:, 2] > 0)]
        # the power crust's measure of what the mesh lies near (docs/mesh.md), for comparison
        out["cloud_covered_fraction"] = cloud_coverage(verts, faces, pts, sample_spacing(pts))
        return Mesh(vertices_m=verts, faces=np.asarray(faces, dtype=np.int64), info=out)
