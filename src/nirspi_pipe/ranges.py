"""Declarative ranges of stage fields (issue 42, item 2).

A stage declares each field's range where it declares its type, in the annotation::

    klux: Annotated[float, Range(0.0, 100.0, "an illuminance in kLux")] = 0.0
    spectrum: Annotated[str, OneOf(("sun", "halogen", "blackbody"))] = "blackbody"

and its ``__post_init__`` calls :func:`check_ranges` once. One function checks every declared
range and raises the one-line :class:`~nirspi_pipe.errors.ConfigError` naming the key and the
allowed values (``klux=150.0 is not allowed; allowed: an illuminance in kLux in [0, 100]``);
:func:`describe` lists them for ``python -m nirspi_pipe.ranges`` and docs/ranges.md. Checks that
relate two fields (``lo < hi``) or need the physics stay in the stage's ``__post_init__``.

A value of ``None`` passes: whether a field may be null is its type's business
(:func:`nirspi_pipe.instantiate.check_types`), and a stage fills its own defaults after the check.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import sys
import typing
from collections.abc import Iterator
from dataclasses import dataclass
from functools import lru_cache
from typing import Any

import numpy as np

from nirspi_pipe.errors import ConfigError

__all__ = ["Range", "OneOf", "check_ranges", "check_value", "field_ranges", "allowed_text", "describe"]


def _num(x: float) -> str:
    """``100.0`` → ``100``, ``0.001`` → ``0.001``, ``1e9`` → ``1e+09`` (as ``%g`` writes it)."""
    return f"{x:g}"


@dataclass(frozen=True)
class Range:
    """A finite number in an interval.

    Attributes:
        lo, hi: the bounds (None = unbounded on that side; the value must still be finite).
        what: what the number is, in words with its unit (``a distance in mm``).
        lo_open, hi_open: whether the bound itself is excluded (``> 0`` rather than ``>= 0``).
        integer: the value must be a whole number (``int`` or a float with no fraction).
        finite: infinities are refused (NaN always is); False lets ``.inf`` through where the
            interval holds it (an unbounded fog).
        note: said after the interval, in parentheses (``.inf for unbounded fog``).
        also: words accepted besides a number (``("auto",)``: the stage chooses the value).
        key: the config key that sets the field, when it is not the field's own name (an effect
            built from ``source.effects.led_droop_rel`` keeps it as ``LedDroop.rel``); the error
            and the docs name it, so the user reads the key they set.
    """

    lo: float | None = None
    hi: float | None = None
    what: str = "a number"
    lo_open: bool = False
    hi_open: bool = False
    integer: bool = False
    finite: bool = True
    note: str = ""
    also: tuple[str, ...] = ()
    key: str = ""

    def allowed(self) -> str:
        """The allowed values in words (the ``allowed:`` part of the error)."""
        words = "".join(f"{w}, or " for w in self.also)
        return words + self._interval() + (f" ({self.note})" if self.note else "")

    def _interval(self) -> str:
        lo, hi = self.lo, self.hi
        if lo is not None and hi is not None:
            return f"{self.what} in {'(' if self.lo_open else '['}{_num(lo)}, {_num(hi)}{')' if self.hi_open else ']'}"
        if lo is not None:
            return f"{self.what} {'>' if self.lo_open else '>='} {_num(lo)}"
        if hi is not None:
            return f"{self.what} {'<' if self.hi_open else '<='} {_num(hi)}"
        return f"{self.what} (finite)"

    def contains(self, value: Any) -> bool:
        """Whether ``value`` is a finite number (not a bool) inside the interval, or one of ``also``."""
        if isinstance(value, str):
            return value in self.also
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
            return False
        v = float(value)
        if math.isnan(v) or (self.finite and math.isinf(v)) or (self.integer and not v.is_integer()):
            return False
        if self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo):
            return False
        return not (self.hi is not None and (v >= self.hi if self.hi_open else v > self.hi))


@dataclass(frozen=True)
class OneOf:
    """One of a fixed set of values (names of a registry, say)."""

    values: tuple[Any, ...]
    what: str = ""

    def allowed(self) -> str:
        return f"{self.what + ': ' if self.what else ''}one of {list(self.values)}"

    def contains(self, value: Any) -> bool:
        return any(value == v and type(value) is type(v) for v in self.values)


Spec = Range | OneOf


@lru_cache(maxsize=512)
def field_ranges(cls: Any) -> tuple[tuple[str, Spec, bool], ...]:
    """``(field, range, nullable)`` for every field of dataclass ``cls`` whose annotation carries
    a :class:`Range` or :class:`OneOf` (read once per class); ``nullable``: the type admits None."""
    if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
        return ()
    hints = typing.get_type_hints(cls, vars(sys.modules[cls.__module__]), include_extras=True)
    out = []
    for f in dataclasses.fields(cls):
        hint = hints.get(f.name)
        for meta in getattr(hint, "__metadata__", ()):
            if isinstance(meta, (Range, OneOf)):
                nullable = type(None) in typing.get_args(typing.get_args(hint)[0])
                out.append((f.name, meta, nullable))
    return tuple(out)


def allowed_text(spec: Spec, nullable: bool) -> str:
    """The allowed values of a field in words (``…, or null`` when its type admits None)."""
    return spec.allowed() + (", or null" if nullable else "")


def check_ranges(obj: Any) -> None:
    """Raise :class:`ConfigError` for the first field of dataclass ``obj`` outside its declared
    range (fields in declaration order; None passes). A whole float in an integer field becomes
    the ``int`` (the object is frozen: set once, here, before any use)."""
    cls: Any = type(obj)
    for name, spec, nullable in field_ranges(cls):
        value = getattr(obj, name)
        if value is not None and not spec.contains(value):
            raise ConfigError(_key(name, spec), value, allowed_text(spec, nullable))
        if isinstance(spec, Range) and spec.integer and isinstance(value, float):
            object.__setattr__(obj, name, int(value))  # 4.0 from a command line: the count 4


def check_value(value: Any, spec: Range, key: str = "") -> None:
    """Raise :class:`ConfigError` when ``value`` is outside ``spec``: the same check and words as
    :func:`check_ranges`, for a value that is a function's argument rather than a field (the
    function and the stage it builds share one declaration). The key is ``key``, else ``spec.key``."""
    if not spec.contains(value):
        raise ConfigError(key or spec.key, value, spec.allowed())


def _key(name: str, spec: Spec) -> str:
    """The key a user sets for field ``name``: the range's own ``key`` where it has one."""
    return spec.key if isinstance(spec, Range) and spec.key else name


def describe(cls: type) -> Iterator[str]:
    """``key: allowed values`` lines of ``cls``'s declared ranges."""
    for name, spec, nullable in field_ranges(cls):
        yield f"{_key(name, spec)}: {allowed_text(spec, nullable)}"
