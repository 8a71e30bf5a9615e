"""Files a 3D run writes next to its record: ``mesh.ply`` and ``mesh.png``.

``mesh.png`` is an off-screen pyvista render (EGL here; no display needed) of the final mesh
beside the ground-truth surface (the true depth map back-projected and triangulated, on the grid
the 3D metrics score depth on: the upscaled 32² one on the device preset), both in millimetres in
the camera frame, seen from beside the camera, each with a 3D ruler of :data:`SCALE_BAR_MM` along
x under the object (perspective: the ruler is true to scale at its own depth).
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np

from nirspi_pipe.stages import Products
from nirspi_pipe.types import Mesh, Scene

__all__ = ["SCALE_BAR_MM", "render_meshes", "truth_mesh", "warm_up", "write_mesh_outputs", "write_ply"]

SCALE_BAR_MM = 20.0  # length of the ruler under each mesh (mm): assumed, 40 % of the Ø50 mm sphere


def _polydata(vertices_m: np.ndarray, faces: np.ndarray):
    import pyvista as pv  # start-up: loads 6ec57f84c680d3a3778b__mypyc, librt, mypy (248 ms here)

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
    # start-up: loads scipy, charset_normalizer (263 ms here)
    from nirspi_pipe.mesh.pointcloud import (
        back_project,
        grid_triangles,
    )

    mask = truth.mask & np.isfinite(truth.depth_m)
    verts = back_project(np.where(mask, truth.depth_m, 0.0), truth.camera).reshape(-1, 3)
    faces = grid_triangles(mask)
    used, inv = np.unique(faces, return_inverse=True)
    return Mesh(vertices_m=verts[used], faces=inv.reshape(-1, 3))


def render_meshes(path: Path, mesh: Mesh, truth: Mesh | None, size: tuple[int, int] = (900, 450)) -> Path:
    """Off-screen render (PNG) of ``mesh`` (left) beside ``truth`` (right), same camera."""
    if not os.environ.get("DISPLAY"):
        # headless: go straight to EGL instead of failing over from X with a warning (VTK >= 9.4)
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
    import pyvista as pv  # start-up: loads 6ec57f84c680d3a3778b__mypyc, librt, mypy (248 ms here)

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
            if len(m.faces):
                v = np.asarray(m.vertices_m) * 1e3
                x0, y0 = float(v[:, 0].min()), float(v[:, 1].min()) - 4.0  # 4 mm under the object
                # from +x to -x: seen from the camera's side +x is on the left, so 0 reads on the left
                plotter.add_ruler(  # type: ignore[call-arg]  # pyvista 0.49 types its decorator without self
                    pointa=(x0 + SCALE_BAR_MM, y0, float(centre[2])),
                    pointb=(x0, y0, float(centre[2])),
                    title=f"{SCALE_BAR_MM:g} mm",
                    number_labels=2,  # 0 and 20: a middle "10" lay under the centred title "20 mm"
                    label_format="%.0f",
                    font_size_factor=0.8,
                    label_color="black",
                    tick_color="black",
                )
            plotter.camera_position = [(centre[0] - 80.0, centre[1] + 60.0, 0.0), tuple(centre), (0.0, 1.0, 0.0)]
            plotter.camera.zoom(1.4)  # the object and its ruler fill the panel (the object filled a fifth)
        plotter.screenshot(str(path))
    finally:
        plotter.close()
    return path


def write_mesh_outputs(folder: Path, products: Products, render: bool = True, truth: Scene | None = None) -> list[Path]:
    """Write ``mesh.ply`` and (when ``render``) ``mesh.png`` into ``folder`` when the run produced
    a mesh with faces; returns the written paths (empty otherwise). A failing render is warned
    about, not raised. The runner passes ``render = output.images``: sweeps that write no images
    skip the off-screen render (hundreds of ms per job). ``truth``: the ground truth to draw
    beside the mesh (the runner passes the one depth is scored against,
    :func:`nirspi_pipe.mesh.metrics3d.run_depth_truth`); default ``products.truth``."""
    mesh = products.mesh
    if mesh is None or len(mesh.faces) == 0:
        return []
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written = [write_ply(folder / "mesh.ply", mesh)]
    if not render:
        return written
    try:
        scene = truth if truth is not None else products.truth
        written.append(render_meshes(folder / "mesh.png", mesh, truth_mesh(scene) if scene is not None else None))
    except Exception as exc:  # noqa: BLE001 - a missing GL context must not fail the run
        warnings.warn(f"mesh render failed: {type(exc).__name__}: {exc}", stacklevel=2)
    return written


def warm_up() -> None:
    """Import pyvista (0.5 s), through which ``mesh.ply`` and ``mesh.png`` are written."""
    # warm-up: loads 6ec57f84c680d3a3778b__mypyc, librt, mypy (248 ms here), before jobs fork
    import pyvista  # noqa: F401
