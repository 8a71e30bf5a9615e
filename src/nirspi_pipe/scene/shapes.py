"""The paper's test objects (§7) and triangle-mesh scenes.

* ``torus``: outer Ø55 mm, inner Ø25 mm (tube radius 7.5 mm, ring radius 20 mm), axis towards the
  camera by default; exact ray casting by sphere tracing its signed distance, exact normals.
* ``cube``: 40 mm, turned to show three faces; exact ray–box (slab) intersection.
* ``u_shape``: 65 × 40 × 17 mm, a bar and two arms (15 mm thick; the paper does not give it),
  the union of three boxes.
* ``plane``: a flat Lambertian board filling the view (the reflectance targets of Table 2).
* ``mesh``: any triangle mesh file (PLY, STL, OBJ; read by our bounded parser, :mod:`~nirspi_pipe.scene.meshfiles`), placed at the distance and
  scaled; Möller–Trumbore ray–triangle tests, vectorised, accelerated by binning each triangle
  into the pixels its projection covers (a pinhole camera at the origin makes that exact).

Every scene takes ``distance_mm`` (camera to object centre), ``reflectance`` (0–1),
``supersample`` (rays per pixel side) and ``rotation_deg`` (``[rx, ry, rz]``: the object is
rotated by ``Rx·Ry·Rz`` about its centre), and renders through
:func:`nirspi_pipe.scene.render.compose_scene`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.ranges import check_ranges
from nirspi_pipe.safeio import UnsafeInputError
from nirspi_pipe.scene.meshfiles import MeshFileError, read_mesh_file
from nirspi_pipe.scene.render import DistanceMm, Reflectance, Supersample, check_size, compose_scene
from nirspi_pipe.types import Camera, Scene

__all__ = [
    "rotation_matrix",
    "ray_boxes",
    "raycast_mesh",
    "closed_orientation",
    "load_mesh",
    "Torus",
    "Cube",
    "UShape",
    "Plane",
    "MeshScene",
]


def rotation_matrix(rotation_deg: tuple[float, float, float] | list[float]) -> np.ndarray:
    """``Rx(rx) · Ry(ry) · Rz(rz)`` (3 × 3) from Euler angles in degrees."""
    rx, ry, rz = np.deg2rad(np.asarray(rotation_deg, dtype=np.float64))
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    mx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    my = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    mz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return mx @ my @ mz


def _check_rotation(rotation_deg: Any) -> tuple[float, float, float]:
    """``rotation_deg`` as three floats; any other value (a config's, unchecked) is a one-line error."""
    rot: tuple[float, ...]
    try:
        rot = tuple(float(a) for a in rotation_deg)
    except TypeError:
        rot = ()
    if len(rot) != 3 or not all(np.isfinite(rot)):
        raise ConfigError("rotation_deg", rotation_deg, "three finite angles [rx, ry, rz] in degrees")
    return rot[0], rot[1], rot[2]


def ray_boxes(
    rays: np.ndarray, center_m: np.ndarray, rot: np.ndarray, boxes: list[tuple[np.ndarray, np.ndarray]]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Intersect rays from the origin with a union of boxes (slab method).

    Args:
        rays: ``(..., 3)`` unit directions (camera frame).
        center_m: object centre (m); rot: object-to-camera rotation.
        boxes: ``(centre, half_size)`` pairs in the object frame, metres.

    Returns ``(hit, t, normals)``: nearest hit distance along the ray (m) and its outward
    normal in the camera frame.
    """
    d = rays @ rot  # directions in the object frame (rot is orthonormal: Rᵀ d)
    d = np.where(np.abs(d) < 1e-15, 1e-15, d)
    o_all = (-center_m) @ rot
    t_best = np.full(rays.shape[:-1], np.inf)
    n_best = np.zeros(rays.shape)
    for c, h in boxes:
        o = o_all - c
        t1 = (-h - o) / d
        t2 = (h - o) / d
        tmin = np.minimum(t1, t2)
        tmax = np.maximum(t1, t2)
        tn = tmin.max(axis=-1)
        tf = tmax.min(axis=-1)
        hit = (tn <= tf) & (tn > 0) & (tn < t_best)
        axis = tmin.argmax(axis=-1)
        nl = np.zeros(rays.shape)
        np.put_along_axis(nl, axis[..., None], -np.sign(np.take_along_axis(d, axis[..., None], axis=-1)), axis=-1)
        t_best = np.where(hit, tn, t_best)
        n_best = np.where(hit[..., None], nl @ rot.T, n_best)
    return np.isfinite(t_best), t_best, n_best


@dataclass(frozen=True)
class Torus:
    """Scene ``torus``: a Lambertian torus (paper: outer Ø55 mm, inner Ø25 mm).

    Attributes:
        distance_mm: camera to torus centre, mm.
        outer_diameter_mm, inner_diameter_mm: outer and hole diameters, mm.
        reflectance: Lambertian reflectance in [0, 1].
        supersample: rays per pixel side (1–16).
        rotation_deg: ``[rx, ry, rz]``; ``[0, 0, 0]`` puts the axis along the view.
    """

    distance_mm: DistanceMm = 200.0
    outer_diameter_mm: float = 55.0
    inner_diameter_mm: float = 25.0
    reflectance: Reflectance = 0.8
    supersample: Supersample = 4
    rotation_deg: tuple[float, float, float] = (20.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        check_ranges(self)
        check_size(self, "outer_diameter_mm")
        if not np.isfinite(self.inner_diameter_mm) or not 0 <= self.inner_diameter_mm < self.outer_diameter_mm:
            raise ConfigError(
                "inner_diameter_mm", self.inner_diameter_mm, f"a diameter in mm in [0, {self.outer_diameter_mm:g})"
            )
        object.__setattr__(self, "rotation_deg", _check_rotation(self.rotation_deg))

    def render(self, camera: Camera) -> Scene:
        """Sphere-trace the torus's signed distance; exact normals from the ring geometry."""
        rays = camera.rays(self.supersample)
        c = np.array([0.0, 0.0, self.distance_mm * 1e-3])
        rot = rotation_matrix(self.rotation_deg)
        big = 0.25 * (self.outer_diameter_mm + self.inner_diameter_mm) * 1e-3  # ring radius
        tube = 0.25 * (self.outer_diameter_mm - self.inner_diameter_mm) * 1e-3
        d_loc = rays @ rot
        o_loc = (-c) @ rot
        bound = big + tube
        # only rays that hit the bounding sphere are traced
        b = rays @ c
        disc = b * b - (c @ c - bound * bound)
        cand = disc > 0
        t = np.where(cand, np.maximum(b - np.sqrt(np.maximum(disc, 0.0)), 0.0), np.inf)
        t_far = np.where(cand, b + np.sqrt(np.maximum(disc, 0.0)), -np.inf)
        idx = np.nonzero(cand.ravel())[0]
        dl = d_loc.reshape(-1, 3)[idx]
        tt = t.ravel()[idx]
        tf = t_far.ravel()[idx]
        hit = np.zeros(idx.size, dtype=bool)
        active = np.ones(idx.size, dtype=bool)
        eps = 1e-9 + 1e-7 * tube
        for _ in range(300):
            if not active.any():
                break
            a = np.nonzero(active)[0]
            p = o_loc + dl[a] * tt[a, None]
            q = np.hypot(np.hypot(p[:, 0], p[:, 1]) - big, p[:, 2])
            f = q - tube
            done = f < eps
            hit[a[done]] = True
            tt[a] += np.where(done, 0.0, f)
            out = tt[a] > tf[a]
            active[a[done | out]] = False
        t_flat = np.full(rays.shape[:-1], np.inf).ravel()
        t_flat[idx[hit]] = tt[hit]
        t_all = t_flat.reshape(rays.shape[:-1])
        hit_all = np.isfinite(t_all)
        p = o_loc + d_loc * np.where(hit_all, t_all, 0.0)[..., None]
        rxy = np.maximum(np.hypot(p[..., 0], p[..., 1]), 1e-12)
        ring = np.stack([big * p[..., 0] / rxy, big * p[..., 1] / rxy, np.zeros_like(rxy)], axis=-1)
        nl = p - ring
        nl /= np.maximum(np.linalg.norm(nl, axis=-1, keepdims=True), 1e-15)
        normals = np.where(hit_all[..., None], nl @ rot.T, 0.0)
        refl = np.full(hit_all.shape, float(self.reflectance))
        return compose_scene("torus", camera, rays, hit_all, t_all, normals, refl, self.distance_mm * 1e-3)


@dataclass(frozen=True)
class Cube:
    """Scene ``cube``: a Lambertian cube (paper: 40 mm), turned to show three faces.

    Attributes:
        distance_mm: camera to cube centre, mm.
        side_mm: edge length, mm.
        reflectance, supersample, rotation_deg: as in :class:`Torus`.
    """

    distance_mm: DistanceMm = 200.0
    side_mm: float = 40.0
    reflectance: Reflectance = 0.8
    supersample: Supersample = 4
    rotation_deg: tuple[float, float, float] = (25.0, 35.0, 0.0)

    def __post_init__(self) -> None:
        check_ranges(self)
        check_size(self, "side_mm", factor=float(np.sqrt(3)))  # its diagonal in front of the camera
        object.__setattr__(self, "rotation_deg", _check_rotation(self.rotation_deg))

    def render(self, camera: Camera) -> Scene:
        """Exact ray–box intersection."""
        rays = camera.rays(self.supersample)
        c = np.array([0.0, 0.0, self.distance_mm * 1e-3])
        h = np.full(3, 0.5 * self.side_mm * 1e-3)
        hit, t, nrm = ray_boxes(rays, c, rotation_matrix(self.rotation_deg), [(np.zeros(3), h)])
        refl = np.full(hit.shape, float(self.reflectance))
        return compose_scene("cube", camera, rays, hit, t, nrm, refl, self.distance_mm * 1e-3)


@dataclass(frozen=True)
class UShape:
    """Scene ``u_shape``: a U of ``width × height × depth`` (paper: 65 × 40 × 17 mm), opening
    upwards, made of a bottom bar and two arms of thickness ``thickness_mm``.

    Attributes:
        distance_mm: camera to the U's bounding-box centre, mm.
        width_mm, height_mm, depth_mm: outer sizes along x, y and z (towards the camera), mm.
        thickness_mm: thickness of the bar and the arms, mm (not in the paper).
        reflectance, supersample, rotation_deg: as in :class:`Torus`.
    """

    distance_mm: DistanceMm = 200.0
    width_mm: float = 65.0
    height_mm: float = 40.0
    depth_mm: float = 17.0
    thickness_mm: float = 15.0
    reflectance: Reflectance = 0.8
    supersample: Supersample = 4
    rotation_deg: tuple[float, float, float] = (15.0, 20.0, 0.0)

    def __post_init__(self) -> None:
        check_ranges(self)
        for key in ("width_mm", "height_mm", "depth_mm"):
            check_size(self, key)
        if not np.isfinite(self.thickness_mm) or not 0 < self.thickness_mm < 0.5 * min(
            self.width_mm, 2 * self.height_mm
        ):
            raise ConfigError(
                "thickness_mm", self.thickness_mm, "a thickness in mm below half the width and the height"
            )
        object.__setattr__(self, "rotation_deg", _check_rotation(self.rotation_deg))

    def boxes(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The three boxes ``(centre, half size)`` in the object frame, metres."""
        w, h, d, th = (v * 1e-3 for v in (self.width_mm, self.height_mm, self.depth_mm, self.thickness_mm))
        bar = (np.array([0.0, -0.5 * h + 0.5 * th, 0.0]), np.array([0.5 * w, 0.5 * th, 0.5 * d]))
        arm_h = h - th
        yc = -0.5 * h + th + 0.5 * arm_h
        left = (np.array([-0.5 * w + 0.5 * th, yc, 0.0]), np.array([0.5 * th, 0.5 * arm_h, 0.5 * d]))
        right = (np.array([0.5 * w - 0.5 * th, yc, 0.0]), np.array([0.5 * th, 0.5 * arm_h, 0.5 * d]))
        return [bar, left, right]

    def render(self, camera: Camera) -> Scene:
        """Exact ray–box intersections with the three boxes; the nearest wins."""
        rays = camera.rays(self.supersample)
        c = np.array([0.0, 0.0, self.distance_mm * 1e-3])
        hit, t, nrm = ray_boxes(rays, c, rotation_matrix(self.rotation_deg), self.boxes())
        refl = np.full(hit.shape, float(self.reflectance))
        return compose_scene("u_shape", camera, rays, hit, t, nrm, refl, self.distance_mm * 1e-3)


@dataclass(frozen=True)
class Plane:
    """Scene ``plane``: a flat Lambertian board facing the camera (Table 2's reflectance targets).

    Attributes:
        distance_mm: camera to board, mm.
        size_mm: side of the square board, mm; null: it fills the view.
        reflectance: Lambertian reflectance in [0, 1].
        supersample: rays per pixel side (1–16).
    """

    distance_mm: DistanceMm = 200.0
    size_mm: float | None = None
    reflectance: Reflectance = 0.5
    supersample: Supersample = 1

    def __post_init__(self) -> None:
        check_ranges(self)
        if self.size_mm is not None and (not np.isfinite(self.size_mm) or not self.size_mm > 0):
            raise ConfigError("size_mm", self.size_mm, "a size in mm > 0, or null to fill the view")

    def render(self, camera: Camera) -> Scene:
        """Intersect the plane ``z = distance``."""
        rays = camera.rays(self.supersample)
        d = self.distance_mm * 1e-3
        t = d / rays[..., 2]
        if self.size_mm is None:
            hit = np.ones(t.shape, dtype=bool)
        else:
            half = 0.5 * self.size_mm * 1e-3
            hit = (np.abs(rays[..., 0] * t) <= half) & (np.abs(rays[..., 1] * t) <= half)
        normals = np.broadcast_to(np.array([0.0, 0.0, -1.0]), rays.shape)
        refl = np.full(hit.shape, float(self.reflectance))
        return compose_scene("plane", camera, rays, hit, t, normals, refl, d)


def load_mesh(path: str) -> tuple[np.ndarray, np.ndarray]:
    """Read a triangle mesh file (cached on path, size and modification time); see
    :func:`_load_mesh_file`."""
    file = Path(path).expanduser()
    if not file.is_file():
        raise ConfigError("path", path, "an existing mesh file (.ply, .stl, .obj)")
    st = file.stat()
    verts, faces = _load_mesh_file(str(file.resolve()), st.st_size, st.st_mtime_ns)
    return verts.copy(), faces.copy()


def _orientation(path: str) -> int:
    """:func:`closed_orientation` of a mesh file, cached like the file itself."""
    file = Path(path).expanduser()
    st = file.stat()
    return _orientation_cached(str(file.resolve()), st.st_size, st.st_mtime_ns)


@lru_cache(maxsize=8)
def _orientation_cached(path: str, size: int, mtime_ns: int) -> int:
    verts, faces = _load_mesh_file(path, size, mtime_ns)
    return closed_orientation(faces, verts)


@lru_cache(maxsize=8)
def _load_mesh_file(path: str, size: int, mtime_ns: int) -> tuple[np.ndarray, np.ndarray]:
    """Read a triangle mesh file (PLY, STL, OBJ) → ``(vertices (v, 3) float64, faces (f, 3)
    int64)`` in the file's units, with our own bounded parser
    (:mod:`nirspi_pipe.scene.meshfiles`: declared counts checked against the file's length and
    the memory budget, face indices checked). Polygons are fan-triangulated. Raises
    :class:`ConfigError` on ``path`` when the file is missing, and
    :class:`~nirspi_pipe.scene.meshfiles.MeshFileError` naming the file when it is malformed."""
    file = Path(path).expanduser()
    if not file.is_file():
        raise ConfigError("path", path, "an existing mesh file (.ply, .stl, .obj)")
    try:
        return read_mesh_file(file)
    except (MeshFileError, UnsafeInputError) as exc:
        problem = str(exc).split(": ", 1)[-1]
        raise ConfigError("path", path, f"a valid mesh file .ply/.stl/.obj, but {problem}") from None


def closed_orientation(faces: np.ndarray, vertices: np.ndarray) -> int:
    """+1 when the mesh is closed, consistently oriented and its normals point outwards, −1 when
    closed and consistent but pointing inwards, 0 otherwise (open or inconsistent)."""
    f = np.asarray(faces, dtype=np.int64)
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    nv = int(vertices.shape[0])
    code = directed[:, 0] * nv + directed[:, 1]
    reverse = directed[:, 1] * nv + directed[:, 0]
    if np.unique(code).size != code.size:  # an edge used twice in the same direction
        return 0
    if not np.isin(reverse, code).all():  # an edge with one face only: open
        return 0
    v = np.asarray(vertices, dtype=np.float64)
    vol = np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum()
    return 1 if vol > 0 else (-1 if vol < 0 else 0)


def raycast_mesh(
    camera: Camera,
    supersample: int,
    vertices_m: np.ndarray,
    faces: np.ndarray,
    chunk: int = 1 << 15,
    orientation: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Nearest ray–triangle hits for every (sub)pixel ray of ``camera``.

    Each triangle is projected through the pinhole and tested (Möller–Trumbore, vectorised)
    only against the rays of the pixels its projected bounding box covers, so the work is
    proportional to the image area the mesh covers, not to (rays × triangles).

    Args:
        vertices_m: ``(v, 3)`` camera-frame vertices, metres, all in front of the camera.
        faces: ``(f, 3)`` vertex indices.
        orientation: from :func:`closed_orientation`; for a closed, consistently oriented mesh
            (±1) the triangles facing away from the camera are culled (they can never be the
            first hit), which halves the work.

    Returns ``(rays, t, tri, u, v)``: the rays ``(n, n, s², 3)``, hit distances ``(n, n, s²)``
    (inf where no hit), triangle index (−1), and barycentric coordinates of the hit.
    """
    n, s2 = camera.resolution, int(supersample) ** 2
    rays = camera.rays(supersample)
    flat_rays = rays.reshape(n * n, s2, 3)
    v = np.asarray(vertices_m, dtype=np.float64)
    fc = np.asarray(faces, dtype=np.int64)
    if (v[:, 2] <= 1e-6).any():
        nearest_mm = float(v[:, 2].min()) * 1e3
        raise ConfigError(
            "distance_mm",
            "?",
            f"a distance that keeps the whole mesh in front of the camera "
            f"(its nearest vertex is at z = {nearest_mm:.3g} mm)",
        )
    f = camera.focal_px
    col = f * v[:, 0] / v[:, 2] + n / 2.0
    row = n / 2.0 - f * v[:, 1] / v[:, 2]
    tc, tr = col[fc], row[fc]
    c0 = np.floor(tc.min(axis=1)).astype(np.int64)
    c1 = np.floor(tc.max(axis=1)).astype(np.int64)
    r0 = np.floor(tr.min(axis=1)).astype(np.int64)
    r1 = np.floor(tr.max(axis=1)).astype(np.int64)
    keep = (c1 >= 0) & (c0 < n) & (r1 >= 0) & (r0 < n)
    if orientation:
        p0 = v[fc[:, 0]]
        fn = np.cross(v[fc[:, 1]] - p0, v[fc[:, 2]] - p0) * orientation  # outward normals
        keep &= np.einsum("ij,ij->i", fn, p0) < 0  # front-facing: normal against the view ray
    tri_ids = np.nonzero(keep)[0]
    c0, c1 = np.clip(c0[keep], 0, n - 1), np.clip(c1[keep], 0, n - 1)
    r0, r1 = np.clip(r0[keep], 0, n - 1), np.clip(r1[keep], 0, n - 1)
    w = c1 - c0 + 1
    counts = w * (r1 - r0 + 1)
    total = int(counts.sum())
    t_best = np.full(n * n * s2, np.inf)
    tri_best = np.full(n * n * s2, -1, dtype=np.int64)
    u_best = np.zeros(n * n * s2)
    v_best = np.zeros(n * n * s2)
    if total:
        p0 = v[fc[:, 0]]
        e1 = v[fc[:, 1]] - p0
        e2 = v[fc[:, 2]] - p0
        tvec = -p0
        qvec = np.cross(tvec, e1)
        starts = np.cumsum(counts) - counts
        step = max(1, chunk // s2)
        for lo in range(0, total, step):
            k = np.arange(lo, min(total, lo + step))
            j = np.searchsorted(starts, k, side="right") - 1  # pair → kept-triangle index
            off = k - starts[j]
            pix = (r0[j] + off // w[j]) * n + (c0[j] + off % w[j])
            tri = tri_ids[j]
            d = flat_rays[pix]  # (P, s², 3)
            pvec = np.cross(d, e2[tri][:, None, :])
            det = np.einsum("pk,psk->ps", e1[tri], pvec)
            ok = np.abs(det) > 1e-18
            inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
            uu = np.einsum("pk,psk->ps", tvec[tri], pvec) * inv
            vv = np.einsum("psk,pk->ps", d, qvec[tri]) * inv
            tt = np.einsum("pk,pk->p", e2[tri], qvec[tri])[:, None] * inv
            good = ok & (uu >= 0) & (vv >= 0) & (uu + vv <= 1) & (tt > 1e-9)
            if not good.any():
                continue
            pi, si = np.nonzero(good)
            ray = pix[pi] * s2 + si
            tg = tt[pi, si]
            np.minimum.at(t_best, ray, tg)
            win = tg <= t_best[ray]
            tri_best[ray[win]] = tri[pi[win]]
            u_best[ray[win]] = uu[pi[win], si[win]]
            v_best[ray[win]] = vv[pi[win], si[win]]
    shape = (n, n, s2)
    return rays, t_best.reshape(shape), tri_best.reshape(shape), u_best.reshape(shape), v_best.reshape(shape)


@dataclass(frozen=True)
class MeshScene:
    """Scene ``mesh``: a triangle mesh file, placed and scaled by config.

    Attributes:
        path: a .ply, .stl or .obj file.
        distance_mm: camera to the centre of the mesh's bounding box, mm.
        size_mm: the largest side of the bounding box after scaling, mm; null: use ``scale``.
        scale: file units → mm when ``size_mm`` is null (1: the file is in mm).
        reflectance, supersample, rotation_deg: as in :class:`Torus` (rotation about the centre).
        smooth: interpolate vertex normals (smooth shading) instead of flat face normals.
    """

    path: str = ""
    distance_mm: DistanceMm = 200.0
    size_mm: float | None = 50.0
    scale: float = 1.0
    reflectance: Reflectance = 0.8
    supersample: Supersample = 4
    rotation_deg: tuple[float, float, float] = field(default=(0.0, 0.0, 0.0))
    smooth: bool = True

    def __post_init__(self) -> None:
        check_ranges(self)
        if not self.path:
            raise ConfigError("path", self.path, "a mesh file (.ply, .stl, .obj)")
        if self.size_mm is not None:
            check_size(self, "size_mm")
        if not np.isfinite(self.scale) or not self.scale > 0:
            raise ConfigError("scale", self.scale, "a factor > 0 (file units to mm)")
        object.__setattr__(self, "rotation_deg", _check_rotation(self.rotation_deg))

    def placed_vertices(self, vertices: np.ndarray) -> np.ndarray:
        """File vertices → camera-frame metres (centred, scaled, rotated, at the distance)."""
        lo, hi = vertices.min(axis=0), vertices.max(axis=0)
        centred = vertices - 0.5 * (lo + hi)
        extent = float((hi - lo).max())
        if self.size_mm is not None:
            if extent <= 0:
                raise ConfigError("path", self.path, "a mesh with a non-zero extent")
            k = self.size_mm * 1e-3 / extent
        else:
            k = self.scale * 1e-3
        return centred @ rotation_matrix(self.rotation_deg).T * k + np.array([0.0, 0.0, self.distance_mm * 1e-3])

    def render(self, camera: Camera) -> Scene:
        """Ray-cast the mesh; normals face the camera (two-sided shading)."""
        verts, faces = load_mesh(self.path)
        vm = self.placed_vertices(verts)
        nearest_mm = float(vm[:, 2].min()) * 1e3
        if nearest_mm <= 1e-3:  # behind or at the pinhole: the projection is undefined
            reach = self.distance_mm - nearest_mm
            raise ConfigError(
                "distance_mm",
                self.distance_mm,
                f"a distance above {reach:.4g} mm, which keeps the whole mesh "
                f"in front of the camera (or a smaller size_mm/scale)",
            )
        rays, t, tri, u, v = raycast_mesh(camera, self.supersample, vm, faces, orientation=_orientation(self.path))
        hit = tri >= 0
        e1 = vm[faces[:, 1]] - vm[faces[:, 0]]
        e2 = vm[faces[:, 2]] - vm[faces[:, 0]]
        fn = np.cross(e1, e2)
        area2 = np.linalg.norm(fn, axis=1, keepdims=True)
        fn /= np.maximum(area2, 1e-300)
        ti = tri[hit]  # normals only where a ray hits
        if self.smooth:
            vn = np.zeros_like(vm)
            for k in range(3):  # area-weighted vertex normals
                np.add.at(vn, faces[:, k], fn * area2)
            vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)
            f3 = faces[ti]
            uh, vh = u[hit][:, None], v[hit][:, None]
            nh = (1 - uh - vh) * vn[f3[:, 0]] + uh * vn[f3[:, 1]] + vh * vn[f3[:, 2]]
            bad = np.linalg.norm(nh, axis=-1) < 1e-9
            nh[bad] = fn[ti[bad]]
            nh /= np.maximum(np.linalg.norm(nh, axis=-1, keepdims=True), 1e-300)
        else:
            nh = fn[ti]
        facing = np.einsum("ik,ik->i", nh, rays[hit])
        nh[facing > 0] *= -1.0  # two-sided: face the camera
        nrm = np.zeros(rays.shape)
        nrm[hit] = nh
        refl = np.full(hit.shape, float(self.reflectance))
        return compose_scene("mesh", camera, rays, hit, t, nrm, refl, self.distance_mm * 1e-3)
