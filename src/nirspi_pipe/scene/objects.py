"""Built-in scene models: the paper's sphere, and a flat image target.

All lengths in configs are millimetres (keys say ``_mm``); internally metres.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.ranges import check_ranges
from nirspi_pipe.safeio import UnsafeInputError, check_budget, sanitize_text
from nirspi_pipe.scene.render import DistanceMm, Reflectance, Supersample, check_size, compose_scene
from nirspi_pipe.types import Camera, Scene

__all__ = ["Sphere", "ImageTarget", "load_gray_image"]


@dataclass(frozen=True)
class Sphere:
    """Scene ``sphere``: a Lambertian sphere on the optical axis (paper §7: Ø50 mm at 20 cm).

    Attributes:
        distance_mm: distance from the camera to the sphere's centre, mm.
        diameter_mm: sphere diameter, mm.
        reflectance: Lambertian reflectance in [0, 1].
        supersample: rays per pixel side for anti-aliasing (1–16).
    """

    distance_mm: DistanceMm = 200.0
    diameter_mm: float = 50.0
    reflectance: Reflectance = 0.8
    supersample: Supersample = 4

    def __post_init__(self) -> None:
        check_ranges(self)
        check_size(self, "diameter_mm")

    def render(self, camera: Camera) -> Scene:
        """Ray-cast the sphere; see :func:`~nirspi_pipe.scene.render.compose_scene`."""
        rays = camera.rays(self.supersample)
        c = np.array([0.0, 0.0, self.distance_mm * 1e-3])
        r = 0.5 * self.diameter_mm * 1e-3
        b = rays @ c  # u·c
        disc = b * b - (c @ c - r * r)
        hit = disc >= 0.0
        t = np.where(hit, b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
        p = rays * np.where(hit, t, 0.0)[..., None]
        normals = np.where(hit[..., None], (p - c) / r, 0.0)
        refl = np.full(hit.shape, float(self.reflectance))
        return compose_scene("sphere", camera, rays, hit, t, normals, refl, self.distance_mm * 1e-3)


#: ``skimage:<name>`` → the sample image file shipped inside scikit-image's own ``skimage/data``
#: folder (issue 41: a fixed list; a name is loaded by its ``skimage.data`` function only after
#: its file is found in that folder, so nothing is downloaded). Every 2D sample of scikit-image
#: 0.26 that ships in the wheel; the experiments' image lists (experiments/heldout, FSRCNN's
#: training set) use these.
SKIMAGE_SAMPLES: dict[str, str] = {
    "astronaut": "astronaut.png",
    "brick": "brick.png",
    "camera": "camera.png",
    "cat": "chelsea.png",
    "cell": "cell.png",
    "checkerboard": "chessboard_GRAY.png",
    "chelsea": "chelsea.png",
    "clock": "clock_motion.png",
    "coffee": "coffee.png",
    "coins": "coins.png",
    "colorwheel": "color.png",
    "grass": "grass.png",
    "gravel": "gravel.png",
    "horse": "horse.png",
    "hubble_deep_field": "hubble_deep_field.jpg",
    "immunohistochemistry": "ihc.png",
    "lfw_subset": "lfw_subset.npy",
    "logo": "logo.png",
    "microaneurysms": "microaneurysms.png",
    "moon": "moon.png",
    "page": "page.png",
    "retina": "retina.jpg",
    "rocket": "rocket.jpg",
    "shepp_logan_phantom": "phantom.png",
    "text": "text.png",
}


def load_gray_image(path: str) -> np.ndarray:
    """Load a grayscale image in [0, 1] from a file, or ``skimage:<name>`` for a scikit-image
    sample shipped with it (:data:`SKIMAGE_SAMPLES`: ``skimage:camera``, ``skimage:astronaut``,
    …). Raises :class:`ConfigError` on ``path`` when it cannot be read."""
    from skimage import color, data, util  # start-up: loads skimage, lazy_loader (8 ms here)

    if path.startswith("skimage:"):
        name = path.split(":", 1)[1]
        if name not in SKIMAGE_SAMPLES:
            raise ConfigError(
                "path", path, f"an image file or skimage:<sample> with sample one of {', '.join(SKIMAGE_SAMPLES)}"
            )
        if not (Path(str(data.__file__)).parent / SKIMAGE_SAMPLES[name]).is_file():  # then it would download
            raise ConfigError("path", path, "a sample shipped with this scikit-image (its file is missing)")
        img = getattr(data, name)()
    else:
        file = Path(path).expanduser()
        if not file.is_file():
            raise ConfigError("path", path, "an existing image file or skimage:<sample name>")
        img = _read_image_bounded(file, path)
    img = np.asarray(img)
    if img.ndim == 3:
        img = color.rgb2gray(img[..., :3]) if img.shape[-1] >= 3 else img[..., 0]
    img = util.img_as_float(img) if img.dtype.kind in "ui" else img.astype(np.float64)
    lo, hi = float(np.nanmin(img)), float(np.nanmax(img))
    if not np.isfinite(lo) or not np.isfinite(hi):
        raise ConfigError("path", path, "an image with finite pixel values")
    return np.clip(img, 0.0, 1.0)


def _read_image_bounded(file: Path, path: str, budget: int | None = None) -> np.ndarray:
    """Decode an image file with Pillow after checking its declared size against the memory
    budget (:mod:`nirspi_pipe.safeio`): the header is read lazily, so a small file that declares
    a gigapixel image is refused before any pixel is decoded. Raises :class:`ConfigError` on
    ``path`` naming the file."""
    from PIL import Image  # start-up: loads PIL (12 ms here)

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            with Image.open(file) as im:
                w, h = im.size
                bands = max(1, len(im.getbands()))
                # the decoded pixels, then float64 grey conversion of up to 3 channels and its result
                check_budget(
                    w * h * (bands * 4 + 4 * 8), f"a {w}x{h} image with {bands} band(s)", f"image {path}", budget
                )
                decoded: Image.Image = im
                if im.mode in ("P", "PA", "1", "CMYK", "YCbCr", "LAB", "HSV"):
                    decoded = im.convert("RGBA" if "A" in im.mode or "transparency" in im.info else "RGB")
                img = np.asarray(decoded)
    except UnsafeInputError as exc:
        raise ConfigError("path", path, f"an image within the read budget ({str(exc).split(': ', 1)[-1]})") from None
    except Exception as exc:  # noqa: BLE001 - unreadable, truncated or not an image
        raise ConfigError(
            "path", path, f"a readable image file ({type(exc).__name__}: {sanitize_text(exc, 100)})"
        ) from None
    if img.ndim not in (2, 3) or img.size == 0:
        raise ConfigError("path", path, f"a 2-D image (got an array of shape {img.shape})")
    return img


@dataclass(frozen=True)
class ImageTarget:
    """Scene ``image``: a flat, fronto-parallel target textured with a grayscale image.

    The texture is the target's reflectance (times ``reflectance``); it is lit from the camera,
    so pixels away from the axis get the ``cos θ`` of the oblique incidence.

    Attributes:
        path: image file, or ``skimage:<name>`` for a scikit-image sample (default camera man).
        distance_mm: distance from the camera to the target plane, mm.
        size_mm: side of the square target, mm; ``null`` makes it exactly fill the field of view.
        reflectance: peak reflectance in [0, 1] (white in the texture).
        supersample: rays per pixel side for anti-aliasing (1–16).
    """

    path: str = "skimage:camera"
    distance_mm: DistanceMm = 200.0
    size_mm: float | None = None
    reflectance: Reflectance = 0.8
    supersample: Supersample = 4

    def __post_init__(self) -> None:
        check_ranges(self)
        if self.size_mm is not None and not self.size_mm > 0:
            raise ConfigError("size_mm", self.size_mm, "a size in mm > 0, or null to fill the view")

    def render(self, camera: Camera) -> Scene:
        from scipy.ndimage import map_coordinates  # start-up: loads scipy and numpy (928 ms here)

        texture = load_gray_image(self.path)
        d = self.distance_mm * 1e-3
        half = 0.5 * self.size_mm * 1e-3 if self.size_mm is not None else d * np.tan(np.deg2rad(camera.fov_deg) / 2.0)
        rays = camera.rays(self.supersample)
        t = d / rays[..., 2]
        x, y = rays[..., 0] * t, rays[..., 1] * t
        hit = (np.abs(x) <= half) & (np.abs(y) <= half)
        h, w = texture.shape
        rows = (half - y) / (2 * half) * h - 0.5  # texture row grows downwards
        cols = (x + half) / (2 * half) * w - 0.5
        tex = map_coordinates(texture, [rows.ravel(), cols.ravel()], order=1, mode="nearest")
        refl = self.reflectance * tex.reshape(hit.shape)
        normals = np.broadcast_to(np.array([0.0, 0.0, -1.0]), rays.shape)
        return compose_scene("image", camera, rays, hit, t, normals, refl, d)
