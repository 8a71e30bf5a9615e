"""The physical model of the NIR-SPI camera in the fog chamber (docs/physics.md).

* :mod:`.fog` — droplet size (Eq. 5), Mie (miepython, lazily), extinction (Eq. 6), Beer–Lambert,
  Koschmieder (Eqs. 7–9), backscatter (Eq. 12); fog models ``NoFog``, ``MieFog``, ``MeasuredFog``.
* :mod:`.light` — kLux → in-band irradiance and photon flux; the ``Background`` effect.
* :mod:`.budget` — the photon budget at the photodiode (Eqs. 10–11), ``PhotonBudget``.
* :mod:`.detector` — ``IdealDetector`` and the InGaAs ``Photodiode`` (shot, dark, read noise,
  saturation, ADC).
* :mod:`.timevarying` — background drift/flicker/wander and fog fluctuation (seeded).
* :mod:`.range_model` — Algorithm A1 and the calibration of its free constants on Table 2.
* :mod:`.stagetypes` — the forward model's typed stages: the hand-offs (``ImageState``, ``Readings``,
  ``Output``), the protocols of image, reading and output effects and of the read-out, the
  measurement and the ideal read-out between them; the import path for plugin effects.
* :mod:`.splitmeasure` — the split Hadamard measurement (``split_measure``, ``modulated_split``).
* :mod:`.lighteffects` — the built-in effects of light: illumination (photon budget), background
  light and its drift.
* :mod:`.effects` — the other built-in effects (fog attenuation, fog fluctuation and trend,
  backscatter, LED droop, detector read-out, Gaussian noise), the
  :class:`~.effects.ForwardModel` that holds them by stage, and :func:`~.effects.forward_model`.

The simulator (:mod:`nirspi_pipe.sources.simulator`) runs the forward model the runner built from
the config.
"""
