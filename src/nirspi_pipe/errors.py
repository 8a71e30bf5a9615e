"""Errors that nirspi-pipe reports to the user as one line, without a traceback."""

from __future__ import annotations

from typing import Any

__all__ = ["NirspiError", "ConfigError", "NumericalError", "plain_value", "yaml_problem"]


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
            super().__init__(f"{key}={plain_value(value)!r} is not allowed; allowed: {allowed}")

    def under(self, prefix: str) -> ConfigError:
        """The same error with its key prefixed by ``prefix`` (``scene`` → ``scene.distance_mm``)."""
        if not prefix or self.absolute or self.key.startswith(prefix + "."):
            return self
        return ConfigError(f"{prefix}.{self.key}", self.value, self.allowed, self.unknown_key)


class NumericalError(NirspiError):
    """A stage's arithmetic left float64's range (overflow, an invalid operation, a division by
    zero) or produced a NaN/Inf result: the job fails with one line naming the stage
    (``stage`` attribute) and what happened, never with status ok (docs/hostile.md)."""

    def __init__(self, stage: str, what: str) -> None:
        self.stage, self.what = stage, what
        super().__init__(f"{stage}: {what}")


def plain_value(value: Any) -> Any:
    """A numpy scalar as the Python number it holds (``0.0``, not ``np.float64(0.0)``, in a
    message); anything else unchanged."""
    item = getattr(value, "item", None)
    if callable(item) and getattr(value, "shape", None) == ():
        try:
            return item()
        except (TypeError, ValueError):
            return value
    return value


def yaml_problem(exc: BaseException) -> str | None:
    """One line naming the config file and line when ``exc`` (or what it wraps) is a YAML error
    from reading a config file, else None. Config files are read with a safe loader (OmegaConf's),
    so a ``!!python/...`` tag never builds anything; it is reported as a tag that is not allowed."""
    import yaml  # start-up: loads yaml (15 ms here)

    seen: set[int] = set()
    err: BaseException | None = exc
    while err is not None and not isinstance(err, yaml.YAMLError) and id(err) not in seen:
        seen.add(id(err))
        err = err.__cause__ or err.__context__
    if not isinstance(err, yaml.YAMLError):
        return None
    mark = getattr(err, "problem_mark", None) or getattr(err, "context_mark", None)
    where = f"config file {mark.name}, line {mark.line + 1}" if mark is not None else "a config file"
    problem = " ".join(str(getattr(err, "problem", None) or err).split())
    marker = "tag:yaml.org,2002:"
    if "constructor for the tag" in problem and "'" in problem:
        tag = problem.split("'")[1]
        tag = "!!" + tag[len(marker) :] if tag.startswith(marker) else tag
        return f"{where}: the YAML tag {tag!r} is not allowed; allowed: plain YAML values (a config never builds Python objects)"
    return f"{where}: not valid YAML: {problem}"
