"""SFS stages: orthographic Lambertian (Alg. A2 done right), perspective, and non-Lambertian.

Every stage turns an :class:`~nirspi_pipe.types.Image2D` of relative radiance (reflectance ×
cos incidence, light at the camera) into a :class:`~nirspi_pipe.types.DepthMap` with
``metric=False``: depth in units of the pixel pitch *at the object* (``z_metric = z_ref +
depth · z_ref / focal_px`` for a nearest-point distance ``z_ref``), zero at the nearest
(singular) points and growing away from the camera, valid where ``mask``. The fusion stage
fixes scale and offset from the iToF points. See ``docs/sfs.md`` for the equations.

Shared keys (all stages):

* ``albedo``: ``auto`` (the brightest object pixel is frontal: divide by the maximum of the,
  optionally median-filtered, image over the object) or a number in (0, 1].
* ``min_intensity``: normalised radiance ``I/albedo`` at or below which a pixel is not object
  (background, shadow, I = 0). It also caps the slope at ``sqrt(1/min² − 1)``.
* ``source_tol``: pixels with ``I/albedo ≥ 1 − source_tol`` are singular points (Dirichlet
  data).
* ``singular`` (orthographic stages): ``maximal`` (default): each connected singular region gets
  a depth consistent with the others, the maximal solution from the occluding contour
  (:func:`singular_depths`), with a warning that the choice is ambiguous; ``zero``: every
  singular point at ``z = 0`` (the nearest depth).
* ``median_px``: odd median-filter window applied to the image first (0 = off); use it against
  salt noise.
* ``scheme``, ``backend``, ``tol`` (pixel units), ``max_sweeps``.
* ``device``: the OpenCL device of ``backend`` ``auto``/``opencl``: ``auto`` (``PYOPENCL_CTX``,
  else the first GPU, else the first device), ``cpu``, ``gpu`` or ``<platform>:<device>`` by
  index (:mod:`nirspi_pipe.opencl_devices`). The record's ``info.sfs.device`` names the one used.
* ``slope_average`` (orthographic stages, ``scheme: second_order`` only): ``cos2`` (slopes
  averaged along the upwind edges with cos²θ linear, see :mod:`nirspi_pipe.sfs.second_order`)
  or ``node`` (the pixel's own slope: fast marching's order 2).
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Annotated, Any

import numpy as np

from nirspi_pipe.errors import ConfigError, NirspiError
from nirspi_pipe.opencl_devices import check_device
from nirspi_pipe.ranges import OneOf, Range, check_ranges
from nirspi_pipe.sfs.second_order import SLOPE_AVERAGES
from nirspi_pipe.sfs.sweeping import BIG, SCHEMES, SweepProblem, SweepResult, solve_numpy
from nirspi_pipe.types import Camera, DepthMap, Image2D

__all__ = [
    "LaxFriedrichsSFS",
    "PerspectiveSFS",
    "OrenNayarSFS",
    "PhongSFS",
    "oren_nayar_ab",
    "prepare_image",
]

BACKENDS = ("auto", "numpy", "opencl")
SINGULAR_CHOICES = ("maximal", "zero")  # depths of the singular regions: see singular_depths


def oren_nayar_ab(roughness_rad: float) -> tuple[float, float]:
    """Oren–Nayar ``A = 1 − 0.5σ²/(σ² + 0.33)`` and ``B = 0.45σ²/(σ² + 0.09)`` (σ in radians)."""
    s = float(roughness_rad) ** 2
    return 1.0 - 0.5 * s / (s + 0.33), 0.45 * s / (s + 0.09)


# Largest roughness for which the Oren–Nayar brightness with the light at the camera,
# A·c + B·(1 − c²), is increasing in c = cos θ on [0, 1] (A ≥ 2B): beyond it two slopes give the
# same brightness and the inversion below is ambiguous.
_ON_MAX_ROUGHNESS = float(
    next(r for r in np.linspace(0.0, 1.5, 15001)[::-1] if oren_nayar_ab(r)[0] >= 2 * oren_nayar_ab(r)[1])
)


def _warm_up_opencl(backend: str) -> None:
    """With ``backend`` ``auto`` or ``opencl``, import pyopencl and the kernels' module only: the
    context and the compiled program are made when the stage is built, in the job's own process
    (:class:`nirspi_pipe.stages.WarmsUp`: no threads before a fork)."""
    if backend in ("auto", "opencl"):
        # warm-up: loads pyopencl, attrs, pytools (63 ms here), before jobs fork
        import pyopencl  # noqa: F401

        # import circle: nirspi_pipe.sfs.opencl imports this module
        import nirspi_pipe.sfs.opencl  # noqa: F401


@dataclass(frozen=True)
class Prepared:
    """Image after validation and albedo normalisation (internal)."""

    norm: np.ndarray  # I / albedo, clipped to [0, 1]
    mask: np.ndarray  # object pixels
    sources: np.ndarray  # singular points (Dirichlet z = 0)
    albedo: float
    info: dict[str, Any]


def _check_common(obj: Any) -> None:
    """The checks of the SFS options that relate to more than a field's declared range."""
    check_ranges(obj)
    if obj.albedo != "auto":
        ok = isinstance(obj.albedo, (int, float)) and not isinstance(obj.albedo, bool)
        if not ok or not 0.0 < float(obj.albedo) <= 1.0:
            raise ConfigError("albedo", obj.albedo, "auto, or a reflectance in (0, 1]")
    if obj.median_px > 0 and obj.median_px % 2 == 0:
        raise ConfigError("median_px", obj.median_px, "0 (off) or an odd window size in pixels")


