"""Training and held-out data for FSRCNN: high-resolution radiance and the SPI reconstruction
the pipeline would make of it at ``1/scale`` the resolution (the paper's CS-SRCNN setting).

Everything is generated offline by the project: scikit-image sample images that ship with the
package (no download), random shape scenes synthesised here, and Lambertian spheres rendered with
:class:`nirspi_pipe.scene.objects.Sphere`. Train and held-out sets never share an image (or a
seed, for the synthetic ones).

Degradation (what :func:`spi_lowres` does, the same path as ``source=simulator`` → ``solver=fwht``):

1. the camera pixel integrates radiance over its area: low-res = ``scale × scale`` block mean of
   the high-res radiance (:func:`~nirspi_pipe.upscale.base.block_mean`);
2. every Hadamard pattern is measured in the split convention
   (:func:`~nirspi_pipe.physics.splitmeasure.split_measure`) with Gaussian detector noise of
   standard deviation ``noise_rel × (Σ radiance)/2`` on each reading, as the simulator does;
3. the image is reconstructed by the exact fast inverse
   (:func:`~nirspi_pipe.solvers.fwht.zero_filled_inverse`).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from nirspi_pipe.metrics import fit_gain_offset
from nirspi_pipe.patterns.hadamard import is_power_of_two
from nirspi_pipe.physics.splitmeasure import split_measure
from nirspi_pipe.scene.objects import Sphere, load_gray_image
from nirspi_pipe.solvers.fwht import zero_filled_inverse
from nirspi_pipe.types import Camera
from nirspi_pipe.upscale.base import block_mean

__all__ = [
    "TRAIN_SAMPLES",
    "HELDOUT_SAMPLES",
    "TRAIN_SEED",
    "HELDOUT_SEED",
    "Pair",
    "RenderCamera",
    "spi_lowres",
    "texture_hr",
    "random_shapes_hr",
    "sphere_hr",
    "training_pairs",
    "heldout_pairs",
    "equivalent_noise_rel",
]

#: scikit-image samples used for training (all ship with scikit-image; none is downloaded).
TRAIN_SAMPLES = (
    "brick",
    "grass",
    "gravel",
    "rocket",
    "coffee",
    "chelsea",
    "clock",
    "horse",
    "hubble_deep_field",
    "immunohistochemistry",
    "page",
    "text",
    "retina",
    "cell",
    "colorwheel",
    "shepp_logan_phantom",
    "logo",
    "checkerboard",
)
#: scikit-image samples kept for evaluation only (``camera`` is the default ``scene=image``).
HELDOUT_SAMPLES = ("camera", "astronaut", "coins", "moon")
#: Seeds of the synthetic scenes: training and held-out sets use disjoint streams.
TRAIN_SEED = 20160
HELDOUT_SEED = 91550


@dataclass(frozen=True)
class Pair:
    """One example: ``hr`` ``(n·s, n·s)`` true radiance, ``lr`` ``(n, n)`` its SPI reconstruction,
    ``name`` where it came from, ``noise_rel`` the detector noise used."""

    name: str
    hr: np.ndarray
    lr: np.ndarray
    noise_rel: float


class RenderCamera(Camera):
    """A :class:`Camera` for ground-truth rendering only: any side length (×3 grids are not
    powers of two). The power-of-two rule is for Hadamard patterns, which are not used here."""

    def __post_init__(self) -> None:
        if not 2 <= int(self.resolution) <= 8192:
            raise ValueError(f"render resolution {self.resolution} out of range")


def spi_lowres(hr: np.ndarray, scale: int, noise_rel: float, rng: np.random.Generator) -> np.ndarray:
    """The ``fwht`` reconstruction of a camera ``scale`` times coarser than ``hr`` (module
    docstring). ``hr`` is ``(n·s, n·s)`` relative radiance with ``n`` a power of two; returns
    ``(n, n)`` relative radiance (noisy, unclipped, as the solver returns it)."""
    lr_true = block_mean(hr, scale)
    n = lr_true.shape[0]
    if lr_true.shape != (n, n) or not is_power_of_two(n):
        raise ValueError(f"low-res side must be a power of two, got {lr_true.shape}")
    idx = np.arange(n * n)
    y_pos, y_neg = split_measure(lr_true, idx)
    sigma = noise_rel * 0.5 * float(lr_true.sum())  # Simulator: relative to the mean half reading
    if sigma > 0:
        y_pos = y_pos + rng.normal(0.0, sigma, y_pos.shape)
        y_neg = y_neg + rng.normal(0.0, sigma, y_neg.shape)
    return zero_filled_inverse(n, idx, y_pos - y_neg)


def _resize_area(img: np.ndarray, side: int) -> np.ndarray:
    from skimage.transform import resize  # start-up: loads scipy, skimage, lazy_loader (42 ms here)

    return resize(img, (side, side), order=1, anti_aliasing=img.shape[0] > side, mode="reflect")


def texture_hr(name: str, side: int, rng: np.random.Generator | None, reflectance: float = 0.8) -> np.ndarray:
    """A scikit-image sample as ``side × side`` radiance: the central square (``rng`` None) or a
    random square crop of random size, random flip/rotation, times ``reflectance``."""
    img = load_gray_image(f"skimage:{name}")
    h, w = img.shape
    c = min(h, w)
    if rng is None:
        y0, x0 = (h - c) // 2, (w - c) // 2
    else:
        c = int(rng.integers(min(c, max(side // 2, 32)), c + 1))
        y0, x0 = int(rng.integers(0, h - c + 1)), int(rng.integers(0, w - c + 1))
    crop = img[y0 : y0 + c, x0 : x0 + c]
    if rng is not None:
        crop = np.rot90(crop, int(rng.integers(4)))
        if rng.random() < 0.5:
            crop = crop[:, ::-1]
    return np.clip(_resize_area(np.ascontiguousarray(crop), side) * reflectance, 0.0, 1.0)


def random_shapes_hr(side: int, rng: np.random.Generator) -> np.ndarray:
    """A synthetic scene ``side × side``: shaded background, random polygons, ellipses, thin
    bars and Lambertian discs (spheres seen from the light), anti-aliased by 4× supersampling."""
    from skimage.draw import ellipse, polygon  # start-up: loads skimage, lazy_loader (13 ms here)

    ss = 4
    big = side * ss
    yy, xx = np.mgrid[0:big, 0:big] / big
    g = rng.uniform(-0.3, 0.3, 2)
    img = np.clip(rng.uniform(0.0, 0.4) + g[0] * (yy - 0.5) + g[1] * (xx - 0.5), 0.0, 1.0)
    for _ in range(int(rng.integers(4, 12))):
        kind = rng.integers(4)
        value = rng.uniform(0.0, 1.0)
        if kind == 0:  # polygon
            k = int(rng.integers(3, 7))
            cy, cx, r = rng.uniform(0, big, 2).tolist() + [rng.uniform(0.05, 0.35) * big]
            angles = np.sort(rng.uniform(0, 2 * np.pi, k))
            rr, cc = polygon(cy + r * np.sin(angles), cx + r * np.cos(angles), (big, big))
            img[rr, cc] = value
        elif kind == 1:  # ellipse
            cy, cx = rng.uniform(0, big, 2)
            ry, rx = rng.uniform(0.02, 0.25, 2) * big
            rr, cc = ellipse(cy, cx, ry, rx, (big, big), rotation=rng.uniform(0, np.pi))
            img[rr, cc] = value
        elif kind == 2:  # thin bar (resolution-chart-like lines)
            width = rng.uniform(0.5, 4.0) * ss
            ang = rng.uniform(0, np.pi)
            d = (yy * big - rng.uniform(0, big)) * np.cos(ang) - (xx * big - rng.uniform(0, big)) * np.sin(ang)
            img[np.abs(d) < width / 2] = value
        else:  # Lambertian sphere lit from the camera: R·cos(incidence) = R·sqrt(1 − ρ²)
            cy, cx = rng.uniform(0, big, 2)
            r = rng.uniform(0.05, 0.3) * big
            rho2 = ((yy * big - cy) ** 2 + (xx * big - cx) ** 2) / r**2
            inside = rho2 < 1.0
            img[inside] = value * np.sqrt(1.0 - rho2[inside])
    return np.clip(block_mean(img, ss), 0.0, 1.0)


def sphere_hr(
    side: int, distance_mm: float, diameter_mm: float, reflectance: float, fov_deg: float = 20.0
) -> np.ndarray:
    """The project's sphere scene rendered at ``side × side`` (any side), radiance in [0, 1]."""
    scene = Sphere(distance_mm=distance_mm, diameter_mm=diameter_mm, reflectance=reflectance, supersample=2)
    return scene.render(RenderCamera(resolution=side, fov_deg=fov_deg)).radiance


