"""Errors that nirspi-pipe reports to the user as one line, without a traceback."""

from __future__ import annotations

from typing import Any

__all__ = ["NirspiError", "ConfigError"]


class NirspiError(Exception):
    """Base class for errors with a user-facing one-line message."""


class ConfigError(NirspiError, ValueError):
    """A configuration value is out of range.

    ``key`` is the config key relative to the object that raised it (``resolution``); the
    pipeline prefixes the group it was building (``camera.resolution``) with :meth:`under`,
    unless ``absolute`` says the key is already a full path (``fog.number_density_per_cm3``).
    """

    def __init__(self, key: str, value: Any, allowed: str, unknown_key: bool = False, absolute: bool = False) -> None:
        self.key, self.value, self.allowed, self.unknown_key = key, value, allowed, unknown_key
        self.absolute = absolute  # key is already the full config path: never prefix it
        if unknown_key:
            super().__init__(f"{key} is not a key; allowed keys: {allowed}")
        else:
            super().__init__(f"{key}={value!r} is not allowed; allowed: {allowed}")

    def under(self, prefix: str) -> ConfigError:
        """The same error with its key prefixed by ``prefix`` (``scene`` → ``scene.distance_mm``)."""
        if not prefix or self.absolute or self.key.startswith(prefix + "."):
            return self
        return ConfigError(f"{prefix}.{self.key}", self.value, self.allowed, self.unknown_key)
