"""Frozen dataclasses passed between pipeline stages.

Units: SI inside (metres, seconds, watts); images are dimensionless relative radiance in [0, 1]
unless a field says otherwise. Arrays are numpy; a dataclass being frozen means its fields are
never rebound, and stages never write into arrays they received.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Annotated, Any

import numpy as np

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.patterns.hadamard import is_power_of_two
from nirspi_pipe.ranges import Range, check_ranges

__all__ = [
    "Medium",
    "Camera",
    "Scene",
    "Acquisition",
    "Image2D",
    "DepthMap",
    "ItofSample",
    "PointCloud",
    "Mesh",
]

Info = Mapping[str, Any]


@dataclass(frozen=True)
class Camera:
    """Pinhole camera at the origin looking along +z; the LED array and photodiode sit here too.

    Attributes:
        resolution: virtual pixels per side (a power of two, 2–4096); the number of Hadamard
            patterns is ``resolution²``.
        fov_deg: full field of view in degrees (0 < fov < 170). The default 20° matches the
            paper's α_FOV = 10° half angle (Table 1).
    """

    resolution: int = 64
    fov_deg: Annotated[float, Range(0.0, 170.0, "degrees", lo_open=True, hi_open=True)] = 20.0
    #: False for a camera grid that no pattern is shown on (e.g. after ×3 upscaling): then any
    #: resolution from 2 to 16384 is allowed. See :meth:`resampled`.
    patterned: bool = field(default=True, repr=False, metadata={"config": False})  # set by resampled()

    def __post_init__(self) -> None:
        if self.patterned:
            if not is_power_of_two(self.resolution) or not 2 <= self.resolution <= 4096:
                raise ConfigError("resolution", self.resolution, "a power of two from 2 to 4096")
        elif int(self.resolution) != self.resolution or not 2 <= self.resolution <= 16384:
            raise ConfigError("resolution", self.resolution, "an integer from 2 to 16384")
        check_ranges(self)

    def resampled(self, resolution: int) -> Camera:
        """The same camera (field of view, pose) on an ``resolution × resolution`` grid, e.g. the
        grid of an upscaled image; no Hadamard patterns live on it, so any size is allowed."""
        return Camera(resolution=int(resolution), fov_deg=self.fov_deg, patterned=False)

    @property
    def focal_px(self) -> float:
        """Focal length in pixels: ``(n/2) / tan(fov/2)``."""
        return 0.5 * self.resolution / np.tan(np.deg2rad(self.fov_deg) / 2.0)

    def pixel_coords(self, supersample: int = 1) -> tuple[np.ndarray, np.ndarray]:
        """Normalised image-plane coordinates ``(x/z, y/z)`` of (sub)pixel centres.

        Returns two arrays of shape ``(n, n, s²)`` for ``s = supersample``; row index grows
        downwards (image convention), so ``y/z`` decreases with the row.
        """
        n, s = self.resolution, int(supersample)
        sub = (np.arange(s) + 0.5) / s  # sub-pixel offsets in [0, 1)
        pos = (np.arange(n)[:, None] + sub[None, :]).ravel() - n / 2.0  # (n·s,)
        u = pos / self.focal_px
        xs = np.broadcast_to(u[None, :], (n * s, n * s))  # columns → x
        ys = np.broadcast_to(-u[:, None], (n * s, n * s))  # rows → −y

        def blocks(a: np.ndarray) -> np.ndarray:
            return a.reshape(n, s, n, s).transpose(0, 2, 1, 3).reshape(n, n, s * s)

        return blocks(xs), blocks(ys)

    def rays(self, supersample: int = 1) -> np.ndarray:
        """Unit ray directions, shape ``(n, n, s², 3)``, in the camera frame (dimensionless)."""
        x, y = self.pixel_coords(supersample)
        d = np.stack([x, y, np.ones_like(x)], axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)


@dataclass(frozen=True)
class Scene:
    """Ground truth of a rendered scene at the camera resolution.

    Attributes:
        name: scene identifier (``sphere``, ``image``, …).
        camera: the camera it was rendered for.
        radiance: ``(n, n)`` relative radiance = reflectance × cos(incidence), in [0, 1]: what an
            ideal detector sees with the light at the camera, before distance fall-off, fog,
            background and noise (those are the source's effects).
        depth_m: ``(n, n)`` z-depth along the optical axis in metres; ``inf`` off the object.
        normals: ``(n, n, 3)`` unit surface normals (camera frame); zero off the object.
        mask: ``(n, n)`` bool, pixels at least half covered by the object.
        coverage: ``(n, n)`` fraction of each pixel covered by the object, in [0, 1].
        reflectance: ``(n, n)`` Lambertian reflectance (albedo) in [0, 1]; zero off the object.
        distance_m: nominal object distance (metres) from the scene config.
    """

    name: str
    camera: Camera
    radiance: np.ndarray
    depth_m: np.ndarray
    normals: np.ndarray
    mask: np.ndarray
    coverage: np.ndarray
    reflectance: np.ndarray
    distance_m: float


@dataclass(frozen=True)
class Medium:
    """What the medium between camera and scene was during an acquisition, for the stages that
    look through it too (the iToF lasers). Clear, dark air by default.

    Attributes:
        beta_per_m: fog extinction coefficient β, 1/m (Eq. 6; 0 = clear air).
        background_irradiance_w_m2: in-band background irradiance on the scene, W/m² (0 = dark).
    """

    beta_per_m: float = 0.0
    background_irradiance_w_m2: float = 0.0


@dataclass(frozen=True)
class Acquisition:
    """Single-pixel measurements of one acquisition, in the order they were taken.

    Split convention: each ±1 Hadamard pattern ``P_k`` is shown as the complementary 0/1 pair
    ``(1 + P_k)/2`` and ``(1 − P_k)/2``; ``y_pos`` and ``y_neg`` are the two photodiode readings
    and their difference ``y_pos − y_neg`` is the ±1 measurement (Eq. 1). Background light adds
    equally to both and cancels in the difference.

    Attributes:
        n: image side in pixels (patterns are ``n × n``).
        indices: ``(m,)`` int64 flat pattern indices in measurement order (see
            :mod:`nirspi_pipe.patterns.hadamard` for the index convention).
        y_pos: ``(m,)`` readings of the positive half-patterns, detector units.
        y_neg: ``(m,)`` readings of the negative half-patterns, or None when the device measured
            the ±1 difference directly.
        gain: detector units per unit relative radiance per pixel, so that the noise-free
            differential reading is ``gain · Σ P_k ⊙ radiance``.
        truth: the ground-truth scene when it is known (simulation, or stored in a file).
        patterns: ``(m, n²)`` explicit ±1-equivalent patterns (row-major pixels) when the
            acquisition is not on the Hadamard basis; None for Hadamard acquisitions.
        timestamps_s: ``(m,)`` acquisition time of each ±1 measurement, seconds, or None.
        medium: the fog and background light the source measured through (typed hand-off to
            the iToF stage); clear and dark when the source does not know.
        derived: physical quantities the source used (``beta_per_m``, ``snr_db``, …), for the
            record only: stages read typed fields, never this mapping.
        info: source bookkeeping (counts, flags) for the record.
        reference: ``(n, n)`` the noise-free, static image this camera forms of the scene, in
            relative radiance (fall-off, fog transmission and veil included; no noise, no change
            during the acquisition): what the normalised image metrics compare against
            (:mod:`nirspi_pipe.metrics`). None when unknown (then the truth's radiance is used).
    """

    n: int
    indices: np.ndarray
    y_pos: np.ndarray
    y_neg: np.ndarray | None = None
    gain: float = 1.0
    truth: Scene | None = None
    patterns: np.ndarray | None = None
    timestamps_s: np.ndarray | None = None
    medium: Medium = field(default_factory=Medium)
    derived: Info = field(default_factory=dict)
    info: Info = field(default_factory=dict)
    reference: np.ndarray | None = None

    @property
    def n_pixels(self) -> int:
        """Number of virtual pixels ``n²`` (= number of basis patterns)."""
        return self.n * self.n

    @property
    def ratio(self) -> float:
        """Fraction of the ``n²`` basis patterns that were measured, in (0, 1]."""
        return len(self.indices) / self.n_pixels

    @property
    def differential(self) -> np.ndarray:
        """``(m,)`` ±1 measurements in detector units (``y_pos − y_neg``)."""
        return self.y_pos if self.y_neg is None else self.y_pos - self.y_neg

    def coefficients(self) -> np.ndarray:
        """``(m,)`` ±1 measurements calibrated to relative radiance (``differential / gain``).

        For a noise-free Hadamard acquisition these equal ``fwht2(truth.radiance).ravel()[indices]``.
        """
        return self.differential / self.gain


@dataclass(frozen=True)
class Image2D:
    """A reconstructed image. ``data`` is ``(h, w)`` relative radiance; ``info`` holds the
    producing stage's bookkeeping (iterations, stopping reason, …) for the record."""

    data: np.ndarray
    info: Info = field(default_factory=dict)


@dataclass(frozen=True)
class DepthMap:
    """Depth recovered from shading: ``depth_m`` ``(h, w)`` in metres (or relative units when
    ``metric`` is False), valid where ``mask`` is True."""

    depth_m: np.ndarray
    mask: np.ndarray
    metric: bool = False
    info: Info = field(default_factory=dict)


@dataclass(frozen=True)
class ItofSample:
    """The four iToF reference points: ``points_m`` ``(4, 3)`` camera-frame positions in metres and
    ``sigma_m`` ``(4,)`` their range standard deviations in metres."""

    points_m: np.ndarray
    sigma_m: np.ndarray
    info: Info = field(default_factory=dict)


@dataclass(frozen=True)
class PointCloud:
    """``points_m`` ``(p, 3)`` camera-frame points in metres, optional ``normals`` ``(p, 3)``.

    ``depth_scale`` and ``depth_offset_m``: the global affine map ``z = scale · z_sfs + offset``
    the fusion fitted from relative SFS depth to metres (typed hand-off to the metrics); None
    when the cloud was not made from relative SFS depth. ``info`` is for the record only.
    """

    points_m: np.ndarray
    normals: np.ndarray | None = None
    depth_scale: float | None = None
    depth_offset_m: float | None = None
    info: Info = field(default_factory=dict)


@dataclass(frozen=True)
class Mesh:
    """Triangle mesh: ``vertices_m`` ``(v, 3)`` in metres, ``faces`` ``(f, 3)`` int vertex indices."""

    vertices_m: np.ndarray
    faces: np.ndarray
    info: Info = field(default_factory=dict)