def _noise(rng: np.random.Generator, noise_max: float, noise_min: float | None = None) -> float:
    """Training noise level: 0 with probability 1/3, else log-uniform in [noise_min, noise_max]
    (``noise_min`` None: ``noise_max/30``)."""
    if noise_max <= 0 or rng.random() < 1 / 3:
        return 0.0
    lo = noise_max / 30 if noise_min is None else noise_min
    if not 0 < lo <= noise_max:
        raise ValueError(f"noise_min={lo} must lie in (0, noise_max={noise_max}]")
    return float(np.exp(rng.uniform(np.log(lo), np.log(noise_max))))


def training_pairs(
    scale: int,
    n_lr: int = 64,
    variants: int = 3,
    n_shapes: int = 30,
    n_spheres: int = 10,
    noise_max: float = 2e-3,
    seed: int = TRAIN_SEED,
    noise_min: float | None = None,
) -> Iterator[Pair]:
    """Training examples: each training sample image ``variants`` times (random crop, flip,
    rotation, reflectance in [0.3, 1], noise), ``n_shapes`` synthetic scenes and ``n_spheres``
    spheres at random distances and sizes. Low-res side ``n_lr`` (a power of two; 64 for the
    64² study, 8 for the paper's 8 × 8 LED device). Noise: :func:`_noise`."""
    rng = np.random.default_rng([seed, scale])
    side = n_lr * scale
    for name in TRAIN_SAMPLES:
        for v in range(variants):
            hr = texture_hr(name, side, rng, reflectance=rng.uniform(0.3, 1.0))
            nr = _noise(rng, noise_max, noise_min)
            yield Pair(f"{name}#{v}", hr, spi_lowres(hr, scale, nr, rng), nr)
    for i in range(n_shapes):
        hr = random_shapes_hr(side, rng)
        nr = _noise(rng, noise_max, noise_min)
        yield Pair(f"shapes#{i}", hr, spi_lowres(hr, scale, nr, rng), nr)
    for i in range(n_spheres):
        hr = sphere_hr(side, rng.uniform(120, 400), rng.uniform(20, 80), rng.uniform(0.3, 1.0))
        nr = _noise(rng, noise_max, noise_min)
        yield Pair(f"sphere#{i}", hr, spi_lowres(hr, scale, nr, rng), nr)


