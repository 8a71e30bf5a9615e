"""Source ``simulator``: the NIR-SPI camera in the fog chamber (paper §§3–5, Eqs. 5–12).

The simulator is composed of the effects the config lists, and of nothing else:

=================  ========================================  =====================================
effect             config                                    what it does
=================  ========================================  =====================================
photon budget      ``detector=ingaas`` (``detector.budget``)  1/r² fall-off per pixel, LED power,
                                                              lens, QE, T_int, A_pix, FF, f#
fog                ``fog=chamber|measured``                   e^{−2βr} per pixel (round trip),
                                                              backscatter veil (Eq. 12)
background light   ``illumination=klux``                      ambient charge on every reading
                                                              (Eqs. 7, 10–11), with its shot noise
detector           ``detector=ingaas``                        shot, dark, read noise, saturation,
                                                              ADC (counted, never hidden)
time-varying       ``illumination.drift_rel_per_s`` …,        background and fog density change
                   ``fog.fluctuation_rel``                    between readings (seeded)
=================  ========================================  =====================================

``fog=none``, ``illumination=none`` (0 kLux) and ``detector=ideal`` build nothing: no Mie call, no
fog array, no noise draw. With all three, the readings are the split Hadamard measurements of
the scene radiance and the reconstruction equals it to rounding.

Split convention: each ±1 pattern ``P_k`` is shown as ``(1 + P_k)/2`` then ``(1 − P_k)/2``, one
pattern period apart (``1/pattern_rate_hz``), so a changing background does not cancel exactly
in their difference. A physical detector first takes ``dark_readings`` LEDs-off readings (the
background/dark reference used for the measured signal in ``derived``).

Units: readings are ADC counts for a physical detector (``gain`` = counts per unit relative
radiance per pixel at the scene's nominal distance in clear air), relative radiance for the
ideal one (``gain = 1``). ``Acquisition.coefficients()`` is therefore always relative radiance.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np

from nirspi_pipe.errors import ConfigError, NirspiError
from nirspi_pipe.patterns.hadamard import fwht2
from nirspi_pipe.types import Acquisition, Scene

__all__ = ["Simulator", "split_measure", "modulated_split"]

#: ``snr_db`` is clipped to ±this (noise-free or signal-free readings), so records stay finite.
SNR_DB_LIMIT = 200.0


def split_measure(radiance: np.ndarray, indices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free split measurements of ``radiance`` for the given flat pattern indices.

    Pattern ``P_k`` (±1) is shown as ``(1 + P_k)/2`` and ``(1 − P_k)/2``; with ``c_k = Σ P_k O``
    (Eq. 1, α = 1) and ``S = Σ O`` the two readings are ``(S + c_k)/2`` and ``(S − c_k)/2``.
    Units: radiance × pixels. Cost ``O(N log N)`` for all patterns at once.
    """
    coeffs = fwht2(radiance).ravel()[np.asarray(indices, dtype=np.int64)]
    total = float(radiance.sum())
    return 0.5 * (total + coeffs), 0.5 * (total - coeffs)


