"""Strict JSON (RFC 8259: no ``NaN``/``Infinity`` tokens) for every JSON file the project writes.

A non-finite number, such as the user's ``fog.extent_mm=inf`` in a record's ``config``, is
written as the YAML spelling the command line and config files accept: the strings ``".inf"``,
``"-.inf"`` and ``".nan"`` (:data:`NONFINITE_SPELLINGS`); :func:`decode_nonfinite` turns them
back into floats. Moved out of :mod:`nirspi_pipe.records` (issue 42 item 5).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

__all__ = ["NONFINITE_SPELLINGS", "decode_nonfinite", "dumps_strict", "jsonable"]


#: How a non-finite float is written in a record (YAML 1.1's spellings, which OmegaConf's loader
#: and ``nirspi-run key=.inf`` read back as floats).
NONFINITE_SPELLINGS = {math.inf: ".inf", -math.inf: "-.inf"}
_NAN_SPELLING = ".nan"
_DECODED = {".inf": math.inf, "-.inf": -math.inf, ".nan": math.nan}


def _float_leaf(x: float) -> float | str:
    if math.isfinite(x):
        return x
    return _NAN_SPELLING if math.isnan(x) else NONFINITE_SPELLINGS[x]


def decode_nonfinite(value: Any) -> Any:
    """``value`` (read from a record) with the spellings ``".inf"``, ``"-.inf"``, ``".nan"``
    turned back into floats, at any depth; anything else unchanged."""
    if isinstance(value, dict):
        return {k: decode_nonfinite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [decode_nonfinite(v) for v in value]
    if isinstance(value, str) and value in _DECODED:
        return _DECODED[value]
    return value


def dumps_strict(value: Any, **kwargs: Any) -> str:
    """``json.dumps`` of ``value`` as strict JSON: numpy values made plain and every non-finite
    float written as its spelling (``".inf"``, module docstring), ``allow_nan=False``; the
    writer for every JSON file the project writes (``kwargs``: ``indent``, ``sort_keys``, ...)."""
    return json.dumps(jsonable(value), allow_nan=False, **kwargs)


def jsonable(value: Any) -> Any:
    """Convert numpy scalars/arrays and other leaves into JSON-friendly Python values (a
    non-finite float as its spelling, :data:`NONFINITE_SPELLINGS`).

    Plain values (exactly ``dict`` with ``str`` keys, ``list``, ``str``, ``int``, ``bool``,
    ``float``, None: all of a resolved config and most of a record) take a short path by exact
    type; anything else, subclasses included, goes through :func:`_jsonable_other` as before
    (the same result: ``tests/test_job_overhead.py``). The short path took the 44 records of
    ``paper_ci`` (7 kB each) from 0.49 to 0.07 ms of CPU each (issue 42 item 6)."""
    t = type(value)
    if t is dict:
        return {(k if type(k) is str else str(k)): jsonable(v) for k, v in value.items()}
    if t is str or t is int or t is bool or value is None:
        return value
    if t is float:
        return value if math.isfinite(value) else _float_leaf(value)
    if t is list:
        return [jsonable(v) for v in value]
    return _jsonable_other(value)


def _jsonable_other(value: Any) -> Any:
    """:func:`jsonable` of a value that is not plain (numpy, tuples, mappings, subclasses)."""
    if isinstance(value, Mapping):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, (np.bool_, bool)):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, (np.floating, float)):
        return _float_leaf(float(value))
    if value is None or isinstance(value, (str, int)):
        return value
    return str(value)
