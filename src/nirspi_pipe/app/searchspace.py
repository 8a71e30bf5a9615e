"""The Optuna study's search space and objectives, pure functions (:mod:`nirspi_pipe.app.study`
drives the study): a swept key as Optuna samples it (:class:`Dimension`, :func:`dimension_of`,
Hydra's sweep syntax as hydra-optuna-sweeper reads it), the objective keys checked against a
record (:func:`check_objective_keys`), each objective's median over a trial's repeats
(:func:`median_values`) and a repeat's folder key (:func:`repeat_key`).
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from nirspi_pipe.app.objective import SECTIONS
from nirspi_pipe.jobkey import config_hash

__all__ = [
    "Dimension",
    "as_override_value",
    "check_objective_keys",
    "dimension_of",
    "median_values",
    "record_keys",
    "repeat_key",
]


# -- the search space ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Dimension:
    """One swept key as Optuna samples it (Hydra's sweep syntax, as hydra-optuna-sweeper reads it):
    ``choice(...)`` and a shuffled ``range`` are categorical; ``range(a,b,s)`` an integer (or a
    float on a grid) from ``a`` up to below ``b``; ``interval(a,b)`` a float (an integer when both
    ends are), log-uniform with ``tag(log, ...)``."""

    name: str
    kind: str  # "categorical", "int" or "float"
    choices: tuple[Any, ...] = ()
    low: float = 0.0
    high: float = 0.0
    step: float | None = None
    log: bool = False

    def suggest(self, trial: Any) -> Any:
        """The trial's value (Optuna's ``Trial.suggest_*``)."""
        if self.kind == "categorical":
            return trial.suggest_categorical(self.name, list(self.choices))
        if self.kind == "int":
            return trial.suggest_int(self.name, int(self.low), int(self.high), step=int(self.step or 1), log=self.log)
        return trial.suggest_float(self.name, self.low, self.high, step=self.step, log=self.log)

    def first(self) -> Any:
        """The space's first value: the first choice, or the low end."""
        if self.kind == "categorical":
            return self.choices[0]
        return int(self.low) if self.kind == "int" else self.low


def dimension_of(override: Any) -> Dimension | None:
    """The :class:`Dimension` of a parsed Hydra override, or None when it is not a sweep.
    Raises ``ValueError`` (one line) for a sweep Optuna cannot sample."""
    # start-up: Hydra's override grammar, only for a sweep
    from hydra.core.override_parser.types import Transformer

    if not override.is_sweep_override():
        return None
    name = override.get_key_element()
    value = override.value()
    if override.is_choice_sweep() or (override.is_range_sweep() and value.shuffle):
        choices = tuple(override.sweep_iterator(transformer=Transformer.encode))
        for c in choices:
            if not isinstance(c, (str, int, float, bool, type(None))):
                raise ValueError(f"{name}: a choice of Optuna is a string, number, boolean or null, not {c!r}")
        return Dimension(name, "categorical", choices=choices)
    if override.is_range_sweep():
        start, stop, step = value.start, value.stop, value.step
        if any(isinstance(v, float) for v in (start, stop, step)):
            n = math.ceil((stop - start) / step) - 1
            if n < 0:
                raise ValueError(f"{name}: range({start},{stop},{step}) is empty")
            return Dimension(name, "float", low=float(start), high=float(start + n * step), step=float(step))
        n = len(range(int(start), int(stop), int(step)))
        if n == 0 or step < 0:
            raise ValueError(f"{name}: range({start},{stop},{step}) is empty or descending")
        return Dimension(name, "int", low=int(start), high=int(start + (n - 1) * step), step=int(step))
    if override.is_interval_sweep():
        log = "log" in value.tags
        is_int = isinstance(value.start, int) and isinstance(value.end, int)
        if not value.start < value.end or (log and value.start <= 0):
            raise ValueError(
                f"{name}: interval({value.start},{value.end}) is empty" + (" or not positive" if log else "")
            )
        return Dimension(name, "int" if is_int else "float", low=value.start, high=value.end, log=log)
    raise ValueError(f"{name}: {override.input_line} is not a sweep Optuna samples (choice, range, interval)")


def as_override_value(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    return str(value)


# -- objectives against records -----------------------------------------------------------------


def record_keys(record: Mapping[str, Any], sections: Sequence[str]) -> list[str]:
    """The dotted keys of a record's numeric leaves in ``sections`` (``metrics.psnr``, ...)."""
    out: list[str] = []

    def walk(prefix: str, node: Any) -> None:
        if isinstance(node, Mapping):
            for k, v in node.items():
                walk(f"{prefix}.{k}", v)
        elif isinstance(node, (int, float)) and not isinstance(node, bool):
            out.append(prefix)

    for section in sections:
        walk(section, record.get(section))
    return out


def check_objective_keys(names: Sequence[str], record: Mapping[str, Any]) -> str | None:
    """One line naming every objective key that ``record`` (an ``ok`` record of this sweep) lacks,
    with the nearest keys it has, or None when it has them all."""
    keys = record_keys(record, SECTIONS)
    missing = [n for n in names if n not in keys]
    if not missing:
        return None
    parts = []
    for name in missing:
        near = difflib.get_close_matches(name, keys, n=3, cutoff=0.6)
        parts.append(f"{name!r}" + (f" (did you mean {', '.join(near)}?)" if near else ""))
    section_keys = sorted({k for k in keys if k.split(".")[0] in {m.split(".")[0] for m in missing}})
    shown = ", ".join(section_keys[:12]) + (", ..." if len(section_keys) > 12 else "")
    return (
        f"objective: {'; '.join(parts)} {'is' if len(missing) == 1 else 'are'} not a key of this sweep's records; "
        f"allowed: {shown or 'keys of ' + ', '.join(SECTIONS)} (checked on one job's record before any trial)"
    )


def _value_of(record: Mapping[str, Any], name: str) -> float | None:
    node: Any = record
    for part in name.split("."):
        if not isinstance(node, Mapping) or part not in node:
            return None
        node = node[part]
    if isinstance(node, bool) or not isinstance(node, (int, float)) or not math.isfinite(node):
        return None
    return float(node)


def median_values(records: Sequence[Mapping[str, Any] | None], names: Sequence[str]) -> list[float] | None:
    """Each objective's median over a trial's repeats, or None (a failed trial) when any repeat
    failed or lacks a finite value."""
    rows = []
    for rec in records:
        if rec is None or (rec.get("meta") or {}).get("status") != "ok":
            return None
        row = [_value_of(rec, n) for n in names]
        if any(v is None for v in row):
            return None
        rows.append(row)
    if not rows:
        return None
    return [float(v) for v in np.median(np.asarray(rows, dtype=float), axis=0)]


def repeat_key(key: str, repeat: int) -> str:
    """The folder key of repeat ``repeat`` of the job keyed ``key`` (repeat 0 is ``key``)."""
    return key if repeat == 0 else config_hash({"repeat_of": key, "repeat": repeat})
