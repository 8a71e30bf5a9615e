"""The hard-case catalogue's probes (``call: NAME``, :data:`PROBES`): a stage called directly, a run
repeated, a run under other BLAS threads, a run with one input moved; and one run of overrides with
its record's values (:func:`run`, :func:`record_values`).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from typing import Any

import numpy as np

import nirspi_pipe
from nirspi_pipe.types import Camera, Image2D, PointCloud

__all__ = ["PROBES", "Probe", "caught_warnings", "probe", "record_values", "run"]


@contextmanager
def caught_warnings() -> Iterator[list[warnings.WarningMessage]]:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield caught


def run(overrides: list[str]) -> Any:

    return nirspi_pipe.run(overrides)


def record_values(result: Any) -> dict[str, Any]:
    record = result.record()
    recon = np.asarray(result.reconstruction, dtype=np.float64)
    return {
        "record": record,
        "metrics": record["metrics"],
        "derived": record["derived"],
        "info": record["info"],
        "recon_max_abs": float(np.max(np.abs(recon))) if recon.size else 0.0,
        "recon_finite": float(np.all(np.isfinite(recon))),
        "n_warnings": float(len(result.warnings)),
    }


# ---- probes (call: NAME) ----------------------------------------------------------------------

Probe = Callable[[Mapping[str, Any]], dict[str, Any]]
PROBES: dict[str, Probe] = {}


def probe(name: str) -> Callable[[Probe], Probe]:
    def deco(fn: Probe) -> Probe:
        PROBES[name] = fn
        return fn

    return deco


def _arrays(result: Any) -> dict[str, np.ndarray]:
    p = result.products
    out = {"image": np.asarray(p.image.data)}
    if p.upscaled is not None:
        out["upscaled"] = np.asarray(p.upscaled.data)
    if p.depth is not None:
        out["depth"] = np.where(p.depth.mask, p.depth.depth_m, 0.0)
    if p.cloud is not None:
        out["cloud"] = np.asarray(p.cloud.points_m)
    if p.mesh is not None:
        out["mesh"] = np.asarray(p.mesh.vertices_m)
    return out


def _max_diff(a: dict[str, np.ndarray], b: dict[str, np.ndarray], key: str) -> float:
    if a[key].shape != b[key].shape:
        return math.inf
    return float(np.max(np.abs(a[key] - b[key]))) if a[key].size else 0.0


def _nearest(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The distance from each point of ``a`` to the nearest point of ``b`` and back (both ways)."""
    from scipy.spatial import cKDTree  # start-up: loads scipy

    if len(a) == 0 or len(b) == 0:
        return np.zeros(1) if len(a) == len(b) else np.full(1, math.inf)
    return np.concatenate([cKDTree(b).query(a)[0], cKDTree(a).query(b)[0]])


@probe("rerun")
def _probe_rerun(args: Mapping[str, Any]) -> dict[str, Any]:
    """The same overrides twice in this process: the record and every array bitwise equal."""
    r1, r2 = run(list(args["run"])), run(list(args["run"]))
    a1, a2 = _arrays(r1), _arrays(r2)
    rec1, rec2 = r1.record(), r2.record()
    for rec in (rec1, rec2):
        rec.pop("timings_ms")
    same_arrays = all(a1[k].shape == a2[k].shape and np.array_equal(a1[k], a2[k]) for k in a1)
    return {"records_equal": float(repr(rec1) == repr(rec2)), "arrays_equal": float(same_arrays)}


@probe("threads")
def _probe_threads(args: Mapping[str, Any]) -> dict[str, Any]:
    """The overrides with 1 and with 2 BLAS/OpenMP threads (threadpoolctl): the largest change of
    the image (and of the upscaled image, depth, cloud where the run makes them)."""
    from threadpoolctl import threadpool_limits  # start-up: loads threadpoolctl

    with threadpool_limits(limits=1):
        r1 = run(list(args["run"]))
    with threadpool_limits(limits=2):
        r2 = run(list(args["run"]))
    a1, a2 = _arrays(r1), _arrays(r2)
    out = {f"{k}_max_abs_diff": _max_diff(a1, a2, k) for k in a1 if k not in ("cloud", "mesh")}
    out["max_abs_diff"] = max(out.values())
    return out


