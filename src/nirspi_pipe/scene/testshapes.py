"""Shapes nobody tuned for (issue 14): generated in code, ray-cast as smooth triangle meshes.

Scene ``shape`` with ``kind``:

* ``plate_edge``: a thin plate (``size_mm`` × 0.6·size × 3 mm) turned 75° about the vertical
  axis, so the camera sees its 3 mm edge and the broad face at a grazing angle.
* ``ring``: a thin torus (ring radius 0.4·size, tube radius 0.08·size), tilted 30°.
* ``bowl``: the inside of a spherical bowl (radius 0.6·size, rim at 60° from its bottom), opening
  towards the camera: a concave surface.
* ``multi``: three separate spheres of radii 0.24, 0.18 and 0.14·size at different places and
  depths.
* ``partial``: a sphere of diameter ``size_mm`` whose centre sits 0.56·size right of the axis:
  at the default distance the image border cuts it.
* ``off_centre``: a sphere of diameter 0.6·size, up and to the left of the axis, whole in view.
* ``vase``: the camera-facing half of a surface of revolution about the vertical axis, radius
  profile ``R(y)`` with a body, a neck and a lip (``R`` has two maxima and a minimum between):
  a vase-like height field whose singular points (``I = 1``) lie at three different depths.

All lengths scale with ``size_mm`` (default 50 mm, the paper's sphere) and the object sits at
``distance_mm`` plus ``offset_mm``; ``rotation_deg`` turns it about its centre before placing.
Every surface is a parametric triangle mesh with analytic vertex normals, interpolated over the
triangles (smooth shading), ray-cast exactly (:func:`~nirspi_pipe.scene.shapes.raycast_mesh`).
Lambertian, light at the camera (:func:`~nirspi_pipe.scene.render.compose_scene`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.ranges import check_ranges
from nirspi_pipe.scene.render import DistanceMm, Reflectance, Supersample, check_size, compose_scene
from nirspi_pipe.scene.shapes import raycast_mesh, rotation_matrix
from nirspi_pipe.types import Camera, Scene

__all__ = ["KINDS", "GeneratedShape", "grid_surface", "render_smooth_mesh", "shape_mesh"]

KINDS = ("plate_edge", "ring", "bowl", "multi", "partial", "off_centre", "vase")


def grid_surface(points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Triangles of a ``(a, b, 3)`` grid of surface points with normals ``(a, b, 3)``:
    ``(vertices (a·b, 3), normals (a·b, 3), faces (2(a−1)(b−1), 3))``."""
    a, b = points.shape[:2]
    idx = np.arange(a * b).reshape(a, b)
    p, q, r, s = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    faces = np.concatenate([np.stack([p, r, q], -1).reshape(-1, 3), np.stack([q, r, s], -1).reshape(-1, 3)])
    return points.reshape(-1, 3), normals.reshape(-1, 3), faces