def modulated_split(
    base: np.ndarray, x: np.ndarray, c_pos: np.ndarray, c_neg: np.ndarray, indices: np.ndarray, tol: float = 1e-12
) -> tuple[np.ndarray, np.ndarray]:
    """Split readings of ``base ⊙ exp(−c x)`` where the scalar ``c`` changes per reading.

    ``pos_k = Σ (1 + P_k)/2 ⊙ base ⊙ e^{−c_pos[k] x}``, ``neg_k`` likewise with ``(1 − P_k)/2``
    and ``c_neg[k]``. This is how a fog density that fluctuates during the acquisition
    (``β(t) = β f(t)``) acts on every pattern without building the patterns: around the
    base-weighted mean ``x₀``, ``e^{−c x} = e^{−c x₀} Σ_j (−c)^j (x − x₀)^j / j!``, one transform per
    term, truncated when the remainder bound is below ``tol`` (a handful of terms in practice).
    When ``|c (x − x₀)|`` exceeds 8 the series is replaced by exact transforms at 65 levels of
    ``c`` with linear interpolation between them.
    """
    idx = np.asarray(indices, dtype=np.int64)
    c_pos = np.asarray(c_pos, dtype=np.float64)
    c_neg = np.asarray(c_neg, dtype=np.float64)
    w = np.abs(base)
    x = np.where(w > 0, x, 0.0)
    x0 = float((w * x).sum() / w.sum()) if w.sum() > 0 else 0.0
    dx = np.where(w > 0, x - x0, 0.0)
    cmax = float(max(np.abs(c_pos).max(initial=0.0), np.abs(c_neg).max(initial=0.0)))
    amp = cmax * float(np.abs(dx).max(initial=0.0))
    if amp <= 8.0:
        pos = np.zeros(idx.size)
        neg = np.zeros(idx.size)
        term = base.astype(np.float64)
        w_pos = np.ones(idx.size)  # (−c)^j, updated in place
        w_neg = np.ones(idx.size)
        j = 0
        while True:
            f = fwht2(term).ravel()[idx]
            s = float(term.sum())
            pos += w_pos * (s + f)
            neg += w_neg * (s - f)
            bound = amp ** (j + 1) / math.factorial(j + 1) * math.exp(amp)
            if bound < tol or j >= 60:
                break
            j += 1
            term = term * dx / j
            w_pos *= -c_pos
            w_neg *= -c_neg
        pos *= 0.5
        neg *= 0.5
        return pos * np.exp(-c_pos * x0), neg * np.exp(-c_neg * x0)
    both = np.concatenate([c_pos, c_neg])
    levels = np.linspace(both.min(), both.max(), 65)
    f_lv = np.empty((levels.size, idx.size))
    s_lv = np.empty(levels.size)
    for i, c in enumerate(levels):
        img = base * np.exp(-c * x)
        f_lv[i] = fwht2(img).ravel()[idx]
        s_lv[i] = img.sum()

    def interp(c: np.ndarray, sign: float) -> np.ndarray:
        pos_in = np.clip(np.searchsorted(levels, c) - 1, 0, levels.size - 2)
        t = (c - levels[pos_in]) / np.maximum(levels[pos_in + 1] - levels[pos_in], 1e-300)
        k = np.arange(idx.size)
        lo = 0.5 * (s_lv[pos_in] + sign * f_lv[pos_in, k])
        hi = 0.5 * (s_lv[pos_in + 1] + sign * f_lv[pos_in + 1, k])
        return (1 - t) * lo + t * hi

    return interp(c_pos, 1.0), interp(c_neg, -1.0)


def _spawn(rng: np.random.Generator, k: int) -> list[np.random.Generator]:
    """``k`` independent child generators (one per effect) without drawing from ``rng``, so an
    effect switched on does not change another's noise."""
    if hasattr(rng, "spawn"):  # numpy >= 1.25
        return rng.spawn(k)
    seq = rng.bit_generator.seed_seq  # type: ignore[attr-defined]
    return [np.random.default_rng(s) for s in seq.spawn(k)]


def _is_active(effect: Any) -> bool:
    return effect is not None and bool(getattr(effect, "active", True))


def _build_effect(group: str, node: Any) -> Any:
    """Instantiate an effect config (``_target_``) of config group ``group``; its errors name
    ``group.<key>`` (what the user typed), not ``source.<group>.<key>``."""
    from collections.abc import Mapping

    from omegaconf import DictConfig, OmegaConf

    from nirspi_pipe.pipeline import build

    if isinstance(node, DictConfig):
        node = OmegaConf.to_container(node, resolve=True)
    if not isinstance(node, Mapping) or "_target_" not in node:
        raise ConfigError(
            group, node, f"a {group} config with a _target_ (conf/{group}/*.yaml), or null", absolute=True
        )
    try:
        return build(OmegaConf.create(dict(node)), group)
    except ConfigError as exc:
        # the effects are config groups of their own, although the source builds them
        raise ConfigError(exc.key, exc.value, exc.allowed, exc.unknown_key, absolute=True) from None


