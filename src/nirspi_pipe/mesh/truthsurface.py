"""The true surface that the 3D metrics measure against (issue 44, docs/mesh.md "What each 3D
metric is measured against").

The truth is sampled by point rays, never by pixel averages: the scene model is rendered again
on a grid :data:`FINE_FACTOR` times finer than the scored grid with one ray per fine pixel
(``supersample = 1``), so every sample is an exact hit of the ray through its fine pixel centre
(no partly covered sample, no depth averaged over two surfaces). The samples are triangulated on
the fine grid only where neighbours lie on one surface (:func:`same_surface`), so no face bridges
a silhouette or a depth jump. Without a scene model the scored grid's own truth is used, with the
same jump rule.

With ``FINE_FACTOR = 4`` and a scene rendered at its default ``supersample = 4``, the fine samples
of a scored pixel are exactly the rays its truth value averaged (``Camera.pixel_coords``: sub-pixel
offsets ``(i + 0.5)/s``), so :func:`inner_pixels` knows which scored pixels are fully covered by
one surface.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from nirspi_pipe.mesh.pointcloud import back_project
from nirspi_pipe.scene.render import render_cached
from nirspi_pipe.types import Camera, Scene

__all__ = ["FINE_FACTOR", "MAX_SLOPE", "TruthSurface", "inner_pixels", "same_surface", "surface_faces", "truth_surface"]

#: Fine samples per scored pixel side. Assumed: 4 makes the metric's own floor (the true surface
#: against itself, sampled as a mesh is) small against the pixel pitch (docs/mesh.md states the
#: measured floor), and equals the scenes' default supersampling, so a scored pixel's fine samples
#: are the rays its truth averaged.
FINE_FACTOR = 4
#: The largest grid side the fine render may reach (a 4096² scored grid is not refined).
MAX_FINE_SIDE = 2048
#: Slope limit of the jump rule: two neighbouring samples are on one surface when their depth
#: difference is at most ``MAX_SLOPE`` times their lateral separation at the nearer depth, i.e.
#: the surface between them is tilted less than ``atan(MAX_SLOPE)`` = 80° from facing the camera.
#: Assumed: tan(80°); a surface seen within 10° of grazing is sampled more than 5.7 footprints
#: apart in depth per grid step and cannot be told from a silhouette on the grid; the steepest
#: face of the project's shapes that must stay connected is the plate turned 75° (tan 75° = 3.73,
#: scene shape kind plate_edge).
MAX_SLOPE = float(np.tan(np.deg2rad(80.0)))


@dataclass(frozen=True)
class TruthSurface:
    """Samples of the true visible surface on a grid (camera frame, metres).

    Attributes:
        points: ``(h·w, 3)`` back-projected samples (rows of missed rays are meaningless).
        hit: ``(h, w)`` bool, the sample's ray hits the object.
        faces: ``(f, 3)`` triangles of sample indices, none across a depth jump.
        factor: samples per scored pixel side (1: the scored grid itself).
        camera: the grid the samples lie on.
    """

    points: np.ndarray
    hit: np.ndarray
    faces: np.ndarray
    factor: int
    camera: Camera

    def cloud(self) -> np.ndarray:
        """The points the chamfer compares with: every hit sample plus the centroid of every face
        (the faces join samples of one surface, so a centroid lies on it up to its sag)."""
        pts = self.points[self.hit.ravel()]
        if len(self.faces):
            pts = np.concatenate([pts, self.points[self.faces].mean(axis=1)])
        return pts


def same_surface(depth_m: np.ndarray, hit: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The jump rule on a grid: bool arrays for the right ``(h, w-1)``, down ``(h-1, w)`` and
    anti-diagonal ``(h-1, w-1)`` (top-right to bottom-left) neighbour pairs, True where both samples
    hit and ``|Δz| ≤ MAX_SLOPE · min(z) · |Δ(x/z, y/z)|`` (the lateral separation at the nearer
    depth)."""
    z = np.where(hit, depth_m, np.nan)
    step = 1.0 / camera.focal_px  # normalised image distance of one grid step

    def pair(a: np.ndarray, b: np.ndarray, dist: float) -> np.ndarray:
        with np.errstate(invalid="ignore"):
            ok = np.abs(a - b) <= MAX_SLOPE * np.fmin(a, b) * dist
        return ok & np.isfinite(a) & np.isfinite(b)

    right = pair(z[:, :-1], z[:, 1:], step)
    down = pair(z[:-1, :], z[1:, :], step)
    anti = pair(z[:-1, 1:], z[1:, :-1], step * np.sqrt(2.0))
    return right, down, anti