def prepare_image(
    data: np.ndarray,
    albedo: float | str,
    min_intensity: float,
    source_tol: float,
    median_px: int,
    weight: np.ndarray | None = None,
) -> Prepared:
    """Validate and normalise an SFS input image (relative radiance).

    ``weight`` (optional, ``(h, w)`` > 0) divides the image before the ``auto`` albedo is taken
    (perspective models normalise ``I/Q`` or ``I/Q³``). Non-finite pixels are set to 0 with a
    warning; so are negative ones. Returns the normalised image in [0, 1], the object mask and
    the singular points; warns when a region has none (the Dirichlet problem then has no data).
    """
    from scipy import ndimage  # start-up: loads scipy, charset_normalizer (219 ms here)

    img = np.array(data, dtype=np.float64)
    if img.ndim != 2:
        raise NirspiError(f"sfs needs a 2D image, got shape {img.shape}")
    bad = ~np.isfinite(img)
    if bad.any():
        warnings.warn(f"sfs: {int(bad.sum())} non-finite pixels set to 0", stacklevel=3)
        img[bad] = 0.0
    if (img < 0).any():
        img = np.maximum(img, 0.0)  # reconstruction ringing below zero: no light
    if median_px:
        img = ndimage.median_filter(img, size=int(median_px), mode="nearest")
    scaled = img / weight if weight is not None else img
    info: dict[str, Any] = {}
    if albedo == "auto":
        rho = float(scaled.max())
        if rho <= 0.0:
            rho = 1.0
    else:
        rho = float(albedo)
    norm = scaled / rho
    mask = norm > min_intensity
    over = norm > 1.0 + source_tol
    if over.any():
        warnings.warn(
            f"sfs: {int(over.sum())} pixels are brighter than the albedo ({rho:.3g}): "
            "Lambertian shading cannot exceed it, so the brightness equation has no real "
            "solution there; they are treated as singular points (z = 0)",
            stacklevel=3,
        )
    norm = np.clip(norm, 0.0, 1.0)
    sources = mask & (norm >= 1.0 - source_tol)
    if not mask.any():
        warnings.warn(
            f"sfs: no object pixels (I/albedo <= {min_intensity} everywhere): nothing to "
            "reconstruct, the depth map is empty",
            stacklevel=3,
        )
    else:
        labels, n = ndimage.label(mask)
        with_src = np.unique(labels[sources])
        missing = [k for k in range(1, n + 1) if k not in set(with_src.tolist())]
        if missing:
            size = int(np.isin(labels, missing).sum())
            peak = float(np.max(ndimage.maximum(norm, labels, missing)))
            warnings.warn(
                f"sfs: {len(missing)} of {n} object regions ({size} of {int(mask.sum())} object pixels, "
                f"I/albedo at most {peak:.3g}) have no singular point (I/albedo >= {1 - source_tol:g}), "
                "so the eikonal problem has no Dirichlet data there; each is anchored at its brightest pixel (z = 0). "
                f"Small dim regions are usually background noise just above sfs.min_intensity={min_intensity:g} "
                "(raise it to drop them); a large one is a surface not facing the camera (docs/sfs.md)",
                stacklevel=3,
            )
            idx = ndimage.maximum_position(norm, labels, missing)
            for ij in idx:
                sources[ij] = True
        info["regions"] = int(n)
        info["regions_without_singular_point"] = len(missing)
    info["albedo"] = rho
    info["singular_points"] = int(sources.sum())
    return Prepared(norm, mask, sources, rho, info)


