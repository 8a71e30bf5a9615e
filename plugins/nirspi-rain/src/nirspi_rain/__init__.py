"""nirspi-rain: an example nirspi-pipe plugin adding a physical effect (rain attenuation).

nirspi-pipe imports this module through the entry point ``rain = "nirspi_rain"`` (group
``nirspi_pipe.plugins``) and adds :data:`SEARCHPATH` to Hydra's search path, so
``nirspi-run source=simulator_rain`` works once the package is installed.
"""

from __future__ import annotations

from nirspi_rain.effect import CARBONNEAU_ALPHA, CARBONNEAU_K_DB_PER_KM, Rain, rain_extinction_per_m

__all__ = ["Rain", "rain_extinction_per_m", "CARBONNEAU_K_DB_PER_KM", "CARBONNEAU_ALPHA", "SEARCHPATH"]

#: The config folder holding ``source/simulator_rain.yaml``.
SEARCHPATH = "pkg://nirspi_rain.conf"
