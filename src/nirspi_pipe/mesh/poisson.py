"""Surface ``poisson``: screened Poisson reconstruction (Kazhdan & Hoppe 2013) via pymeshlab.

Normals come from the fusion stage (PCA, oriented towards the camera) when the cloud has them,
else from pymeshlab's ``compute_normal_for_point_clouds`` oriented towards the camera at the
origin (``viewpos``). Coordinates are handed to pymeshlab in millimetres (some of its
thresholds are absolute) and converted back to metres. ``generate_surface_reconstruction_screened_poisson`` always returns a
closed surface; for one-sided depth data its back is extrapolation, so with ``closed: false``
(default) the faces farther than ``trim_factor`` median sample spacings from the samples are
removed (the same rule as the power crust's).
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated, Any

import numpy as np

from nirspi_pipe.errors import NirspiError
from nirspi_pipe.mesh.outputs import warm_up as warm_up_outputs
from nirspi_pipe.mesh.powercrust import trim_to_samples
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
from nirspi_pipe.ranges import Range, check_ranges
from nirspi_pipe.types import Mesh, PointCloud

__all__ = ["ScreenedPoisson"]


@dataclass(frozen=True)
class ScreenedPoisson:
    """Surface ``poisson``: pymeshlab's screened Poisson surface reconstruction.

    Attributes:
        depth: octree depth (pymeshlab ``depth``), 4–12.
        point_weight: screening weight (pymeshlab ``pointweight``), >= 0; 0 = plain Poisson.
        samples_per_node: minimum samples per octree node (``samplespernode``), >= 1.
        normal_knn: neighbours for normal estimation when the cloud has no normals.
        closed: keep the whole closed surface (True) or only the part near the samples.
        trim_factor: with ``closed: false``, the distance to the nearest sample, in median sample
            spacings, beyond which a face is dropped.
        remesh_iterations: rounds of isotropic remeshing after clean-up
            (:func:`~nirspi_pipe.mesh.remesh.clean_and_remesh`); 0 = clean-up only.
        remesh_edge_factor: target edge length, × the cloud's median sample spacing.
        max_hole_edges: clean-up closes holes bounded by at most this many edges (0 = none).
        remesher: ``auto``, ``compiled`` or ``pymeshlab``
            (:func:`~nirspi_pipe.mesh.remesh.resolve_remesher`); ``info.surface.remesher`` says which ran.
    """

    depth: Annotated[int, Range(4, 12, "an integer", integer=True)] = 6
    point_weight: Annotated[float, Range(0.0, None, "a weight")] = 4.0
    samples_per_node: Annotated[float, Range(1.0, None, "a number")] = 1.5
    normal_knn: Annotated[int, Range(3, 100, "an integer", integer=True)] = 10
    closed: bool = False
    trim_factor: Annotated[float, Range(0.0, None, "a factor", lo_open=True)] = 1.5
    remesh_iterations: RemeshIterations = 0
    remesh_edge_factor: RemeshEdgeFactor = 1.0
    max_hole_edges: MaxHoleEdges = 30
    remesher: Remesher = "auto"

    @classmethod
    def warm_up(cls, params: Mapping[str, Any]) -> None:
        """Load pymeshlab, the remesher and the mesh writers (:class:`nirspi_pipe.stages.WarmsUp`)."""
        load_meshlab()
        resolve_remesher(str(params.get("remesher", cls.remesher)))
        warm_up_outputs()

    def __post_init__(self) -> None:
        check_ranges(self)  # before any import or compilation: a bad key is refused at once
        load_meshlab()  # at build, outside the timed stage
        object.__setattr__(self, "_remesher", resolve_remesher(self.remesher))

    def reconstruct(self, cloud: PointCloud) -> Mesh:
        """Screened Poisson mesh of ``cloud.points_m`` (metres)."""
        import pymeshlab  # start-up: loads pymeshlab (208 ms here)

        pts = np.asarray(cloud.points_m, dtype=np.float64)
        if len(pts) < 4 or not np.all(np.isfinite(pts)):
            raise NirspiError(f"poisson: needs at least 4 finite points, got {len(pts)}")
        ms = pymeshlab.MeshSet()
        if cloud.normals is not None and np.all(np.isfinite(cloud.normals)):
            ms.add_mesh(
                pymeshlab.Mesh(vertex_matrix=pts * 1e3, v_normals_matrix=np.asarray(cloud.normals, dtype=np.float64))
            )
        else:
            ms.add_mesh(pymeshlab.Mesh(vertex_matrix=pts * 1e3))
            ms.compute_normal_for_point_clouds(k=int(self.normal_knn), viewpos=np.zeros(3))
        ms.generate_surface_reconstruction_screened_poisson(
            depth=int(self.depth),
            pointweight=float(self.point_weight),
            samplespernode=float(self.samples_per_node),
            fulldepth=min(5, int(self.depth)),
            preclean=True,
            threads=1,  # the machine is shared: more threads were 10x slower under load
        )
        m = ms.current_mesh()
        verts = np.asarray(m.vertex_matrix(), dtype=np.float64) * 1e-3
        faces = np.asarray(m.face_matrix(), dtype=np.int64)
        info: dict[str, Any] = {"faces_closed": int(len(faces))}
        spacing = sample_spacing(pts)  # once, for the trim and the remeshing
        if not self.closed and len(faces):
            verts, faces = trim_to_samples(verts, faces, pts, self.trim_factor, spacing)
        if len(faces) == 0:
            warnings.warn("poisson: empty surface", stacklevel=2)
        remesher = self._remesher  # type: ignore[attr-defined]
        verts, faces, rinfo = remesh_to_cloud(
            verts, faces, pts, self.remesh_iterations, self.remesh_edge_factor, self.max_hole_edges, spacing, remesher
        )
        info.update(rinfo)
        info["faces"] = int(len(faces))
        info["remesher"] = remesher
        return Mesh(vertices_m=verts, faces=faces, info=info)