def _run(
    problem: SweepProblem,
    scheme: str,
    backend: str,
    tol: float,
    max_sweeps: int,
    slope_average: str = "cos2",
    device: str = "auto",
) -> SweepResult:
    if backend == "opencl":
        from nirspi_pipe.sfs.opencl import solve_opencl  # import circle: nirspi_pipe.sfs.opencl imports this module

        try:
            return solve_opencl(problem, scheme, tol, max_sweeps, slope_average=slope_average, device=device)
        except Exception as exc:  # turned into a one-line user error
            if type(exc).__module__.startswith("pyopencl") or isinstance(exc, RuntimeError):
                lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
                errs = [ln for ln in lines if "error" in ln.lower() and "clBuildProgram" not in ln]
                why = errs[0] if errs else (lines[0] if lines else type(exc).__name__)
                raise NirspiError(
                    f"sfs.backend=opencl: the OpenCL kernel could not run here ({why}); use sfs.backend=numpy"
                ) from None
            raise
    return solve_numpy(problem, scheme, tol, max_sweeps, slope_average=slope_average)


def singular_depths(
    f: np.ndarray,
    prep: Prepared,
    scheme: str,
    backend: str,
    tol: float,
    max_sweeps: int,
    slope_average: str,
    device: str = "auto",
) -> tuple[np.ndarray, dict[str, Any]]:
    """Consistent depths (pixel pitches) of the singular points, one per connected singular
    region: the maximal-solution choice from the occluding contour.

    Every singular point has ``|∇z| = 0`` but not all lie at one depth (a vase: the body's and
    the lip's ridges, the neck between). Per object region (connected part of the mask) with
    two or more singular regions, the eikonal is solved once more with ``z = 0`` on the object's
    contour (its border pixels that are not on the image border): ``h = L(x, contour)``, the
    maximal solution for a contour at one depth (Lions, Rouy & Tourin 1993; Prados & Faugeras
    2005); it is 1-Lipschitz in the optical metric, so the heights ``h_k`` (median over each
    singular region) are consistent with each other and with the shading between them. Region
    ``k`` gets depth ``max_j h_j − h_k``. Warns that the choice is ambiguous (concave and convex
    shapes shade alike; a contour not at one depth breaks the assumption). Returns the depth map
    of the singular points (0 elsewhere) and bookkeeping.
    """
    from scipy import ndimage  # start-up: loads scipy, charset_normalizer (219 ms here)

    depth = np.zeros(f.shape)
    info: dict[str, Any] = {"singular_regions": 0, "singular_regions_lifted": 0}
    src_lab, n_src = ndimage.label(prep.sources, structure=np.ones((3, 3)))
    info["singular_regions"] = int(n_src)
    if n_src < 2:
        return depth, info
    obj_lab, _ = ndimage.label(prep.mask, structure=np.ones((3, 3)))
    owner = np.asarray(ndimage.maximum(obj_lab, src_lab, np.arange(1, n_src + 1)), dtype=np.int64)
    multi = [o for o in np.unique(owner) if (owner == o).sum() >= 2]
    if not multi:
        return depth, info
    inner = np.zeros_like(prep.mask)
    inner[1:-1, 1:-1] = True
    contour = prep.mask & ~ndimage.binary_erosion(prep.mask, structure=np.ones((3, 3))) & inner
    region = np.isin(obj_lab, multi)
    seeds = contour & region
    if not seeds.any():
        warnings.warn(
            "sfs: several singular regions but no occluding contour in view: all kept at z = 0 (ambiguous)",
            stacklevel=3,
        )
        return depth, info
    problem = SweepProblem(rhs=np.where(seeds, 1.0, np.maximum(f, 1e-12)), fixed=seeds, init=np.where(seeds, 0.0, BIG))
    h = _run(problem, scheme, backend, tol, max_sweeps, slope_average, device).z
    h_k = np.asarray(ndimage.median(np.where(h < 0.5 * BIG, h, np.nan), src_lab, np.arange(1, n_src + 1)))
    lifted, spread = 0, 0.0
    for o in multi:
        ks = np.nonzero(owner == o)[0]
        hk = h_k[ks]
        if not np.all(np.isfinite(hk)):
            continue
        zk = hk.max() - hk
        for k, z in zip(ks, zk):
            depth[src_lab == k + 1] = z
        lifted += int((zk > 0).sum())
        spread = max(spread, float(zk.max()))
    info["singular_regions_lifted"] = lifted
    info["singular_depth_spread_px"] = spread
    if lifted:
        touches = bool((region & ~inner).any())
        warnings.warn(
            f"sfs: {n_src} singular regions; {lifted} set behind the nearest by the "
            f"maximal solution from the occluding contour (up to {spread:.1f} px): ambiguous, it assumes the "
            f"contour at one depth and a convex shape{'; the object touches the image border' if touches else ''}",
            stacklevel=3,
        )
    return depth, info


