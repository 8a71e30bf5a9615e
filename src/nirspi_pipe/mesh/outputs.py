"""Files a 3D run writes next to its record: ``mesh.ply`` and ``mesh.png``.

``mesh.png`` is an off-screen pyvista render (EGL here; no display needed) of the final mesh
beside the ground-truth surface (the true depth map back-projected and triangulated), both in
millimetres in the camera frame, seen from behind the camera.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from nirspi_pipe.stages import Products
from nirspi_pipe.types import Mesh, Scene

__all__ = ["render_meshes", "truth_mesh", "warm_up", "write_mesh_outputs", "write_ply"]


def _polydata(vertices_m: np.ndarray, faces: np.ndarray):
    import pyvista as pv

    f = np.asarray(faces, dtype=np.int64)
    cells = np.column_stack([np.full(len(f), 3, dtype=np.int64), f]).ravel()
    return pv.PolyData(np.asarray(vertices_m, dtype=np.float64) * 1e3, cells)


def write_ply(path: Path, mesh: Mesh) -> Path:
    """Write ``mesh`` as a binary PLY file (vertices in millimetres). Returns the path."""
    _polydata(mesh.vertices_m, mesh.faces).save(str(path))
    return path


def truth_mesh(truth: Scene) -> Mesh:
    """The ground-truth visible surface as a triangle mesh (metres): the true depth map
    back-projected, two triangles per 2×2 block of object pixels."""
    from nirspi_pipe.mesh.fusion import back_project, grid_triangles

    mask = truth.mask & np.isfinite(truth.depth_m)
    verts = back_project(np.where(mask, truth.depth_m, 0.0), truth.camera).reshape(-1, 3)
    faces = grid_triangles(mask)
    used, inv = np.unique(faces, return_inverse=True)
    return Mesh(vertices_m=verts[used], faces=inv.reshape(-1, 3))


def render_meshes(path: Path, mesh: Mesh, truth: Mesh | None, size: tuple[int, int] = (900, 450)) -> Path:
    """Off-screen render (PNG) of ``mesh`` (left) beside ``truth`` (right), same camera."""
    import os

    if not os.environ.get("DISPLAY"):
        # headless: go straight to EGL instead of failing over from X with a warning (VTK >= 9.4)
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista as pv

    shape = (1, 2) if truth is not None else (1, 1)
    plotter = pv.Plotter(off_screen=True, shape=shape, window_size=list(size))
    try:
        panels = [("reconstruction", mesh, "lightsteelblue")]
        if truth is not None:
            panels.append(("ground truth", truth, "wheat"))
        for col, (title, m, colour) in enumerate(panels):
            plotter.subplot(0, col)
            if len(m.faces):
                plotter.add_mesh(
                    _polydata(m.vertices_m, m.faces),
                    color=colour,
                    show_edges=True,
                    edge_color="dimgray",
                    line_width=0.5,
                    smooth_shading=False,
                )
            plotter.add_text(title, font_size=10)
            # the device looks along +z with +y up: view from near the device, a little off axis
            centre = np.asarray(m.vertices_m).mean(axis=0) * 1e3 if len(m.vertices_m) else np.array([0, 0, 200.0])
            plotter.camera_position = [(centre[0] - 80.0, centre[1] + 60.0, 0.0), tuple(centre), (0.0, 1.0, 0.0)]
        plotter.screenshot(str(path))
    finally:
        plotter.close()
    return path


def write_mesh_outputs(folder: Path, products: Products, render: bool = True) -> list[Path]:
    """Write ``mesh.ply`` and (when ``render``) ``mesh.png`` into ``folder`` when the run produced
    a mesh with faces; returns the written paths (empty otherwise). A failing render is warned
    about, not raised. The runner passes ``render = output.images``: sweeps that write no images
    skip the off-screen render (hundreds of ms per job)."""
    mesh = products.mesh
    if mesh is None or len(mesh.faces) == 0:
        return []
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = [write_ply(folder / "mesh.ply", mesh)]
    if not render:
        return written
    try:
        truth = truth_mesh(products.truth) if products.truth is not None else None
        written.append(render_meshes(folder / "mesh.png", mesh, truth))
    except Exception as exc:  # noqa: BLE001 - a missing GL context must not fail the run
        warnings.warn(f"mesh render failed: {type(exc).__name__}: {exc}", stacklevel=2)
    return written


def warm_up() -> None:
    """Import pyvista (0.5 s), through which ``mesh.ply`` and ``mesh.png`` are written."""
    import pyvista  # noqa: F401