def _moved(overrides: list[str], key: str, rel: float) -> list[str]:
    base = [o for o in overrides if o.split("=", 1)[0] == key]
    if len(base) != 1:
        raise ValueError(f"sensitivity: the run must set {key} exactly once")
    value = float(base[0].split("=", 1)[1])
    return [f"{key}={value * (1.0 + rel)!r}" if o.split("=", 1)[0] == key else o for o in overrides]


@probe("sensitivity")
def _probe_sensitivity(args: Mapping[str, Any]) -> dict[str, Any]:
    """The run, and the run with ``key`` multiplied by ``1 + rel`` (default 1e-9): the largest
    change of each output (image and upscaled image relative radiance, depth in pixel pitches,
    fused cloud and mesh vertices in metres as the distance to the nearest point of the other run)."""
    overrides = list(args["run"])
    rel = float(args.get("rel", 1e-9))
    r1, r2 = run(overrides), run(_moved(overrides, str(args["key"]), rel))
    a1, a2 = _arrays(r1), _arrays(r2)
    out: dict[str, Any] = {}
    for k in a1:
        if k in ("cloud", "mesh"):
            moves = 1e3 * _nearest(a1[k], a2[k])
            out[f"{k}_max_move_mm"] = float(moves.max())
            out[f"{k}_p99_move_mm"] = float(np.percentile(moves, 99))
            out[f"{k}_moved_share"] = float(np.mean(moves > 1e-6))  # moved by more than 1 nm
            out[f"{k}_count_change"] = float(abs(len(a1[k]) - len(a2[k])))
        else:
            out[f"{k}_max_abs_diff"] = _max_diff(a1, a2, k)
    for name in args.get("metrics", ()):
        out[f"{name}_change"] = abs(float(r1.metrics[name]) - float(r2.metrics[name]))
    return out


def _degenerate_cloud(name: str) -> np.ndarray:
    """Point clouds (metres, camera at the origin looking along +z) for the power crust."""
    grid_u, grid_v = np.meshgrid(np.linspace(-0.02, 0.02, 8), np.linspace(-0.02, 0.02, 8))
    u, v = grid_u.ravel(), grid_v.ravel()
    cap = np.column_stack([u, v, 0.2 - np.sqrt(0.03**2 - u**2 - v**2)])  # a sphere's cap, 20 cm away
    clouds: dict[str, Callable[[], np.ndarray]] = {
        "cap": lambda: cap,
        "coplanar": lambda: np.column_stack([u, v, np.full_like(u, 0.2)]),
        "tilted_plane": lambda: np.column_stack([u, v, 0.2 + 0.5 * u - 0.3 * v]),
        "collinear": lambda: np.column_stack([np.linspace(-0.02, 0.02, 50), np.zeros(50), np.full(50, 0.2)]),
        "all_duplicated": lambda: np.repeat(cap[:1], 50, axis=0),
        "each_twice": lambda: np.vstack([cap, cap]),
        "empty": lambda: np.zeros((0, 3)),
        "three": lambda: cap[:3],
        "four": lambda: cap[:4],
        "five": lambda: cap[[0, 7, 27, 56, 63]],
        "row_of_five": lambda: cap[:5],
        "nan": lambda: np.vstack([cap, [[np.nan, 0.0, 0.2]]]),
        "inf": lambda: np.vstack([cap, [[0.0, np.inf, 0.2]]]),
        "far": lambda: cap + np.array([0.0, 0.0, 1e6]),
        "tiny": lambda: cap * 1e-9,
        "strip_20nm": lambda: (
            np.column_stack([np.linspace(-0.02, 0.02, 50), np.zeros(50), np.full(50, 0.2)])
            + np.random.default_rng(1).normal(0.0, 2e-8, (50, 3))
        ),
        "behind_camera": lambda: cap * np.array([1.0, 1.0, -1.0]),
        "outlier_1km": lambda: np.vstack([cap, [[0.0, 0.0, 1000.0]]]),
        "two_clusters": lambda: np.vstack([cap[:32], cap[:32] + np.array([0.0, 0.0, 0.5])]),
    }
    return np.asarray(clouds[name](), dtype=np.float64)