def _finish(
    z: np.ndarray, prep: Prepared, res: SweepResult, name: str, extra: dict[str, Any], backend: str, scheme: str
) -> DepthMap:
    """Mask, make finite, warn on non-convergence and pack the DepthMap."""
    valid = prep.mask & np.isfinite(z) & (z < 0.5 * BIG)
    depth = np.where(valid, z, 0.0)
    if valid.any():
        depth = np.where(valid, depth - depth[valid].min(), 0.0)
    if not res.converged:
        warnings.warn(
            f"sfs ({name}): not converged after {res.sweeps} sweeps (last change "
            f"{res.final_change:.3g} px > tol); raise sfs.max_sweeps",
            stacklevel=3,
        )
    info = {
        "model": name,
        "scheme": scheme,
        "backend": backend,
        "sweeps": int(res.sweeps),
        "final_change": float(res.final_change),
        "converged": bool(res.converged),
        "depth_units": "pixel_pitch",
        "valid_fraction": float(valid.mean()),
        **prep.info,
        **extra,
    }
    return DepthMap(depth_m=depth, mask=valid, metric=False, info=info)


def _resolve(
    backend: str, model: int, scheme: str, slope_average: str = "cos2", device: str = "auto", size: int = 64
) -> str:
    """The back end a solve of image side ``size`` uses; ``auto`` is ``opencl`` when a device
    builds the kernel and OpenCL was measured faster there (:func:`nirspi_pipe.opencl_devices.choose`)."""
    if backend == "numpy":
        return "numpy"
    from nirspi_pipe.sfs.opencl import resolve_backend  # import circle: nirspi_pipe.sfs.opencl imports this module

    return resolve_backend(backend, model, scheme, slope_average, device, size)


def _device_info(backend: str, device: str) -> dict[str, Any]:
    """The record's ``device`` (and ``device_requested``) of a solve on ``backend``."""
    if backend != "opencl":
        return {"device": "cpu (numpy)", "device_requested": device}
    from nirspi_pipe.sfs.opencl import device_name  # import circle: nirspi_pipe.sfs.opencl imports this module

    return {"device": device_name(device), "device_requested": device}


def _check_device(obj: Any) -> None:
    check_device(obj.device)


def _effective_scheme(scheme: str, shape: tuple[int, int]) -> str:
    if scheme == "lax_friedrichs" and min(shape) < 3:
        warnings.warn("sfs: image smaller than 3x3, using the godunov scheme", stacklevel=3)
        return "godunov"
    return scheme