def surface_faces(depth_m: np.ndarray, hit: np.ndarray, camera: Camera) -> np.ndarray:
    """The triangles of ``grid_triangles(hit)`` whose three edges obey the jump rule
    (:func:`same_surface`). ``grid_triangles`` splits each 2×2 block (a b / c d) into (a, c, b)
    and (b, c, d): their edges are the block's sides and its anti-diagonal b–c."""
    right, down, anti = same_surface(depth_m, hit, camera)
    t1 = right[:-1, :] & down[:, :-1] & anti  # a-b, a-c, b-c
    t2 = right[1:, :] & down[:, 1:] & anti  # c-d, b-d, b-c
    h, w = hit.shape
    idx = np.arange(h * w).reshape(h, w)
    ia, ib, ic, id_ = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    f1 = np.stack([ia, ic, ib], axis=-1)[t1]
    f2 = np.stack([ib, ic, id_], axis=-1)[t2]
    return np.concatenate([f1, f2]).reshape(-1, 3)


def truth_surface(truth: Scene, scene_model: Any = None, factor: int = FINE_FACTOR) -> TruthSurface:
    """The true surface of ``truth``'s view: ``scene_model`` rendered with one ray per sample on a
    grid ``factor`` times finer (same field of view), or, without a scene model (or one that has no
    ``supersample`` to set), ``truth``'s own grid: its pixels with ``mask`` (coverage ≥ 0.5), each
    at the mean depth of its hitting rays, and ``factor`` = 1. Faces obey the jump rule."""
    cam = truth.camera
    fine = _fine_render(truth, scene_model, factor)
    if fine is None:
        hit = np.asarray(truth.mask, dtype=bool) & np.isfinite(truth.depth_m)
        depth, grid, factor = truth.depth_m, cam, 1
    else:
        hit = np.asarray(fine.coverage, dtype=np.float64) > 0.0  # one ray per sample: 0 or 1
        hit &= np.isfinite(fine.depth_m)
        depth, grid = fine.depth_m, fine.camera
    z = np.where(hit, depth, 0.0)
    points = back_project(z, grid).reshape(-1, 3)
    return TruthSurface(points=points, hit=hit, faces=surface_faces(depth, hit, grid), factor=factor, camera=grid)


def _fine_render(truth: Scene, scene_model: Any, factor: int) -> Scene | None:
    """``scene_model`` rendered with ``supersample = 1`` on the ``factor``-times finer grid, or None
    (no model, no ``supersample`` field, a grid beyond :data:`MAX_FINE_SIDE`, or a render of
    another size)."""
    if scene_model is None or factor < 1 or not dataclasses.is_dataclass(scene_model) or isinstance(scene_model, type):
        return None
    if "supersample" not in {f.name for f in dataclasses.fields(scene_model)}:
        return None
    side = truth.camera.resolution * factor
    if side > MAX_FINE_SIDE:
        return None
    model = dataclasses.replace(scene_model, supersample=1)
    fine = render_cached(model, truth.camera.resampled(side))
    if fine.depth_m.shape != (side, side):
        return None
    return fine


def inner_pixels(surface: TruthSurface, shape: tuple[int, int]) -> np.ndarray | None:
    """Scored pixels ``shape`` fully inside one surface: all their ``factor²`` samples hit and every
    neighbour pair among them obeys the jump rule. None when the surface is not on a finer grid
    (``factor`` = 1: the scored grid's truth has no sub-pixel samples)."""
    k = surface.factor
    n0, n1 = shape
    if k <= 1 or surface.hit.shape != (n0 * k, n1 * k):
        return None
    grid = surface.camera
    depth = surface.points[:, 2].reshape(surface.hit.shape)
    right, down, _ = same_surface(depth, surface.hit, grid)
    full = surface.hit.reshape(n0, k, n1, k).all(axis=(1, 3))
    # pairs inside a pixel: drop the pairs that straddle two pixels, then require all of them
    r_inside = np.ones((n0 * k, n1 * k - 1), dtype=bool)
    r_inside[:, k - 1 :: k] = False
    r_ok = np.where(r_inside, right, True)
    r_ok = np.concatenate([r_ok, np.ones((n0 * k, 1), dtype=bool)], axis=1)
    d_inside = np.ones((n0 * k - 1, n1 * k), dtype=bool)
    d_inside[k - 1 :: k, :] = False
    d_ok = np.where(d_inside, down, True)
    d_ok = np.concatenate([d_ok, np.ones((1, n1 * k), dtype=bool)], axis=0)
    one = r_ok.reshape(n0, k, n1, k).all(axis=(1, 3)) & d_ok.reshape(n0, k, n1, k).all(axis=(1, 3))
    return np.asarray(full & one, dtype=bool)
