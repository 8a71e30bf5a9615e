"""Turning per-ray hits into an anti-aliased ground-truth :class:`~nirspi_pipe.types.Scene`.

Every scene model casts ``s²`` rays per pixel (``s`` = supersampling) from the camera at the
origin, which is also where the light is. It reports, per ray, whether it hit, the hit's
distance along the ray (m), the unit normal and the reflectance. :func:`compose_scene` averages
them into pixels: radiance and coverage are area averages (anti-aliased edges); depth and
normals are averaged over the hitting rays only.
"""

from __future__ import annotations

from functools import lru_cache
from typing import Any

import numpy as np

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.types import Camera, Scene

__all__ = ["check_common", "compose_scene", "forget_renders", "render_cached"]


def render_cached(shape: Any, camera: Any) -> Scene:
    """``shape.render(camera)``, remembered within one run (:func:`forget_renders`, which the
    runner calls as each run starts: a scene that reads a file must see the file as it is). The
    metrics stages render the same ground truth on the same fine grid, the upscale and the 3D
    metrics of one job (the torus costs 20-30 ms each time). The arrays of a remembered scene are
    read-only. Unhashable scene objects are rendered each time."""
    try:
        hash((shape, camera))
    except TypeError:
        return shape.render(camera)
    return _render_remembered(shape, camera)


def forget_renders() -> None:
    """Forget the scenes :func:`render_cached` remembers."""
    _render_remembered.cache_clear()


@lru_cache(maxsize=4)
def _render_remembered(shape: Any, camera: Any) -> Scene:
    scene = shape.render(camera)
    for value in vars(scene).values():
        if isinstance(value, np.ndarray):
            value.setflags(write=False)
    return scene


def check_common(distance_mm: float, reflectance: float, supersample: int) -> None:
    """Validate the keys every scene shares; raises :class:`ConfigError` naming the key."""
    if not np.isfinite(distance_mm) or distance_mm <= 0:
        raise ConfigError("distance_mm", distance_mm, "a distance in mm > 0")
    if not 0.0 <= float(reflectance) <= 1.0:
        raise ConfigError("reflectance", reflectance, "a reflectance in [0, 1]")
    if int(supersample) != supersample or not 1 <= supersample <= 16:
        raise ConfigError("supersample", supersample, "an integer from 1 to 16")


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