def heldout_pairs(
    scale: int, noise_rel: float, n_lr: int = 64, n_shapes: int = 4, seed: int = HELDOUT_SEED
) -> list[Pair]:
    """Held-out examples: the held-out sample images (central square, reflectance 0.8), the
    paper's sphere (Ø50 mm at 200 mm, and Ø50 mm at 150 mm), and ``n_shapes`` synthetic scenes
    from a seed the training never uses; all with the same ``noise_rel``."""
    rng = np.random.default_rng([seed, scale])
    side = n_lr * scale
    hrs = [(name, texture_hr(name, side, None)) for name in HELDOUT_SAMPLES]
    hrs += [("sphere200", sphere_hr(side, 200.0, 50.0, 0.8)), ("sphere150", sphere_hr(side, 150.0, 50.0, 0.8))]
    hrs += [(f"shapes#{i}", random_shapes_hr(side, rng)) for i in range(n_shapes)]
    return [Pair(name, hr, spi_lowres(hr, scale, noise_rel, rng), noise_rel) for name, hr in hrs]


def equivalent_noise_rel(image: np.ndarray, reference: np.ndarray) -> float:
    """The ``noise_rel`` of :func:`spi_lowres` that would give ``image`` (an ``n × n`` full-sampling
    reconstruction, relative radiance) its error against ``reference`` (the camera's noise-free
    image, e.g. ``Acquisition.reference``): the residual after the least-squares gain and offset
    (as the normalised metrics fit them), whose per-pixel std is ``noise_rel · n · mean / √2``
    for white noise on each of the ``2n²`` split readings. Dimensionless; how the device's noise
    level is matched by the training data (docs/upscale.md)."""
    img = np.asarray(image, dtype=np.float64)
    ref = np.asarray(reference, dtype=np.float64)
    if img.ndim != 2 or img.shape != ref.shape or img.shape[0] != img.shape[1]:
        raise ValueError(f"image {img.shape} and reference {ref.shape} must be the same square shape")
    mean = float(img.mean())
    if not mean > 0:
        raise ValueError("image has no positive mean: no relative noise level")
    a, b = fit_gain_offset(img, ref)
    return float(np.std(img - (a * ref + b)) / mean / (img.shape[0] / np.sqrt(2.0)))
