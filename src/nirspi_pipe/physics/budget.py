"""Photon budget at the photodiode (Eqs. 10–11).

Eq. (10) counts the photons the photodiode collects in one integration:

``E(N) = R τ_lens QE T_int A_pix λ / (h c f#²) · [E_sun + Φ / (π z² tan α_FOV)]``

We use it in the standard radiometric form (camera equation), which keeps its factors and makes
the units consistent (docs/physics.md lists the departures):

* active light: the LED array (``led_count`` LEDs of ``led_power_mw`` each, at ``wavelength_nm``)
  spreads its power over the disc of half-angle α_FOV, so the irradiance on a target at range z
  is ``E_obj = P / (π (z tan α)²)`` (the paper writes ``π z² tan α``, which is not an area).
* a Lambertian target of reflectance R has radiance ``R E_obj / π``; the lens (transmittance
  τ, f-number f#) puts ``E_img = π L τ / (4 f#²) = R E_obj τ / (4 f#²)`` on the photodiode (the
  paper's ``1/f#²`` without the 4).
* photoelectrons: ``N = E_img · A_pix · FF · T_int · QE · λ / (h c)`` (the fill factor FF is
  listed in the paper's symbols but missing from its Eq. 10).
* background light (Eq. 11's ``E_sun``): the ambient in-band photon irradiance on the scene,
  reflected the same way (``E_img = ρ E_amb τ / (4 f#²)``), with a band-averaged QE. Eq. (11)'s
  ``L(z) A_pix / R_pd`` has no consistent units and is not used.

Table 1's values are the defaults (A_pix = 235 µm², FF = 0.38, T_int = 150 µs, α_FOV = 10°).
The paper does not give the LED power, the lens or the QE; the defaults here are stated
assumptions: 64 LEDs × 1 mW (an 8 × 8 array of 1550 nm LEDs such as Thorlabs LED1550E),
f/1.4, τ = 0.9, QE = 0.8 (≈ 1 A/W responsivity of InGaAs at 1550 nm).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import numpy as np

from nirspi_pipe.physics.light import C_LIGHT, H_PLANCK
from nirspi_pipe.ranges import Range, check_ranges

__all__ = ["PhotonBudget"]


#: Keys of the photon budget with closed ranges ``[lo, hi]``. The upper bounds are the earlier
#: ones (assumed: far beyond any LED array or photodiode). The lower bounds keep the image
#: finite: each key scales the white target's signal ``N_white`` (Eq. 10), and the image is the
#: readings divided by it, so a vanishing budget makes the image read noise times 1/N_white,
#: which overflowed float64 in the scores (measured at 8²: led_power_mw, t_int_us, a_pix_um2,
#: fill_factor, quantum_efficiency, lens_transmittance each at 1e-300 overflowed; led_power_mw
#: 1e-50 finished, 1e-100 overflowed). Each lower bound is assumed, far below any device and
#: leaving a white target a tiny fraction of one photoelectron, yet 30 decades above overflow:
#: 1 fW per LED; 1 ps of integration (faster than any InGaAs photodiode's response);
#: 1e-6 µm² (a square of 1 nm). ``fov_half_deg`` below 1e-3° (3.6″) made ``tan(α)²`` underflow
#: to 0 at 1e-300 (a division by zero); 1e-3° is narrower than any LED's beam.
CLOSED_RANGES = {
    "led_power_mw": (1e-12, 1e6),
    "t_int_us": (1e-6, 1e9),
    "a_pix_um2": (1e-6, 1e12),
    "fov_half_deg": (1e-3, 85.0),
}
#: Efficiency fractions: ``[FRACTION_MIN, 1]``. Assumed: one part per million (a lens passing
#: 1e-6, a photodiode with QE 1e-6) is no working camera, and keeps the image finite as above.
FRACTIONS = ("lens_transmittance", "quantum_efficiency", "fill_factor")
FRACTION_MIN = 1e-6


@dataclass(frozen=True)
class PhotonBudget:
    """Photon budget of the NIR-SPI camera (Eqs. 10–11); Table 1 values are the defaults.

    Attributes:
        led_count: LEDs in the illumination array (8 × 8 = 64); also the number of resolvable
            patches used by the range model (Alg. A1).
        led_power_mw: optical power per LED, mW.
        wavelength_nm: LED wavelength, nm.
        fov_half_deg: α_FOV, half angle of the illuminated cone, degrees (Table 1: 10°).
        lens_transmittance: τ_lens in (0, 1].
        quantum_efficiency: QE in (0, 1].
        t_int_us: integration time per pattern, µs (Table 1: 150 µs).
        a_pix_um2: photosensitive area, µm² (Table 1: 235 µm²).
        fill_factor: FF in (0, 1] (Table 1: 0.38).
        f_number: f# of the receiving lens.
    """

    led_count: Annotated[int, Range(1, 1_000_000, "an integer number of LEDs", integer=True)] = 64
    led_power_mw: Annotated[float, Range(*CLOSED_RANGES["led_power_mw"], "a power per LED in mW")] = 1.0
    wavelength_nm: Annotated[float, Range(200.0, 20000.0, "a wavelength in nm", lo_open=True)] = 1550.0
    fov_half_deg: Annotated[float, Range(*CLOSED_RANGES["fov_half_deg"], "a half angle in degrees")] = 10.0
    lens_transmittance: Annotated[float, Range(FRACTION_MIN, 1.0, "a fraction")] = 0.9
    quantum_efficiency: Annotated[float, Range(FRACTION_MIN, 1.0, "a fraction")] = 0.8
    t_int_us: Annotated[float, Range(*CLOSED_RANGES["t_int_us"], "an integration time in µs")] = 150.0
    a_pix_um2: Annotated[float, Range(*CLOSED_RANGES["a_pix_um2"], "an area in µm²")] = 235.0
    fill_factor: Annotated[float, Range(FRACTION_MIN, 1.0, "a fraction")] = 0.38
    f_number: Annotated[float, Range(0.3, 100.0, "an f-number", lo_open=True)] = 1.4

    def __post_init__(self) -> None:
        check_ranges(self)

    @property
    def led_power_w(self) -> float:
        """Total optical power of the array, W."""
        return self.led_count * self.led_power_mw * 1e-3

    @property
    def collection_m2_s(self) -> float:
        """``τ A_pix FF T_int QE / (4 f#²)``: image-plane collection (m² s, per unit scene
        irradiance × reflectance) shared by the active and background terms of Eq. (10)."""
        return (
            self.lens_transmittance
            * self.a_pix_um2
            * 1e-12
            * self.fill_factor
            * self.t_int_us
            * 1e-6
            * self.quantum_efficiency
            / (4.0 * self.f_number**2)
        )

    def white_electrons(self, range_m: float | np.ndarray) -> np.ndarray:
        """Photoelectrons per integration from a white (R = 1) Lambertian target that fills the
        field of view at ``range_m`` metres, all LEDs on, clear air  # Eq. (10), active term.

        Infinite range gives 0; ranges are floored at 1 µm to stay finite.
        """
        z = np.maximum(np.asarray(range_m, dtype=np.float64), 1e-6)
        tan_a = np.tan(np.deg2rad(self.fov_half_deg))
        e_obj = self.led_power_w / (np.pi * (z * tan_a) ** 2)  # W/m² on the target
        photon_energy = H_PLANCK * C_LIGHT / (self.wavelength_nm * 1e-9)
        with np.errstate(over="ignore"):
            out = e_obj * self.collection_m2_s / photon_energy
        return np.where(np.isfinite(z), out, 0.0)

    def ambient_electrons(self, photon_irradiance: float, reflectance: float | np.ndarray) -> np.ndarray:
        """Photoelectrons per integration from ambient light of ``photon_irradiance`` (photons
        s⁻¹ m⁻² in band) on a Lambertian scene of ``reflectance`` filling the view
        # Eqs. (10)–(11), background term."""
        return np.asarray(reflectance, dtype=np.float64) * photon_irradiance * self.collection_m2_s