@probe("power_crust")
def _probe_power_crust(args: Mapping[str, Any]) -> dict[str, Any]:
    """:class:`~nirspi_pipe.mesh.powercrust.PowerCrust` (defaults, ``args.params`` over them) on
    a named point cloud (:func:`_degenerate_cloud`)."""
    from nirspi_pipe.mesh.powercrust import PowerCrust  # start-up: loads scipy, numba

    cloud = _degenerate_cloud(str(args["cloud"]))
    mesh = PowerCrust(**dict(args.get("params") or {})).reconstruct(PointCloud(points_m=cloud))
    verts = np.asarray(mesh.vertices_m)
    finite = verts[np.isfinite(verts).all(axis=1)] if len(verts) else verts
    far = float(np.max(np.abs(finite - finite.mean(axis=0)))) if len(finite) else 0.0
    return {
        "faces": float(len(mesh.faces)),
        "vertices_finite": float(np.all(np.isfinite(verts))),
        "extent_ratio": far / max(float(np.ptp(cloud, axis=0).max()), 1e-300),
    }


def _sfs_image(name: str, n: int = 32) -> np.ndarray:
    """Test images (relative radiance, n x n): a Lambertian sphere seen head-on, and variants."""
    y, x = (np.mgrid[0:n, 0:n] + 0.5) / n * 2.0 - 1.0
    r2 = x**2 + y**2
    sphere = np.where(r2 < 0.8, np.sqrt(np.clip(1.0 - r2 / 0.8 * 0.9, 0.0, 1.0)), 0.0)
    images: dict[str, Callable[[], np.ndarray]] = {
        "sphere": lambda: sphere,
        "saturated": lambda: np.minimum(3.0 * sphere, 1.0),
        "black": lambda: np.zeros((n, n)),
        "rescaled_small": lambda: 1e-6 * sphere,
        "rescaled_large": lambda: 1e12 * sphere,
        "constant": lambda: np.full((n, n), 0.5),
    }
    return np.asarray(images[name](), dtype=np.float64)


def _sfs_model(name: str) -> Any:
    from nirspi_pipe.sfs import models  # start-up: loads scipy

    table = {
        "lax_friedrichs": lambda: models.LaxFriedrichsSFS(),
        "godunov": lambda: models.LaxFriedrichsSFS(scheme="godunov"),
        "second_order": lambda: models.LaxFriedrichsSFS(scheme="second_order"),
        "oren_nayar": lambda: models.OrenNayarSFS(),
        "phong": lambda: models.PhongSFS(),
        "perspective": lambda: models.PerspectiveSFS(),
    }
    return table[name]()


@probe("sfs")
def _probe_sfs(args: Mapping[str, Any]) -> dict[str, Any]:
    """An SFS model (numpy back end) on a named image (:func:`_sfs_image`, 32²); with
    ``compare: IMAGE`` also the largest depth change against that image's solve (pixel pitches)."""

    model, camera = _sfs_model(str(args["model"])), Camera(resolution=32)
    depth = model.solve(Image2D(_sfs_image(str(args["image"]))), camera)
    z = np.where(depth.mask, depth.depth_m, 0.0)
    out = {
        "object_pixels": float(depth.mask.sum()),
        "depth_finite": float(np.all(np.isfinite(depth.depth_m))),
        "depth_max": float(np.max(z)) if z.size else 0.0,
        "depth_min": float(np.min(z)) if z.size else 0.0,
    }
    if "compare" in args:
        ref = model.solve(Image2D(_sfs_image(str(args["compare"]))), camera)
        zr = np.where(ref.mask, ref.depth_m, 0.0)
        out["mask_equal"] = float(np.array_equal(ref.mask, depth.mask))
        out["max_abs_diff"] = float(np.max(np.abs(z - zr)))
    if args.get("mirror"):  # a symmetric image: the depth's asymmetry under a left-right flip
        out["mirror_max_abs_diff"] = float(np.max(np.abs(z - z[:, ::-1])))
    return out
