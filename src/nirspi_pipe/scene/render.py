"""Turning per-ray hits into an anti-aliased ground-truth :class:`~nirspi_pipe.types.Scene`.

Every scene model casts ``s²`` rays per pixel (``s`` = supersampling) from the camera at the
origin, which is also where the light is. It reports, per ray, whether it hit, the hit's
distance along the ray (m), the unit normal and the reflectance. :func:`compose_scene` averages
them into pixels: radiance and coverage are area averages (anti-aliased edges); depth and
normals are averaged over the hitting rays only.
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import fields
from typing import Annotated, Any

import numpy as np

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.ranges import Range
from nirspi_pipe.types import Camera, Scene

__all__ = ["DistanceMm", "Reflectance", "Supersample", "check_size", "compose_scene", "forget_renders", "render_cached"]


def render_cached(shape: Any, camera: Any) -> Scene:
    """``shape.render(camera)``, remembered: the metrics stages render the same ground truth on
    the same fine grid, within a job (the upscale and the 3D metrics) and across the jobs of a
    sweep that differ only in seed, scan or light (the torus costs 7-30 ms each time; a Figure 9
    job's metrics stage spent about a third of its time re-rendering). The last
    :data:`MAX_REMEMBERED` renders are kept; the arrays of a remembered scene are read-only. A
    scene that reads a file (a ``path``: meshes, images) is forgotten as each run starts
    (:func:`forget_renders`), so it sees the file as it is then. Unhashable scene objects are
    rendered each time."""
    key = (shape, camera)
    try:
        hash(key)
    except TypeError:
        return shape.render(camera)
    scene = _REMEMBERED.get(key)
    if scene is not None:
        _REMEMBERED.move_to_end(key)
        return scene
    scene = shape.render(camera)
    for value in vars(scene).values():
        if isinstance(value, np.ndarray):
            value.setflags(write=False)
    _REMEMBERED[key] = scene
    while len(_REMEMBERED) > MAX_REMEMBERED:
        _REMEMBERED.popitem(last=False)
    return scene


def forget_renders(files_only: bool = False) -> None:
    """Forget the scenes :func:`render_cached` remembers (with ``files_only``, those whose shape
    reads a file: the runner's call as each run starts)."""
    for key in list(_REMEMBERED):
        if not files_only or getattr(key[0], "path", None):
            del _REMEMBERED[key]


#: How many renders :func:`render_cached` keeps (a fine 32² torus is ~100 kB).
MAX_REMEMBERED = 8
_REMEMBERED: OrderedDict[tuple[Any, Any], Scene] = OrderedDict()


#: The keys every scene shares, with their declared ranges (:mod:`nirspi_pipe.ranges`).
DistanceMm = Annotated[float, Range(0.0, None, "a distance in mm", lo_open=True)]
Reflectance = Annotated[float, Range(0.0, 1.0, "a reflectance")]
Supersample = Annotated[int, Range(1, 16, "an integer", integer=True)]


def check_size(obj: Any, key: str, factor: float = 1.0, limit: float = 2.0) -> None:
    """``factor × obj.<key>`` (mm) must lie in ``(0, limit × obj.distance_mm)``: the object stays in
    front of the camera. A size that is no size (not finite, <= 0) is named. A size too large for
    the distance names the key the user changed: the distance when the size is at its default and
    the distance is not (``scene=torus scene.distance_mm=1`` names ``distance_mm``, not the torus's
    ``outer_diameter_mm`` that the user never set), else the size, with its own value."""
    value, distance = getattr(obj, key), float(obj.distance_mm)
    span = f"in mm in (0, {limit * distance / factor:g}) at distance_mm={distance:g}"
    if not np.isfinite(value) or not value > 0:
        raise ConfigError(key, value, f"a size {span}")
    if factor * value < limit * distance:
        return
    defaults = {f.name: f.default for f in fields(obj)}
    if value == defaults.get(key) and distance != defaults.get("distance_mm"):
        raise ConfigError(
            "distance_mm",
            obj.distance_mm,
            f"a distance in mm > {factor * value / limit:g} for {key}={value:g} (the object must stay in front of the camera)",
        )
    raise ConfigError(key, value, f"a size {span} (the object must stay in front of the camera)")


def compose_scene(
    name: str,
    camera: Camera,
    rays: np.ndarray,
    hit: np.ndarray,
    t_m: np.ndarray,
    normals: np.ndarray,
    reflectance: np.ndarray,
    distance_m: float,
) -> Scene:
    """Average per-ray hits into an ``n × n`` scene.

    Args:
        camera: the camera the rays came from.
        rays: ``(n, n, s², 3)`` unit ray directions.
        hit: ``(n, n, s²)`` bool, the ray hits the object.
        t_m: ``(n, n, s²)`` distance along the ray to the hit, metres (ignored where no hit).
        normals: ``(n, n, s², 3)`` unit outward normals at the hits.
        reflectance: ``(n, n, s²)`` Lambertian albedo at the hits, in [0, 1].
        distance_m: nominal object distance, metres.

    Radiance is Lambertian with the light at the camera: ``R · max(0, n · (−d))``.
    """
    hitf = hit.astype(np.float64)
    cos_inc = np.clip(-np.einsum("...k,...k->...", normals, rays), 0.0, 1.0)
    radiance = (hitf * reflectance * cos_inc).mean(axis=-1)
    coverage = hitf.mean(axis=-1)
    n_hit = hitf.sum(axis=-1)
    safe = np.maximum(n_hit, 1.0)
    z = np.where(hit, t_m * rays[..., 2], 0.0)
    depth = np.where(n_hit > 0, z.sum(axis=-1) / safe, np.inf)
    nsum = (normals * hitf[..., None]).sum(axis=-2)
    norm = np.linalg.norm(nsum, axis=-1, keepdims=True)
    nrm = np.divide(nsum, norm, out=np.zeros_like(nsum), where=norm > 0)
    refl = np.where(n_hit > 0, (reflectance * hitf).sum(axis=-1) / safe, 0.0)
    mask = coverage >= 0.5
    return Scene(
        name=name,
        camera=camera,
        radiance=np.clip(radiance, 0.0, 1.0),
        depth_m=depth,
        normals=nrm,
        mask=mask,
        coverage=coverage,
        reflectance=refl,
        distance_m=float(distance_m),
    )