@dataclass(frozen=True)
class SweepingSFS:
    """The keys and checks every sweeping SFS option shares (:class:`LaxFriedrichsSFS` and its
    reflectance variants, :class:`PerspectiveSFS`); a subclass adds its scheme and its
    ``effective_backend``. Keys: ``backend`` (numpy, opencl or auto), the sweeps' ``tol`` (pixels)
    and ``max_sweeps``, the ``albedo`` (auto or a reflectance), ``min_intensity`` (object pixels),
    ``source_tol`` (singular points), ``median_px`` (a median filter) and the OpenCL ``device``."""

    backend: Annotated[str, OneOf(BACKENDS)] = "numpy"
    tol: Annotated[float, Range(0.0, None, "a tolerance in pixels", lo_open=True)] = 1e-4
    max_sweeps: Annotated[int, Range(4, None, "an integer", integer=True)] = 4000
    albedo: float | str = "auto"
    min_intensity: Annotated[float, Range(0.0, 1.0, "a normalised radiance", lo_open=True, hi_open=True)] = 0.05
    source_tol: Annotated[float, Range(0.0, 0.5, "a value", hi_open=True)] = 1e-3
    median_px: Annotated[int, Range(0, None, "0 (off) or an odd window size in pixels", integer=True)] = 0
    device: str = "auto"

    @classmethod
    def warm_up(cls, params: Mapping[str, Any]) -> None:
        """:func:`_warm_up_opencl` (:class:`nirspi_pipe.stages.WarmsUp`)."""
        _warm_up_opencl(str(params.get("backend", cls.backend)))

    def __post_init__(self) -> None:
        _check_common(self)
        _check_device(self)
        self.effective_backend()  # build the OpenCL kernel now, never inside a timed solve

    def effective_backend(self, size: int = 64) -> str:
        raise NotImplementedError  # each scheme resolves its own back end


@dataclass(frozen=True)
class LaxFriedrichsSFS(SweepingSFS):
    """SFS ``lax_friedrichs``: orthographic Lambertian SFS, light at the camera (Alg. A2, fixed).

    Solves the eikonal ``|∇z| = F = sqrt(1/I² − 1)`` (I normalised by the albedo; the printed
    Alg. A2 line 17 puts Z where I belongs) with ``z = 0`` at the singular points ``I = 1`` by
    Kao–Osher–Qian Lax–Friedrichs fast sweeping (``scheme: lax_friedrichs``), by the Godunov
    upwind update (``scheme: godunov``, much faster for this equation) or by second-order upwind
    sweeping (``scheme: second_order``, with ``slope_average`` ``cos2`` or ``node``; see
    :mod:`nirspi_pipe.sfs.second_order`). Depth in pixel pitches.
    """

    scheme: Annotated[str, OneOf(SCHEMES)] = "lax_friedrichs"
    # Not in the generated config schema (only sfs=second_order, which sets it, reads it): the
    # configs, job keys and derived seeds of the other SFS options stay as they were.
    slope_average: Annotated[str, OneOf(SLOPE_AVERAGES)] = field(default="cos2", metadata={"config": False})
    singular: Annotated[str, OneOf(SINGULAR_CHOICES)] = "maximal"

    def effective_backend(self, size: int = 64) -> str:
        """The back end a solve of image side ``size`` uses: ``auto`` is ``opencl`` when a device
        builds the kernel and OpenCL was measured faster on it at that size
        (:func:`nirspi_pipe.opencl_devices.choose`), else ``numpy`` (the record's ``info.sfs.backend`` says
        which, ``info.sfs.device`` on which device)."""
        return _resolve(self.backend, 0, self.scheme, self.slope_average, self.device, size)

    def cos_incidence(self, norm: np.ndarray) -> np.ndarray:
        """``cos θ`` from the normalised radiance; Lambertian: ``I/albedo`` itself."""
        return norm

    def _model_info(self) -> dict[str, Any]:
        return {}

    def solve(self, image: Image2D, camera: Camera) -> DepthMap:
        """Depth (pixel pitches, 0 at the singular points) from ``image``; ``camera`` is unused
        by the orthographic model except for bookkeeping."""
        prep = prepare_image(image.data, self.albedo, self.min_intensity, self.source_tol, self.median_px)
        c = np.clip(self.cos_incidence(prep.norm), self.min_intensity, 1.0)
        f = np.sqrt(1.0 / (c * c) - 1.0)  # eikonal speed |∇z|, Alg. A2 line 17 with I for Z
        scheme = _effective_scheme(self.scheme, f.shape)
        backend = _resolve(self.backend, 0, scheme, self.slope_average, self.device, max(f.shape))
        z_src, sing = np.zeros(f.shape), dict[str, Any]()
        if self.singular == "maximal":
            z_src, sing = singular_depths(
                f, prep, scheme, backend, float(self.tol), int(self.max_sweeps), self.slope_average, self.device
            )
        problem = SweepProblem(rhs=f, fixed=prep.sources, init=np.where(prep.sources, z_src, BIG))
        if prep.mask.any():
            res = _run(problem, scheme, backend, float(self.tol), int(self.max_sweeps), self.slope_average, self.device)
        else:  # no object pixel (prepare_image warned): nothing to sweep, an empty depth map
            res = SweepResult(z=np.full(f.shape, BIG), sweeps=0, final_change=0.0, converged=True)
        extra = {
            "focal_px": float(camera.focal_px),
            "backend_requested": self.backend,
            **_device_info(backend, self.device),
            **self._model_info(),
            **sing,
        }
        if scheme == "second_order":
            extra["slope_average"] = self.slope_average
        return _finish(res.z, prep, res, type(self).__name__, extra, backend, scheme)


