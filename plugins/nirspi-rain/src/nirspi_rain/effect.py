"""Rain between the camera and the scene, as one effect of nirspi-pipe's forward-model chain.

Rain attenuates the near-infrared beam on its way to the object and back. For free-space optics
the specific attenuation is commonly modelled by Carbonneau's power law in the rain rate ``R``
(mm/h), ``γ = k R^α`` dB/km with ``k = 1.076`` and ``α = 0.67`` (as given for FSO links in ITU-R
F.2106 and used across the FSO literature); it is nearly independent of the wavelength in the
near infrared because raindrops (0.1–5 mm) are far larger than 1.55 µm.

The effect is an image effect (``domain = "image"``: before the patterns measure anything): each
pixel's active light is multiplied by ``e^{−2 β_rain ℓ}`` with ``ℓ = min(range, extent)`` the rain
path along its ray (the round trip, as for fog, Eq. 6 of the paper). A steady physical attenuation,
it is part of the noise-free reference the normalised metrics score against
(``in_reference = True``), as the fog's transmission is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Annotated, ClassVar, Literal

import numpy as np

from nirspi_pipe.physics.stagetypes import Exposure, ImageState
from nirspi_pipe.ranges import Range, check_ranges

__all__ = ["Rain", "rain_extinction_per_m", "CARBONNEAU_K_DB_PER_KM", "CARBONNEAU_ALPHA"]

#: Carbonneau's FSO rain law ``γ = k R^α`` (dB/km, R in mm/h): ITU-R F.2106.
CARBONNEAU_K_DB_PER_KM = 1.076
CARBONNEAU_ALPHA = 0.67

#: dB → natural extinction: ``β [1/m] = γ [dB/km] · ln(10)/10 / 1000``.
_DB_PER_KM_TO_PER_M = math.log(10.0) / 10.0 / 1000.0


def rain_extinction_per_m(rate_mm_per_h: float) -> float:
    """Extinction coefficient of rain, 1/m, for a rain rate in mm/h (Carbonneau, ITU-R F.2106)."""
    return CARBONNEAU_K_DB_PER_KM * float(rate_mm_per_h) ** CARBONNEAU_ALPHA * _DB_PER_KM_TO_PER_M


@dataclass(frozen=True)
class Rain:
    """Rain attenuation on the round trip (module docstring).

    Attributes:
        rate_mm_per_h: rain rate, mm/h, in [0, 500] (0: no rain; 100+ is a cloudburst).
        extent_mm: length of the rainy path from the camera, mm (.inf: all the way).
    """

    rate_mm_per_h: Annotated[float, Range(0.0, 500.0, "a rain rate in mm/h")] = 10.0
    extent_mm: Annotated[
        float, Range(0.0, None, "a path length in mm", lo_open=True, finite=False, note=".inf: unbounded")
    ] = 350.0

    name: ClassVar[str] = "rain"
    domain: ClassVar[Literal["image"]] = "image"  # an image effect: forward_model places it after the fog
    in_reference: ClassVar[bool] = True  # a steady attenuation: in the reference the metrics score against

    def __post_init__(self) -> None:
        check_ranges(self)  # the ranges declared above: one-line ConfigError naming the key

    @property
    def extinction_per_m(self) -> float:
        """β of the rain, 1/m."""
        return rain_extinction_per_m(self.rate_mm_per_h)

    def transmittance(self, exposure: Exposure) -> np.ndarray:
        """``(n, n)`` round-trip transmittance of the rain per pixel, ``e^{−2 β_rain ℓ}`` (1 off the object)."""
        r = exposure.range_m
        path = np.where(np.isfinite(r), np.minimum(r, self.extent_mm * 1e-3), 0.0)
        return np.exp(-2.0 * self.extinction_per_m * path)

    def apply(self, image: ImageState, exposure: Exposure) -> ImageState:
        beta = self.extinction_per_m
        return replace(image, image_e=image.image_e * self.transmittance(exposure)).with_derived(
            rain_beta_per_m=beta, rain_rate_mm_per_h=float(self.rate_mm_per_h)
        )