def _sphere(
    radius: float, centre: tuple[float, float, float], n: int = 48
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    th, ph = np.meshgrid(np.linspace(0.0, np.pi, n + 1), np.linspace(0.0, 2 * np.pi, 2 * n + 1), indexing="ij")
    nrm = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    return grid_surface(radius * nrm + np.asarray(centre), nrm)


def _merge(parts: Sequence[tuple[np.ndarray, ...]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    verts, norms, faces, off = [], [], [], 0
    for v, nr, f in parts:
        verts.append(v)
        norms.append(nr)
        faces.append(f + off)
        off += len(v)
    return np.concatenate(verts), np.concatenate(norms), np.concatenate(faces)


def _box(sx: float, sy: float, sz: float, n: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A box centred at the origin, six flat faces (normals constant per face)."""
    parts = []
    half = np.array([sx, sy, sz]) / 2
    u = np.linspace(-1.0, 1.0, n + 1)
    uu, vv = np.meshgrid(u, u, indexing="ij")
    for axis in range(3):
        for sign in (-1.0, 1.0):
            pts = np.zeros((n + 1, n + 1, 3))
            a, b = [i for i in range(3) if i != axis]
            pts[..., axis] = sign * half[axis]
            pts[..., a] = uu * half[a]
            pts[..., b] = vv * half[b]
            nrm = np.zeros_like(pts)
            nrm[..., axis] = sign
            parts.append(grid_surface(pts, nrm))
    return _merge(parts)


def vase_profile(y: np.ndarray, size: float) -> np.ndarray:
    """Radius ``R(y)`` (units of ``size``) of the vase for heights ``y`` in ``[−size/2, size/2]``:
    a body (maximum near ``y = −0.15·size``), a neck (minimum near ``y = 0.17·size``) and a lip
    (maximum near ``y = 0.33·size``), closed to 0 at both ends."""
    t = np.asarray(y) / size
    body = 0.30 * np.exp(-(((t + 0.15) / 0.2) ** 2))
    lip = 0.17 * np.exp(-(((t - 0.34) / 0.07) ** 2))
    return size * (0.07 + body + lip) * np.sqrt(np.clip(1.0 - (2.0 * t) ** 2, 0.0, 1.0))


def _vase(size: float, n: int = 160) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    y = np.linspace(-0.5 * size, 0.5 * size, n + 1)
    r = vase_profile(y, size)
    dr = np.gradient(r, y)
    ph = np.linspace(0.0, np.pi, n // 2 + 1)
    yy, pp = np.meshgrid(y, ph, indexing="ij")
    rr, dd = np.meshgrid(r, ph, indexing="ij")[0], np.meshgrid(dr, ph, indexing="ij")[0]
    # front half of a surface of revolution about y, facing -z (the camera)
    pts = np.stack([rr * np.cos(pp), yy, -rr * np.sin(pp)], -1)
    nrm = np.stack([np.cos(pp), -dd, -np.sin(pp)], -1)
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    return grid_surface(pts, nrm)


def _bowl(radius: float, rim_deg: float = 60.0, n: int = 64) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inside of a spherical cap: bottom at ``z = +radius`` (far), rim towards the camera (−z)."""
    th, ph = np.meshgrid(
        np.linspace(0.0, np.deg2rad(rim_deg), n + 1), np.linspace(0.0, 2 * np.pi, 2 * n + 1), indexing="ij"
    )
    d = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    pts = radius * d - np.array([0.0, 0.0, radius * np.cos(np.deg2rad(rim_deg))])  # rim at z = 0 plane
    return grid_surface(pts, -d)  # inward normals: the concave side faces the camera


def _torus(ring: float, tube: float, n: int = 96) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    u, v = np.meshgrid(np.linspace(0.0, 2 * np.pi, n + 1), np.linspace(0.0, 2 * np.pi, n // 3 + 1), indexing="ij")
    nrm = np.stack([np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v)], -1)
    centre = np.stack([ring * np.cos(u), ring * np.sin(u), np.zeros_like(u)], -1)
    return grid_surface(centre + tube * nrm, nrm)


def shape_mesh(kind: str, size: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(vertices, vertex normals, faces)`` of a test shape, in the units of ``size``, centred
    near the origin (before rotation and placement)."""
    if kind == "plate_edge":
        return _box(size, 0.6 * size, 0.06 * size)
    if kind == "ring":
        return _torus(0.4 * size, 0.08 * size)
    if kind == "bowl":
        return _bowl(0.6 * size)
    if kind == "multi":
        return _merge(
            [
                _sphere(0.24 * size, (-0.40 * size, -0.20 * size, 0.0)),
                _sphere(0.18 * size, (0.36 * size, 0.25 * size, 0.3 * size)),
                _sphere(0.14 * size, (0.25 * size, -0.40 * size, -0.2 * size)),
            ]
        )
    if kind == "partial":
        return _sphere(0.5 * size, (0.56 * size, 0.0, 0.0))
    if kind == "off_centre":
        return _sphere(0.3 * size, (-0.36 * size, 0.3 * size, 0.0))
    if kind == "vase":
        return _vase(size)
    raise ConfigError("kind", kind, ", ".join(KINDS))


def render_smooth_mesh(
    name: str,
    camera: Camera,
    supersample: int,
    verts_m: np.ndarray,
    vnormals: np.ndarray,
    faces: np.ndarray,
    reflectance: float,
    distance_m: float,
) -> Scene:
    """Ray-cast a mesh with given vertex normals (interpolated, two-sided) into a :class:`Scene`."""
    rays, t, tri, u, v = raycast_mesh(camera, supersample, verts_m, faces)
    hit = tri >= 0
    f3 = faces[tri[hit]]
    uh, vh = u[hit][:, None], v[hit][:, None]
    nh = (1 - uh - vh) * vnormals[f3[:, 0]] + uh * vnormals[f3[:, 1]] + vh * vnormals[f3[:, 2]]
    nh /= np.maximum(np.linalg.norm(nh, axis=-1, keepdims=True), 1e-300)
    nh[np.einsum("ik,ik->i", nh, rays[hit]) > 0] *= -1.0  # two-sided: face the camera
    nrm = np.zeros(rays.shape)
    nrm[hit] = nh
    return compose_scene(name, camera, rays, hit, t, nrm, np.full(hit.shape, float(reflectance)), distance_m)


@dataclass(frozen=True)
class GeneratedShape:
    """Scene ``shape``: one of the generated test shapes (module docstring).

    Attributes:
        kind: ``plate_edge``, ``ring``, ``bowl``, ``multi``, ``partial``, ``off_centre`` or ``vase``.
        size_mm: overall size, mm (all the shape's lengths scale with it).
        distance_mm: camera to the shape's centre, mm.
        offset_mm: ``[x, y]`` shift of the centre across the view, mm (+x right, +y up).
        rotation_deg: ``[rx, ry, rz]`` rotation about the centre, degrees (``Rx·Ry·Rz``).
        reflectance: Lambertian reflectance, 0–1.
        supersample: rays per pixel side.
    """

    kind: str = "vase"
    size_mm: float = 50.0
    distance_mm: DistanceMm = 200.0
    offset_mm: tuple[float, float] = field(default=(0.0, 0.0))
    rotation_deg: tuple[float, float, float] = field(default=(0.0, 0.0, 0.0))
    reflectance: Reflectance = 0.8
    supersample: Supersample = 4

    def __post_init__(self) -> None:
        check_ranges(self)
        if self.kind not in KINDS:
            raise ConfigError("kind", self.kind, ", ".join(KINDS))
        check_size(self, "size_mm", limit=1.0)
        off = np.asarray(self.offset_mm, dtype=np.float64)
        if off.shape != (2,) or not np.all(np.isfinite(off)):
            raise ConfigError("offset_mm", self.offset_mm, "[x, y] in mm")
        rot = np.asarray(self.rotation_deg, dtype=np.float64)
        if rot.shape != (3,) or not np.all(np.isfinite(rot)):
            raise ConfigError("rotation_deg", self.rotation_deg, "[rx, ry, rz] in degrees")

    def placed(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Camera-frame ``(vertices (m), vertex normals, faces)``."""
        v, nr, f = shape_mesh(self.kind, self.size_mm)
        rot = rotation_matrix(tuple(float(a) for a in self.rotation_deg))  # type: ignore[arg-type]
        centre = np.array([self.offset_mm[0], self.offset_mm[1], self.distance_mm])
        return (v @ rot.T + centre) * 1e-3, nr @ rot.T, f

    def render(self, camera: Camera) -> Scene:
        """Ray-cast the shape (smooth shading, two-sided)."""
        v, nr, f = self.placed()
        return render_smooth_mesh(
            self.kind, camera, self.supersample, v, nr, f, self.reflectance, self.distance_mm * 1e-3
        )
