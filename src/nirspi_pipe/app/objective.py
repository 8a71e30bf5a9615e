"""What a sweep optimises: the ``objective`` config key, its directions, and the Pareto front.

``objective`` names record keys as the columns of ``results.parquet`` name them
(``metrics.psnr``, ``timings_ms.solver``, ``derived.snr_db``, ``info.solver.iterations``); a job
returns their values to the sweeper (:func:`objective_values`), and the directions come from the
sweeper's config (``hydra.sweeper.direction``: Optuna's, or the ``nirspi`` grid sweeper's, which
uses them only to mark the front). A failed job, or one whose record lacks a named key or holds a
non-finite value there, returns ``None``: hydra-optuna-sweeper 1.3 tells Optuna such a trial
``FAIL`` and goes on (with Optuna 2.10 a NaN would not do: ``Study.tell`` raises on it, and the
sweeper's own fallback then raises again). :func:`pareto_mask` marks the rows no other row
beats in every objective.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

__all__ = [
    "ObjectiveError",
    "directions_of",
    "objective_names",
    "objective_values",
    "pareto_mask",
]

#: The record sections an objective may name, as ``results.parquet``'s column prefixes.
SECTIONS = ("metrics", "timings_ms", "derived", "info")
_NAME = re.compile(r"^(?:" + "|".join(SECTIONS) + r")(?:\.[A-Za-z_][A-Za-z0-9_]*)+$")
DIRECTIONS = ("minimize", "maximize")


class ObjectiveError(ValueError):
    """``objective`` or ``hydra.sweeper.direction`` is not usable: one line naming the key."""


def objective_names(value: Any) -> list[str]:
    """The record keys ``objective`` names: ``[]`` for null, a list for one name or several.
    Raises :class:`ObjectiveError` (one line, the allowed form) for anything else."""
    if value is None:
        return []
    names = [value] if isinstance(value, str) else value
    allowed = f"allowed: a record key ({', '.join(s + '.<name>' for s in SECTIONS)}) or a list of them"
    if not isinstance(names, Sequence) or isinstance(names, (str, bytes)) or not names:
        return _bad(f"objective={value!r} is not allowed; {allowed}")
    for name in names:
        if not isinstance(name, str) or not _NAME.match(name):
            return _bad(f"objective: {name!r} is not allowed; {allowed}")
    if len(set(names)) != len(names):
        return _bad(f"objective={list(names)!r} names a key twice; {allowed}, each once")
    return list(names)


def _bad(message: str) -> list[str]:
    raise ObjectiveError(message)


def directions_of(value: Any, n_objectives: int) -> list[str]:
    """``hydra.sweeper.direction`` as a list of ``minimize``/``maximize``, one per objective
    (``[]`` when it is null). Raises :class:`ObjectiveError` for a wrong word or count."""
    if value is None:
        return []
    raw = [value] if isinstance(value, str) or not isinstance(value, Sequence) else list(value)
    out = [str(getattr(d, "name", d)) for d in raw]  # Optuna's config may hold its Direction enum
    for d in out:
        if d not in DIRECTIONS:
            raise ObjectiveError(f"hydra.sweeper.direction: {d!r} is not allowed; allowed: minimize or maximize")
    if len(out) != n_objectives:
        raise ObjectiveError(
            f"hydra.sweeper.direction has {len(out)} direction(s) for {n_objectives} objective(s) "
            f"(objective); allowed: one direction per objective"
        )
    return out


def _lookup(record: Mapping[str, Any], name: str) -> Any:
    node: Any = record
    for part in name.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return None
        node = node[part]
    return node


def objective_values(record: Mapping[str, Any]) -> float | list[float] | None:
    """The values of the objective the record's config names: a float for one key, a list for
    several, ``None`` when the job failed or a value is missing or not a finite number (a failed
    trial for the Optuna sweeper). Raises :class:`ObjectiveError` when ``objective`` is unset or
    malformed (the caller returns the record itself for sweeps without one)."""
    names = objective_names((record.get("config") or {}).get("objective"))
    if not names:
        raise ObjectiveError("objective is not set")
    if (record.get("meta") or {}).get("status") != "ok":
        return None
    values = []
    for name in names:
        value = _lookup(record, name)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            return None
        values.append(float(value))
    return values[0] if len(values) == 1 else values


def pareto_mask(values: np.ndarray, directions: Sequence[str]) -> np.ndarray:
    """Boolean mask of the non-dominated rows of ``values`` (rows × objectives): no other row is
    at least as good in every objective and strictly better in one. Rows with a non-finite value
    are never on the front; identical rows are all on it when one is."""
    v = np.asarray(values, dtype=float)
    if v.ndim != 2 or v.shape[1] != len(directions):
        raise ValueError(f"values of shape {v.shape} for {len(directions)} directions")
    sign = np.array([1.0 if d == "minimize" else -1.0 for d in directions])
    cost = v * sign  # every objective minimised
    finite = np.isfinite(cost).all(axis=1)
    mask = np.zeros(len(v), dtype=bool)
    pts = cost[finite]
    idx = np.flatnonzero(finite)
    for i, p in zip(idx, pts):
        dominated = np.any(np.all(pts <= p, axis=1) & np.any(pts < p, axis=1))
        mask[i] = not dominated
    return mask