@dataclass(frozen=True)
class OrenNayarSFS(LaxFriedrichsSFS):
    """SFS ``oren_nayar``: orthographic SFS for an Oren–Nayar surface (after Tozza & Falcone
    2016), light at the camera.

    With the light along the view direction, θ_i = θ_r = θ and φ_i = φ_r, so the Oren–Nayar
    brightness is ``I/ρ = A cos θ + B sin²θ`` (``A``, ``B`` from ``roughness_rad``). For
    ``roughness_rad ≤ 0.6`` rad it increases with ``cos θ``, so each pixel's ``cos θ`` follows
    from its brightness (root of ``B c² − A c + I/ρ − B = 0``) and the depth solves the same
    eikonal ``|∇z| = sqrt(1/c² − 1)``. ``albedo: auto`` takes the brightest pixel as frontal
    (``I = ρA``).
    """

    roughness_rad: Annotated[
        float,
        Range(
            0.0,
            _ON_MAX_ROUGHNESS,
            "radians",
            note="beyond, brightness is not monotone in the incidence angle with the light at the camera "
            "and SFS is ambiguous",
        ),
    ] = 0.3

    def cos_incidence(self, norm: np.ndarray) -> np.ndarray:
        a, b = oren_nayar_ab(self.roughness_rad)
        # norm = I/ρ' with ρ' = ρA (frontal brightness): I/ρ = A·norm.
        target = a * norm
        if b < 1e-12:
            return np.clip(target / a, 0.0, 1.0)
        disc = np.maximum(a * a - 4.0 * b * (target - b), 0.0)
        return np.clip((a - np.sqrt(disc)) / (2.0 * b), 0.0, 1.0)

    def _model_info(self) -> dict[str, Any]:
        a, b = oren_nayar_ab(self.roughness_rad)
        return {"oren_nayar_a": a, "oren_nayar_b": b}


@dataclass(frozen=True)
class PhongSFS(LaxFriedrichsSFS):
    """SFS ``phong``: orthographic SFS for a Phong surface, light at the camera (after Tozza &
    Falcone 2016): ``I/ρ = (1 − k_s) cos θ + k_s cos^α θ`` (the mirror direction of the light is
    the view direction, so the specular lobe is ``cos^α θ``). Increasing in ``cos θ``, inverted
    per pixel by bisection, then the eikonal as in ``lax_friedrichs``.
    """

    specular: Annotated[float, Range(0.0, 1.0, "a specular fraction k_s", hi_open=True)] = 0.3
    shininess: Annotated[float, Range(1.0, 1000.0, "a Phong exponent")] = 10.0

    def cos_incidence(self, norm: np.ndarray) -> np.ndarray:
        ks, alpha = float(self.specular), float(self.shininess)
        lo, hi = np.zeros_like(norm), np.ones_like(norm)
        for _ in range(60):  # bisection: g(c) = (1 − ks)c + ks c^α is increasing on [0, 1]
            mid = 0.5 * (lo + hi)
            low = (1.0 - ks) * mid + ks * mid**alpha < norm
            lo = np.where(low, mid, lo)
            hi = np.where(low, hi, mid)
        return 0.5 * (lo + hi)

    def _model_info(self) -> dict[str, Any]:
        return {"specular": float(self.specular), "shininess": float(self.shininess)}


