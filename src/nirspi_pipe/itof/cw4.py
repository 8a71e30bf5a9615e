"""iToF ``cw4``: four continuous-wave indirect time-of-flight lasers (paper §3, Table 1).

Up to four 1550 nm lasers sit at the camera (the origin). With ``spots: fixed`` (the paper) they
point at 360°/n to each other around the optical axis, each ``spot_angle_deg`` off axis, so that
with azimuth 45° each spot lands in one image quadrant; with ``spots: auto`` (default) they are
steered at the object seen in the 2D image (:func:`aim_spots`, via :meth:`ContinuousWave4.aimed`). Each has its own photodiode. A laser is sine-modulated at ``f_mod`` and the
photodiode signal is correlated with the modulation at four phase offsets (0, 90°, 180°, 270°):

    A_k = B/4 + (N_s/4)·(1 + c_d·cos(φ + k·π/2)),   k = 0..3

with ``N_s`` the signal photo-electrons, ``B`` the background photo-electrons and ``c_d`` the
demodulation contrast. The four readings give the phase and the distance (4-phase
demodulation)::

    φ = atan2(A3 − A1, A0 − A2),   d = c·φ / (4π f_mod)   (φ wrapped to [0, 2π))

which is unambiguous up to ``c / (2 f_mod)`` (31.2 m at 4.8 MHz); farther targets wrap.

Noise. The ``A_k`` are Poisson counts (shot noise of signal and background light; a Gaussian of
the same mean and variance above 10¹⁸ electrons, where numpy's Poisson sampler stops, with the
photodiode's code, :func:`nirspi_pipe.physics.detector.sample_electrons`) accumulated over
``frames = round(averaging_s / T_int)`` integration windows of ``T_int``. The shot-noise
range deviation (Lange & Seitz 2001) is ``σ_shot = c/(4π f) · sqrt(ΣA_k / 2) / (2 a)`` with
``a = ½·|(A0 − A2, A3 − A1)|``, estimated from the measured counts as a device would. On top sits
the electronics floor given by Table 1's noise-equivalent distance: ``σ_floor = NED ·
sqrt(ENBW)`` with the equivalent noise bandwidth ``ENBW = 1 / (2·averaging_s)`` of a boxcar
average. Table 1's ``NED = 1 cm/√Hz`` with the default 0.5 s average gives ``σ_floor = 1 cm``,
Table 1's ``σ_min``. (Read as a single 150 µs window, NED would give 58 cm, which contradicts
σ_min; the paper does not say how NED is referenced, so this is our reading.)

Photon budget (not in the paper, documented assumptions): the spot's power ``P`` falls on a
Lambertian surface of reflectance ``R`` at range ``r`` and incidence ``θ``; a coaxial receiver
of aperture ``A_rx`` collects ``P·R·cos θ·A_rx / (π r²)``, attenuated by fog on the way out and
back, ``exp(−2βr)``. Background irradiance ``E_bg`` on the target (in the detector's band)
reflects as radiance ``R·E_bg/π`` into the receiver's field of view (solid angle
``π sin²(α_FOV)``); following Koschmieder (Eq. 7) with the airlight as bright as the object,
fog does not reduce the background. Fog backscatter of the laser into the receiver is ignored.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Annotated, Any

import numpy as np

from nirspi_pipe.errors import ConfigError, NirspiError
from nirspi_pipe.physics.detector import sample_electrons
from nirspi_pipe.ranges import OneOf, Range, check_ranges
from nirspi_pipe.types import Acquisition, Camera, Image2D, ItofSample, Scene

__all__ = ["ContinuousWave4", "aim_spots", "ambiguity_range_m", "demodulate_4phase", "laser_directions"]

SPOT_MODES = ("auto", "fixed")

C_M_S = 299_792_458.0  # speed of light, m/s
H_J_S = 6.626_070_15e-34  # Planck constant, J·s
#: Poisson counts up to here, a Gaussian of the same mean and variance above (the photodiode's
#: rule, :func:`~nirspi_pipe.physics.detector.sample_electrons`). Assumed: 1e18, below numpy's
#: Poisson limit (~9.2e18), rather than the photodiode's 1e7 switch, so that every count numpy
#: could draw keeps its Poisson draw (the default spots hold ~1e12 e⁻: the same random stream,
#: hence the same numbers, as before the fallback existed); at 1e18 the two are indistinguishable.
_POISSON_MAX = 1e18
#: Largest laser power, mW (assumed: 1 TW, far beyond any laser; it keeps the photo-electron
#: counts, ~3e26 for the default sphere, within float64 with room for a target at the lens).
_MAX_POWER_MW = 1e15


def ambiguity_range_m(f_mod_hz: float) -> float:
    """Unambiguous range of a CW iToF at modulation frequency ``f_mod_hz`` (Hz): ``c/(2f)``, m."""
    return C_M_S / (2.0 * f_mod_hz)


def demodulate_4phase(samples: np.ndarray, f_mod_hz: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """4-phase CW demodulation.

    Args:
        samples: ``(..., 4)`` correlation samples ``A0..A3`` at phase offsets 0, 90°, 180°, 270°
            (photo-electrons or any linear unit).
        f_mod_hz: modulation frequency, Hz.

    Returns:
        ``(distance_m, amplitude, offset)``: the distance ``c·φ/(4π f)`` in metres with
        ``φ = atan2(A3 − A1, A0 − A2)`` wrapped to ``[0, 2π)`` (so the distance is in
        ``[0, c/(2f))``), the amplitude ``a = ½|(A0 − A2, A3 − A1)|`` and the offset ``ΣA_k``
        (units of the samples).
    """
    a = np.asarray(samples, dtype=np.float64)
    i = a[..., 0] - a[..., 2]
    q = a[..., 3] - a[..., 1]
    phi = np.mod(np.arctan2(q, i), 2.0 * np.pi)
    dist = C_M_S * phi / (4.0 * np.pi * f_mod_hz)
    # the wrap can return exactly 2π for tiny negative angles: fold it back into [0, c/2f)
    dist = np.where(dist >= ambiguity_range_m(f_mod_hz), 0.0, dist)
    return dist, 0.5 * np.hypot(i, q), a.sum(axis=-1)


def laser_directions(spot_angle_deg: float, azimuth_deg: float) -> np.ndarray:
    """Unit directions ``(4, 3)`` of the four lasers in the camera frame (+z forward, +y up).

    Laser ``k`` is ``spot_angle_deg`` off the optical axis at azimuth ``azimuth_deg + 90°·k``
    (measured from +x towards +y), so the four are at 90° to each other around the axis.
    """
    th = np.deg2rad(spot_angle_deg)
    psi = np.deg2rad(azimuth_deg + 90.0 * np.arange(4))
    return np.stack([np.sin(th) * np.cos(psi), np.sin(th) * np.sin(psi), np.full(4, np.cos(th))], axis=-1)


def aim_spots(image: np.ndarray, camera: Camera, n_spots: int, threshold: float) -> tuple[np.ndarray, list[str]]:
    """Spot pixels ``(k, 2)`` (row, col; ``k ≤ n_spots``) aimed at the object in a 2D image.

    The image is 3×3 median filtered and smoothed (Gaussian, 1 px); the object is where it exceeds both Otsu's threshold
    (object against fog airlight and background) and ``threshold`` × its 99.5th percentile, opened
    (3×3) against isolated noise pixels. Each connected
    part of at least 2 % of the object's pixels gets one spot first (largest parts first, at its
    point farthest from its edge, so the spot and its 2×2 neighbourhood stay on the object);
    the remaining spots go by farthest-point sampling within those parts, each maximising its image distance to the
    spots chosen so far times ``sqrt`` of its depth into the object (spread out, away from the
    edges: spots at different depths fix the SFS scale). Returns the pixels and notes (empty
    when fine; e.g. no object found).
    """
    from scipy import ndimage  # start-up: loads scipy (144 ms here)
    from skimage.filters import threshold_otsu  # start-up: loads scipy, charset_normalizer, lazy_loader (222 ms here)

    img = np.nan_to_num(np.asarray(image, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    img = ndimage.gaussian_filter(ndimage.median_filter(img, size=3, mode="nearest"), 1.0)  # fog noise
    ref = float(np.percentile(img, 99.5)) if img.size else 0.0
    if not ref > 0 or float(img.max() - img.min()) <= 0:
        return np.zeros((0, 2), dtype=np.int64), ["the 2D image is flat or dark: no object to aim at"]
    # object vs background (fog airlight, noise): Otsu's threshold, at least threshold × the top
    mask = ndimage.binary_opening(img > max(threshold * ref, float(threshold_otsu(img))))
    labels, nlab = ndimage.label(mask)
    dt = ndimage.distance_transform_edt(np.pad(mask, 1))[1:-1, 1:-1]  # the image border is an edge
    sizes = np.asarray(ndimage.sum(mask, labels, np.arange(1, nlab + 1))) if nlab else np.zeros(0)
    comp_max = np.asarray(ndimage.maximum(dt, labels, np.arange(1, nlab + 1))) if nlab else np.zeros(0)
    depth = np.where(mask, dt / np.maximum(comp_max[np.maximum(labels - 1, 0)], 1e-9), 0.0)
    chosen: list[tuple[int, int]] = []
    big = np.zeros(nlab + 1, dtype=bool)
    for lab in np.argsort(-sizes)[:n_spots]:
        if sizes[lab] < 0.02 * mask.sum():
            break
        big[lab + 1] = True
        r, c = ndimage.maximum_position(dt, labels, lab + 1)
        chosen.append((int(r), int(c)))
    rr, cc = np.nonzero(big[labels] & (depth >= 0.3))
    while chosen and len(chosen) < n_spots and len(rr):
        ch = np.array(chosen)
        dmin = np.min(np.hypot(rr[:, None] - ch[:, 0], cc[:, None] - ch[:, 1]), axis=1)
        score = dmin * np.sqrt(depth[rr, cc])
        j = int(np.argmax(score))
        if dmin[j] < 1.0:
            break
        chosen.append((int(rr[j]), int(cc[j])))
    notes = [] if chosen else ["no object region large enough to aim at"]
    return np.array(chosen, dtype=np.int64).reshape(-1, 2), notes


def _sample_at(scene: Scene, d: np.ndarray) -> tuple[bool, float, float, float]:
    """Where the ray ``d`` (unit) meets the scene: ``(hit, range_m, reflectance, cos_incidence)``.

    The z-depth is interpolated bilinearly between the four pixel centres around the spot when
    all four are on the object (nearest pixel otherwise); reflectance and normal come from the
    nearest pixel. Raises :class:`ConfigError` (``spot_angle_deg``) when the spot leaves the image.
    """
    cam = scene.camera
    n, f = cam.resolution, cam.focal_px
    col = d[0] / d[2] * f + n / 2.0 - 0.5
    row = -d[1] / d[2] * f + n / 2.0 - 0.5
    if not (-0.5 <= col < n - 0.5 and -0.5 <= row < n - 0.5):
        raise ConfigError("spot_angle_deg", None, "spots inside the camera's field of view")
    ri, ci = int(round(row)), int(round(col))
    if not scene.mask[ri, ci] or not np.isfinite(scene.depth_m[ri, ci]):
        return False, np.inf, 0.0, 0.0
    r0, c0 = int(np.floor(row)), int(np.floor(col))
    z = float(scene.depth_m[ri, ci])
    if 0 <= r0 < n - 1 and 0 <= c0 < n - 1:
        block = scene.depth_m[r0 : r0 + 2, c0 : c0 + 2]
        if np.all(np.isfinite(block)) and np.all(scene.mask[r0 : r0 + 2, c0 : c0 + 2]):
            fr, fc = row - r0, col - c0
            z = float(
                block[0, 0] * (1 - fr) * (1 - fc)
                + block[0, 1] * (1 - fr) * fc
                + block[1, 0] * fr * (1 - fc)
                + block[1, 1] * fr * fc
            )
    cos_inc = float(np.clip(-scene.normals[ri, ci] @ d, 0.0, 1.0))
    return True, z / float(d[2]), float(scene.reflectance[ri, ci]), cos_inc


@dataclass(frozen=True)
class ContinuousWave4:
    """iToF ``cw4``: four CW lasers with 4-phase demodulation, shot noise, background and fog.

    Defaults are the paper's Table 1 and §3 where it gives them (f_mod, T_int, NED, 5 mW,
    α_FOV); the rest are documented assumptions (see the module docstring).

    Attributes:
        f_mod_mhz: modulation frequency, MHz (Table 1 F_mod-eq = 4.8 MHz; ambiguity 31.2 m).
        t_int_us: integration window of one frame, µs (Table 1: 150 µs).
        averaging_s: time over which frames are averaged, s; sets the electronics floor
            ``NED·sqrt(1/(2·averaging_s))`` and the accumulated photon counts.
        ned_cm_per_sqrt_hz: noise-equivalent distance, cm/√Hz (Table 1: 1).
        laser_power_mw: optical power of each laser, mW (§3: 5 mW, IEC 62471); at most 1e15.
        wavelength_nm: laser wavelength, nm (1550).
        spots: ``auto`` (default): steerable spots aimed at the object with the 2D image
            (:func:`aim_spots`; the runner calls :meth:`aimed` before :meth:`measure`), like a
            system with steerable or several emitters; ``fixed``: the paper's geometry below.
        n_spots: number of lasers, 1 to 4.
        aim_threshold: ``auto``: object pixels are brighter than this × the image's 99.5th
            percentile.
        spot_angle_deg: ``fixed``: angle of each laser off the optical axis, degrees (must stay
            inside the camera's field of view). 3.5° puts the spots ~12 mm off axis at 20 cm,
            inside the paper's Ø50 mm sphere.
        azimuth_deg: ``fixed``: azimuth of laser 0 around the axis, degrees; 45° puts one spot
            per quadrant (lasers at 360°/n_spots from each other).
        aim_directions: unit directions ``[[x, y, z], …]`` the spots are aimed at (camera frame);
            set by :meth:`aimed`, or given explicitly; null = from ``spots``.
        aperture_mm: diameter of each receiver's collecting lens, mm (assumption).
        rx_half_fov_deg: half field of view of each receiver, degrees (Table 1 α_FOV = 10°);
            sets how much background light it collects.
        quantum_efficiency: InGaAs quantum efficiency at 1550 nm (0.8).
        demod_contrast: demodulation contrast ``c_d`` in (0, 1] (sine modulation, 4 taps).
        min_phase_snr: a spot whose phase noise exceeds ``1/min_phase_snr`` rad gives no valid
            return: it is reported with ``sigma = inf`` (fusion ignores it) and a warning.
    """

    f_mod_mhz: Annotated[float, Range(0.0, None, "a frequency in MHz", lo_open=True)] = 4.8
    t_int_us: Annotated[float, Range(0.0, None, "an integration time in µs", lo_open=True)] = 150.0
    averaging_s: Annotated[float, Range(0.0, None, "an averaging time in s", lo_open=True)] = 0.5
    ned_cm_per_sqrt_hz: Annotated[float, Range(0.0, None, "a NED in cm/√Hz")] = 1.0
    laser_power_mw: Annotated[float, Range(0.0, _MAX_POWER_MW, "a power in mW", lo_open=True)] = 5.0
    wavelength_nm: Annotated[float, Range(0.0, None, "a wavelength in nm", lo_open=True)] = 1550.0
    spots: Annotated[str, OneOf(SPOT_MODES)] = "auto"
    n_spots: Annotated[int, Range(1, 4, "an integer", integer=True)] = 4
    aim_threshold: Annotated[float, Range(0.0, 1.0, "a fraction", lo_open=True, hi_open=True)] = 0.1
    spot_angle_deg: Annotated[float, Range(0.0, 80.0, "degrees", hi_open=True)] = 3.5
    azimuth_deg: Annotated[float, Range(None, None, "an angle in degrees")] = 45.0
    aim_directions: tuple | None = None
    aperture_mm: Annotated[float, Range(0.0, None, "a diameter in mm", lo_open=True)] = 5.0
    rx_half_fov_deg: Annotated[float, Range(0.0, 90.0, "degrees", lo_open=True, hi_open=True)] = 10.0
    quantum_efficiency: Annotated[float, Range(0.0, 1.0, "a fraction", lo_open=True)] = 0.8
    demod_contrast: Annotated[float, Range(0.0, 1.0, "a contrast", lo_open=True)] = 0.5
    min_phase_snr: Annotated[float, Range(0.0, None, "a phase SNR", lo_open=True)] = 3.0

    @classmethod
    def warm_up(cls, params: Mapping[str, Any]) -> None:
        """Import scikit-image's Otsu threshold (spot aiming; :class:`nirspi_pipe.stages.WarmsUp`)."""
        # warm-up: loads scipy, charset_normalizer, lazy_loader (222 ms here), before jobs fork
        from skimage.filters import threshold_otsu  # noqa: F401

    def __post_init__(self) -> None:
        check_ranges(self)
        if self.averaging_s < self.t_int_us * 1e-6:
            raise ConfigError("averaging_s", self.averaging_s, "at least one frame (>= t_int_us)")
        if self.aim_directions is not None:
            d = np.asarray(self.aim_directions, dtype=np.float64) if np.size(self.aim_directions) else np.zeros(0)
            if (
                d.ndim != 2
                or d.shape[1] != 3
                or not 1 <= len(d) <= 4
                or not np.all(np.isfinite(d))
                or (d[:, 2] <= 0).any()
            ):
                raise ConfigError(
                    "aim_directions", self.aim_directions, "1 to 4 directions [x, y, z] with z > 0, or null"
                )

    def aimed(self, image: Image2D, camera: Camera) -> ContinuousWave4:
        """This iToF with its spots aimed at the object seen in ``image`` (``spots: auto``; the
        ``camera`` is the image's grid). ``fixed``, or explicit ``aim_directions``: unchanged.
        When no object is found the fixed geometry is used, with a warning."""
        if self.spots != "auto" or self.aim_directions is not None:
            return self
        px, notes = aim_spots(image.data, camera, int(self.n_spots), self.aim_threshold)
        if len(px) == 0:
            warnings.warn(f"itof: spots=auto: {'; '.join(notes)}; using the fixed spot geometry", stacklevel=2)
            return self
        x, y = camera.pixel_coords()
        d = np.stack([x[px[:, 0], px[:, 1], 0], y[px[:, 0], px[:, 1], 0], np.ones(len(px))], axis=1)
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        return replace(self, aim_directions=tuple(tuple(float(v) for v in row) for row in d))

    def directions(self) -> np.ndarray:
        """Unit directions ``(k, 3)`` of the lasers (camera frame)."""
        if self.aim_directions is not None:
            d = np.asarray(self.aim_directions, dtype=np.float64).reshape(-1, 3)
            return d / np.linalg.norm(d, axis=1, keepdims=True)
        k = int(self.n_spots)
        th = np.deg2rad(self.spot_angle_deg)
        psi = np.deg2rad(self.azimuth_deg + 360.0 / k * np.arange(k))
        return np.stack([np.sin(th) * np.cos(psi), np.sin(th) * np.sin(psi), np.full(k, np.cos(th))], axis=-1)

    @property
    def f_mod_hz(self) -> float:
        """Modulation frequency, Hz."""
        return self.f_mod_mhz * 1e6

    @property
    def frames(self) -> int:
        """Number of ``T_int`` frames averaged (≥ 1)."""
        return max(1, int(round(self.averaging_s / (self.t_int_us * 1e-6))))

    @property
    def sigma_floor_m(self) -> float:
        """Electronics floor ``NED · sqrt(1/(2·averaging_s))``, metres."""
        return self.ned_cm_per_sqrt_hz * 1e-2 * np.sqrt(1.0 / (2.0 * self.averaging_s))

    def expected_counts(
        self, range_m: float, reflectance: float, cos_inc: float, beta_per_m: float, background_w_m2: float
    ) -> tuple[float, float]:
        """Expected signal and background photo-electrons ``(N_s, B)`` over all frames.

        Args:
            range_m: laser-to-target range, m (``inf`` = no target).
            reflectance: Lambertian reflectance of the target, [0, 1].
            cos_inc: cosine of the incidence angle, [0, 1].
            beta_per_m: fog extinction coefficient, 1/m (signal × exp(−2βr)).
            background_w_m2: in-band background irradiance on the target, W/m².
        """
        e_ph = H_J_S * C_M_S / (self.wavelength_nm * 1e-9)  # J per photon
        t_total = self.frames * self.t_int_us * 1e-6
        a_rx = np.pi * (0.5 * self.aperture_mm * 1e-3) ** 2
        if np.isfinite(range_m) and range_m > 0:
            p_sig = (
                self.laser_power_mw
                * 1e-3
                * reflectance
                * cos_inc
                * a_rx
                / (np.pi * range_m**2)
                * np.exp(-2.0 * beta_per_m * range_m)
            )
        else:
            p_sig = 0.0
        omega = np.pi * np.sin(np.deg2rad(self.rx_half_fov_deg)) ** 2
        refl_bg = reflectance if np.isfinite(range_m) else 0.0
        p_bg = background_w_m2 * refl_bg / np.pi * a_rx * omega
        k = self.quantum_efficiency * t_total / e_ph
        return float(p_sig * k), float(p_bg * k)

    def measure(self, scene: Scene | None, acquisition: Acquisition, rng: np.random.Generator) -> ItofSample:
        """Simulate the four spots on the ground-truth ``scene`` and demodulate them.

        Fog (``beta_per_m``, 1/m) and background light (``background_irradiance_w_m2``, W/m²) are
        read from ``acquisition.derived``; absent keys mean clear air and darkness.

        Returns an :class:`ItofSample` with ``points_m`` ``(4, 3)`` (metres, camera frame: the
        measured range along each laser's direction) and ``sigma_m`` ``(4,)`` (range standard
        deviation in metres; ``inf`` for a spot without a valid return).
        """
        if scene is None:
            raise NirspiError("itof=cw4 simulates the lasers and needs the ground-truth scene")
        beta = float(acquisition.medium.beta_per_m)
        e_bg = float(acquisition.medium.background_irradiance_w_m2)
        if not (np.isfinite(beta) and beta >= 0 and np.isfinite(e_bg) and e_bg >= 0):
            raise NirspiError(f"itof: invalid fog/background in acquisition.derived (beta={beta}, E={e_bg})")
        f = self.f_mod_hz
        lam = ambiguity_range_m(f)
        dirs = self.directions()
        k_phase = np.pi / 2.0 * np.arange(4)
        m = len(dirs)
        points = np.zeros((m, 3))
        sigma = np.zeros(m)
        true_range = np.full(m, np.inf)
        sig_e = np.zeros(m)
        bg_e = np.zeros(m)
        sig_shot = np.zeros(m)
        for j, d in enumerate(dirs):
            hit, r, refl, cos_inc = _sample_at(scene, d)
            n_s, n_b = self.expected_counts(r, refl, cos_inc, beta, e_bg)
            phi = np.mod(4.0 * np.pi * f * r / C_M_S, 2.0 * np.pi) if hit else 0.0
            mean = n_b / 4.0 + n_s / 4.0 * (1.0 + self.demod_contrast * np.cos(phi + k_phase))
            # shot noise of signal + background: Poisson, a Gaussian of the same mean and variance
            # above _POISSON_MAX (numpy's Poisson refuses means above ~9.2e18)
            counts = sample_electrons(mean, rng, shot=True, read_noise_e=0.0, poisson_max=_POISSON_MAX)
            dist_0d, amp, offset = demodulate_4phase(counts, f)  # one pixel: 0-d arrays
            dist = float(dist_0d)
            s_phi: float
            if amp > 0:
                s_phi = float(np.sqrt(offset / 2.0) / (2.0 * amp))  # phase noise, rad
            else:
                s_phi = np.inf
            s_shot = C_M_S / (4.0 * np.pi * f) * s_phi
            if s_phi * self.min_phase_snr > 1.0:
                warnings.warn(
                    f"itof: laser {j} has no valid return (phase SNR {1 / s_phi:.2g} < "
                    f"{self.min_phase_snr:g}{', spot misses the object' if not hit else ''}); sigma = inf",
                    stacklevel=2,
                )
                sigma[j] = np.inf
            else:
                # electronics floor on the averaged range, then wrap into [0, c/2f)
                dist = float(np.mod(dist + rng.normal(0.0, self.sigma_floor_m), lam))
                sigma[j] = float(np.hypot(s_shot, self.sigma_floor_m))
            points[j] = dist * d
            true_range[j], sig_e[j], bg_e[j], sig_shot[j] = r, n_s, n_b, s_shot
        info = {
            "aimed": self.aim_directions is not None,
            "ambiguity_range_m": lam,
            "frames": self.frames,
            "sigma_floor_m": float(self.sigma_floor_m),
            "valid_spots": int(np.isfinite(sigma).sum()),
            "signal_electrons_mean": float(np.mean(sig_e)),
            "background_electrons_mean": float(np.mean(bg_e)),
        }
        # only finite numbers go into the record: a spot without a valid return has no sigma
        if np.isfinite(sig_shot).any():
            info["sigma_shot_max_m"] = float(np.max(sig_shot[np.isfinite(sig_shot)]))
        if np.isfinite(sigma).any():
            info["sigma_mean_m"] = float(np.mean(sigma[np.isfinite(sigma)]))
        return ItofSample(points_m=points, sigma_m=sigma, info=info)
