"""A stand-in for shape-from-shading output, for tests and benchmarks of the 3D path.

It turns the ground-truth z-depth of a scene into what an SFS solver returns: depth in relative
units (pixel pitch at the object's distance), with an unknown offset, a scale error, Gaussian
noise and a fraction of outlier pixels. It is not an SFS method: it needs the ground truth.
"""

from __future__ import annotations

import numpy as np

from nirspi_pipe.types import DepthMap, Scene

__all__ = ["degraded_depth"]


def degraded_depth(
    scene: Scene,
    rng: np.random.Generator,
    scale_error: float = 0.1,
    offset_px: float = 37.0,
    noise_px: float = 0.3,
    outlier_fraction: float = 0.02,
    outlier_px: float = 8.0,
) -> DepthMap:
    """Relative SFS-like depth of ``scene`` (``metric=False``).

    ``z_rel = (1 + scale_error)·(Z − Z_min)/p + offset_px + noise``, with ``p = distance_m/f`` the
    pixel pitch (metres) at the scene distance and ``Z`` the true z-depth (metres); a fraction
    ``outlier_fraction`` of the masked pixels gets an extra ``±outlier_px`` error. All noise
    terms are in pixel-pitch units.
    """
    mask = scene.mask & np.isfinite(scene.depth_m)
    pitch = scene.distance_m / scene.camera.focal_px
    z = np.where(mask, scene.depth_m, 0.0)
    zmin = float(z[mask].min()) if mask.any() else 0.0
    rel = (1.0 + scale_error) * (z - zmin) / pitch + offset_px
    rel = rel + rng.normal(0.0, noise_px, rel.shape)
    out = rng.random(rel.shape) < outlier_fraction
    rel = rel + np.where(out, rng.choice([-1.0, 1.0], rel.shape) * outlier_px, 0.0)
    return DepthMap(depth_m=np.where(mask, rel, np.nan), mask=mask, metric=False, info={"standin": True})