@dataclass(frozen=True)
class PerspectiveSFS(SweepingSFS):
    """SFS ``perspective``: perspective Lambertian SFS with a point light at the optical centre
    (Prados & Faugeras 2005), our camera's geometry.

    With ``w = f ln z`` (f = ``camera.focal_px``) and ``x̂`` the normalised image coordinates,
    the brightness equation becomes ``sqrt(|∇w|² + (x̂·∇w + 1)²) = Q/Î`` without fall-off and
    ``= (Q³/Î) exp(−2w/f)`` with ``1/r²`` fall-off (``falloff: true``), ``Q = 1/sqrt(1 + |x̂|²)``
    the cosine of the ray angle. Solved by Lax–Friedrichs sweeping (KOQ) with σ from the
    Hamiltonian's bound. Without fall-off the singular points (``Î = Q``) carry ``w = 0``; with
    fall-off the equation is strictly increasing in ``w`` and needs no boundary data (the
    sweeping starts from the supersolution ``w₀ = (f/2) ln(K sqrt(1 + |x̂|²)) + 1``). Output:
    ``f (z/z_min − 1)``, the depth behind the nearest point in pixel pitches at that point.
    """

    falloff: Annotated[bool, OneOf((True, False), "true or false")] = True
    scheme: Annotated[str, OneOf(("lax_friedrichs",))] = "lax_friedrichs"

    def effective_backend(self, size: int = 64) -> str:
        """The back end a solve of image side ``size`` uses (``auto``: as
        :meth:`LaxFriedrichsSFS.effective_backend`)."""
        return _resolve(self.backend, 2 if self.falloff else 1, self.scheme, "cos2", self.device, size)

    def solve(self, image: Image2D, camera: Camera) -> DepthMap:
        """Depth (pixel pitches at the nearest point, 0 there) from ``image`` seen by ``camera``."""
        data = np.asarray(image.data)
        if data.ndim != 2:
            raise NirspiError(f"sfs needs a 2D image, got shape {data.shape}")
        if min(data.shape) < 3:
            raise NirspiError("sfs=perspective needs an image of at least 3x3 pixels")
        rows, cols = data.shape
        f = float(camera.focal_px) * cols / camera.resolution  # focal length at this grid size
        xh = (np.arange(cols) + 0.5 - cols / 2.0) / f
        yh = (np.arange(rows) + 0.5 - rows / 2.0) / f
        r2 = xh[None, :] ** 2 + yh[:, None] ** 2
        q = 1.0 / np.sqrt(1.0 + r2)  # cos of the ray angle, f/|m|
        weight = q**3 if self.falloff else q
        prep = prepare_image(data, self.albedo, self.min_intensity, self.source_tol, self.median_px, weight)
        rhs = 1.0 / np.maximum(prep.norm, self.min_intensity)  # Q/Î = 1/norm (Q folded in weight)
        if self.falloff:
            fixed = np.zeros_like(prep.sources)
            init = 0.5 * f * np.log(rhs * np.sqrt(1.0 + r2)) + 1.0
            model = 2
        else:
            fixed = prep.sources
            init = np.where(fixed, 0.0, BIG)
            model = 1
        problem = SweepProblem(rhs=rhs, fixed=fixed, init=init, model=model, xhat=xh, yhat=yh, focal_px=f)
        scheme = self.scheme
        backend = self.effective_backend(max(rows, cols))
        if prep.mask.any():
            res = _run(problem, scheme, backend, float(self.tol), int(self.max_sweeps), device=self.device)
        else:  # no object pixel (prepare_image warned): nothing to sweep, an empty depth map
            res = SweepResult(z=np.full(rhs.shape, BIG), sweeps=0, final_change=0.0, converged=True)
        w = np.where(prep.mask, res.z, np.nan)
        valid = prep.mask & (res.z < 0.5 * BIG)
        z_rel = np.zeros_like(res.z)
        if valid.any():
            w0 = float(np.nanmin(np.where(valid, w, np.nan)))
            z_rel = np.where(valid, np.exp(np.clip((res.z - w0) / f, 0.0, 50.0)), 1.0)
        depth = f * (z_rel - 1.0)  # pixel pitches at the nearest point
        depth = np.where(valid, depth, BIG)
        extra = {"focal_px": f, "falloff": bool(self.falloff)}
        extra["backend_requested"] = self.backend
        extra.update(_device_info(backend, self.device))
        return _finish(depth, prep, res, "PerspectiveSFS", extra, backend, scheme)