@dataclass(frozen=True)
class Simulator:
    """Simulated single-pixel camera, composed of the configured effects (module docstring).

    Attributes:
        noise_rel: extra additive Gaussian noise per reading, relative to the mean half-pattern
            reading (the foundation's idealised noise; 0 = none).
        pattern_rate_hz: patterns shown per second; each ±1 measurement takes two.
        dark_readings: LEDs-off reference readings taken before the patterns (physical
            detectors only), for the background/dark level of the measured signal.
        fog: a fog model (:mod:`nirspi_pipe.physics.fog`), its config (``_target_``), or None.
        illumination: a :class:`~nirspi_pipe.physics.light.Background`, its config, or None.
        detector: :class:`~nirspi_pipe.physics.detector.IdealDetector` (default) or
            :class:`~nirspi_pipe.physics.detector.Photodiode`, or its config.

    From Hydra, the three come as configs (``_recursive_: false`` in conf/source/simulator.yaml)
    and are built here, so that a bad value is reported under its own group
    (``fog.number_density_per_cm3``).
    """

    noise_rel: float = 0.0
    pattern_rate_hz: float = 1000.0
    dark_readings: int = 16
    fog: Any = None
    illumination: Any = None
    detector: Any = None

    needs_scene = True

    def __post_init__(self) -> None:
        from nirspi_pipe.physics.detector import IdealDetector

        if not np.isfinite(self.noise_rel) or self.noise_rel < 0:
            raise ConfigError("noise_rel", self.noise_rel, "a relative noise level >= 0")
        if not np.isfinite(self.pattern_rate_hz) or not self.pattern_rate_hz > 0:
            raise ConfigError("pattern_rate_hz", self.pattern_rate_hz, "a rate in Hz > 0")
        if int(self.dark_readings) != self.dark_readings or not 0 <= self.dark_readings <= 100000:
            raise ConfigError("dark_readings", self.dark_readings, "an integer from 0 to 100000")
        for key in ("fog", "illumination", "detector"):
            value = getattr(self, key)
            if value is not None and not hasattr(value, "__dataclass_fields__"):
                object.__setattr__(self, key, _build_effect(key, value))
        if self.fog is not None and not hasattr(type(self.fog), "extinction_per_m"):  # no Mie here
            raise ConfigError("fog", self.fog, "a fog model exposing extinction_per_m")
        det = self.detector if self.detector is not None else IdealDetector()
        if not hasattr(det, "physical"):
            raise ConfigError("detector", det, "a detector from conf/detector (ideal, ingaas)")
        object.__setattr__(self, "_detector", det)
        object.__setattr__(self, "_fog", self.fog if _is_active(self.fog) else None)
        object.__setattr__(self, "_background", self.illumination if _is_active(self.illumination) else None)

    @property
    def effects(self) -> tuple[str, ...]:
        """Names of the effects this simulator is built from, in the order they act."""
        det, fog, bg = self._detector, self._fog, self._background  # type: ignore[attr-defined]
        names = []
        if det.physical:
            names.append("budget")
        if fog is not None:
            names.append("fog")
            if fog.backscatter_gain > 0:
                names.append("backscatter")
            if fog.fluctuation_rel > 0:
                names.append("fog_fluctuation")
        if bg is not None:
            names.append("background")
            if bg.time_varying:
                names.append("background_drift")
        if det.physical:
            names.append("detector")
        if self.noise_rel > 0:
            names.append("gaussian_noise")
        return tuple(names)

    def acquire(self, scene: Scene | None, indices: np.ndarray, n: int, rng: np.random.Generator) -> Acquisition:
        """Measure ``scene`` with the patterns ``indices``, in that order (see module docstring)."""
        from nirspi_pipe.physics.budget import PhotonBudget

        if scene is None:
            raise NirspiError("source=simulator needs a scene")
        if scene.radiance.shape != (n, n):
            raise NirspiError(f"scene rendered at {scene.radiance.shape}, patterns are {n}x{n}")
        det, fog, bg = self._detector, self._fog, self._background  # type: ignore[attr-defined]
        idx = np.asarray(indices, dtype=np.int64)
        m = idx.size
        physical = bool(det.physical)
        budget = det.budget if physical else PhotonBudget()
        n_dark = int(self.dark_readings) if physical else 0
        period = 1.0 / self.pattern_rate_hz
        t_pos = (n_dark + 2.0 * np.arange(m)) * period
        t_neg = t_pos + period
        derived: dict[str, Any] = {}
        info: dict[str, Any] = {"patterns_measured": m, "patterns_shown": 2 * m + n_dark, "effects": ",".join(self.effects)}
        streams = _spawn(rng, 3) if (physical or fog is not None or bg is not None) else None

        z_nom = float(scene.distance_m)
        ref = float(budget.white_electrons(z_nom)) / (n * n)  # e⁻ per unit radiance per pixel, z_nom, clear air
        rho = scene.radiance
        if physical or fog is not None or bg is not None:
            u, v = scene.camera.pixel_coords(1)
            finite = np.isfinite(scene.depth_m)
            range_m = np.where(finite, scene.depth_m * np.sqrt(1.0 + u[..., 0] ** 2 + v[..., 0] ** 2), np.inf)
        # active light per pixel, e⁻ (ideal detector: no fall-off across the object)
        if physical:
            img = rho * np.where(finite, budget.white_electrons(np.where(finite, range_m, 1.0)), 0.0) / (n * n)
        else:
            img = rho * ref

        beta = 0.0
        veil_pos = veil_neg = None
        if fog is None:
            pos_e, neg_e = split_measure(img, idx)
        else:
            beta = float(fog.extinction_per_m)
            derived.update(fog.derived())
            x = np.where(np.isfinite(range_m), 2.0 * beta * np.where(np.isfinite(range_m), range_m, 0.0), 0.0)
            fog_path = np.minimum(range_m, fog.extent_m)
            white_1m = float(budget.white_electrons(1.0)) / (n * n)
            if fog.fluctuation_rel > 0:
                from nirspi_pipe.physics.timevarying import fog_factor

                f_all = fog_factor(np.concatenate([t_pos, t_neg]), streams[0], fog.fluctuation_rel, fog.fluctuation_time_s)
                f_pos, f_neg = f_all[:m], f_all[m:]
                pos_e, neg_e = modulated_split(img, x, f_pos, f_neg, idx)
                if fog.backscatter_gain > 0:  # Eq. (12): κ N_white(1 m) (1 − e^{−β(t) ℓ})
                    k = np.full(img.shape, fog.backscatter_gain * white_1m)
                    a_pos, a_neg = split_measure(k, idx)
                    b_pos, b_neg = modulated_split(k, beta * fog_path, f_pos, f_neg, idx)
                    veil_pos, veil_neg = a_pos - b_pos, a_neg - b_neg
                derived["fog_factor_std"] = float(np.std(f_all))
            else:
                from nirspi_pipe.physics.fog import backscatter

                img = img * np.exp(-x)
                if fog.backscatter_gain > 0:
                    veil = backscatter(fog.backscatter_gain, white_1m, beta, fog_path) * np.ones(img.shape)
                    veil_pos, veil_neg = split_measure(veil, idx)
                pos_e, neg_e = split_measure(img, idx)
            if veil_pos is not None:
                derived["backscatter_photons_per_pattern"] = float(0.5 * (veil_pos.mean() + veil_neg.mean())) if m else 0.0
                pos_e, neg_e = pos_e + veil_pos, neg_e + veil_neg
        derived["beta_per_m"] = beta
        derived["transmittance_roundtrip"] = float(np.exp(-2.0 * beta * z_nom))
        signal_mean = float(0.5 * (pos_e.mean() + neg_e.mean())) if m else 0.0

        # background light: the same ambient charge on every reading (Eqs. 7, 10–11)
        bg_e = 0.0
        bg_pos = bg_neg = bg_dark = 0.0
        if bg is not None:
            from nirspi_pipe.physics.fog import koschmieder_radiance

            cov = scene.coverage
            if fog is not None:
                alb = float(fog.single_scattering_albedo)
                obj = koschmieder_radiance(scene.reflectance, alb, beta, np.where(np.isfinite(fog_path), fog_path, 0.0))
                wall = koschmieder_radiance(bg.surround_reflectance, alb, beta, fog.extent_m)
            else:
                obj, wall = scene.reflectance, bg.surround_reflectance
            refl = float(np.mean(cov * obj + (1.0 - cov) * wall))
            bg_e = float(budget.ambient_electrons(bg.photon_irradiance, refl))
            bg_pos = bg_neg = bg_dark = bg_e
            if bg.time_varying:
                from nirspi_pipe.physics.timevarying import background_factor

                t_dark = np.arange(n_dark) * period
                fac = background_factor(
                    np.concatenate([t_pos, t_neg, t_dark]), streams[1], bg.drift_rel_per_s, bg.flicker_rel,
                    bg.flicker_hz, bg.wander_rel, bg.wander_time_s,
                )
                bg_pos, bg_neg, bg_dark = bg_e * fac[:m], bg_e * fac[m : 2 * m], bg_e * fac[2 * m :]
                derived["background_factor_std"] = float(np.std(fac))
            pos_e, neg_e = pos_e + bg_pos, neg_e + bg_neg
            derived["klux"] = float(bg.klux)
            derived["background_irradiance_w_m2"] = float(bg.irradiance_w_m2)
        else:
            derived["background_irradiance_w_m2"] = 0.0
        derived["background_photons_per_pattern"] = bg_e
        derived["signal_photons_per_pattern"] = signal_mean

        # detector
        if physical:
            epc = det.electrons_per_count
            y_pos, sat_pos = det.read(pos_e, streams[2])
            y_neg, sat_neg = det.read(neg_e, streams[2])
            saturated = int(sat_pos.sum() + sat_neg.sum())
            gain = ref / epc
            noise_e = float(det.noise_e(signal_mean + bg_e))
            derived.update(
                read_noise_e=float(det.read_noise_e),
                dark_electrons=float(det.dark_electrons),
                electrons_per_count=float(epc),
                led_count=int(budget.led_count),
                noise_photons_per_pattern=noise_e,
            )
            if det.full_scale_e is not None:
                derived["full_scale_e"] = float(det.full_scale_e)
            if n_dark:
                dark_counts, sat_dark = det.read(np.broadcast_to(bg_dark, (n_dark,)) + 0.0, streams[2])
                saturated += int(sat_dark.sum())
                if m:
                    derived["measured_signal_e"] = float((np.mean(y_pos + y_neg) - 2.0 * np.mean(dark_counts)) * epc)
            if m >= 2:
                derived["measured_noise_e"] = float(np.std(y_pos + y_neg, ddof=1) / np.sqrt(2.0) * epc)
            if saturated:
                warnings.warn(
                    f"{saturated} of {2 * m + n_dark} readings saturated the detector (full scale "
                    f"{det.full_scale_e:.3g} e-); reduce klux, LED power or move the object away",
                    stacklevel=2,
                )
            derived.update(self._range(scene, det, fog, bg, beta))
        else:
            y_pos, y_neg = pos_e / ref, neg_e / ref
            gain, saturated, noise_e = 1.0, 0, 0.0
        derived["saturated_patterns"] = saturated
        derived["saturated_fraction"] = saturated / max(2 * m + n_dark, 1)

        # the foundation's idealised Gaussian noise (output units)
        sigma = 0.0
        if self.noise_rel > 0:
            sigma = self.noise_rel * 0.5 * float(scene.radiance.sum()) * gain
            y_pos = y_pos + rng.normal(0.0, sigma, y_pos.shape)
            y_neg = y_neg + rng.normal(0.0, sigma, y_neg.shape)
            noise_e = float(np.hypot(noise_e, sigma * (ref / gain)))
        derived["noise_sigma"] = float(sigma)
        if noise_e > 0 and signal_mean > 0:
            snr_db = 20.0 * np.log10(signal_mean / noise_e)
        else:
            snr_db = SNR_DB_LIMIT if signal_mean > 0 else -SNR_DB_LIMIT
        derived["snr_db"] = float(np.clip(snr_db, -SNR_DB_LIMIT, SNR_DB_LIMIT))
        return Acquisition(
            n=n,
            indices=idx,
            y_pos=np.asarray(y_pos, dtype=np.float64),
            y_neg=np.asarray(y_neg, dtype=np.float64),
            gain=float(gain),
            truth=scene,
            timestamps_s=t_pos,
            derived=derived,
            info=info,
        )

    @staticmethod
    def _range(scene: Scene, det: Any, fog: Any, bg: Any, beta: float) -> dict[str, float]:
        """Alg. A1 for this configuration and the object's mean reflectance."""
        from nirspi_pipe.physics.range_model import max_distance_m

        obj = scene.mask if scene.mask.any() else scene.coverage > 0
        if not obj.any():
            return {}
        refl = float(np.clip(scene.reflectance[obj].mean(), 0.0, 1.0))
        cond: dict[str, float] = {"beta_per_m": beta}
        if fog is not None:
            cond.update(backscatter_gain=float(fog.backscatter_gain), fog_extent_m=float(fog.extent_m),
                        albedo=float(fog.single_scattering_albedo))
        if bg is not None:
            cond["photon_irradiance"] = float(bg.photon_irradiance)
        return {"range_max_m": max_distance_m(refl, det, **cond), "range_reflectance": refl}
