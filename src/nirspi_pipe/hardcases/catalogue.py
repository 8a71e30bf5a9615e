"""The hard-case catalogue's cases: loaded from ``nirspi_pipe/data/hardcases.yaml`` (:func:`load_cases`),
their bounds evaluated (:func:`check_bounds`) and a run's record checked (:func:`record_problems`).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from importlib import resources
from typing import Any

import yaml

from nirspi_pipe.finite import drop_nonfinite

__all__ = ["BOUND", "Case", "Outcome", "check_bounds", "load_cases", "record_problems"]

BOUND = re.compile(r"^(.+?)\s*(<=|>=|==|<|>)\s*(.+)$")
_OPS: dict[str, Callable[[float, float], bool]] = {
    "<=": lambda a, b: a <= b,
    ">=": lambda a, b: a >= b,
    "==": lambda a, b: a == b,
    "<": lambda a, b: a < b,
    ">": lambda a, b: a > b,
}


@dataclass(frozen=True)
class Case:
    """One entry of the catalogue (see the module docstring for the fields)."""

    id: str
    what: str
    run: tuple[str, ...] | None = None
    call: str | None = None
    args: Mapping[str, Any] = field(default_factory=dict)
    expect: str | Mapping[str, str] = "ok"
    bounds: tuple[str, ...] = ()
    left_out: tuple[str, ...] = ()
    pending: str | None = None
    note: str | None = None
    group: str = ""

    @property
    def refused(self) -> str | None:
        return self.expect.get("refused") if isinstance(self.expect, Mapping) else None

    @property
    def failed(self) -> str | None:
        return self.expect.get("failed") if isinstance(self.expect, Mapping) else None


@dataclass
class Outcome:
    """What running one case gave: ``status`` (``ok``, ``refused``, ``failed``, ``error``), the
    measured value of each bound (None when it could not be evaluated) and the problems found
    (empty: the case holds)."""

    case: Case
    status: str = "ok"
    message: str = ""
    values: dict[str, Any] = field(default_factory=dict)
    measured: list[tuple[str, float | None, bool]] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    seconds: float = 0.0
    cpu_seconds: float = 0.0

    @property
    def holds(self) -> bool:
        return not self.problems


def catalogue_text() -> str:
    return resources.files("nirspi_pipe").joinpath("data/hardcases.yaml").read_text(encoding="utf-8")


def load_cases(text: str | None = None) -> list[Case]:
    """The catalogue's cases, in file order (``text``: the YAML, default the packaged file)."""
    doc = yaml.safe_load(catalogue_text() if text is None else text)
    cases: list[Case] = []
    for group in doc["groups"]:
        for raw in group["cases"]:
            unknown = set(raw) - {f for f in Case.__dataclass_fields__ if f != "group"}
            if unknown:
                raise ValueError(f"hardcases.yaml: case {raw.get('id')!r} has unknown fields {sorted(unknown)}")
            if ("run" in raw) == ("call" in raw):
                raise ValueError(f"hardcases.yaml: case {raw.get('id')!r} needs exactly one of run/call")
            cases.append(
                Case(
                    id=str(raw["id"]),
                    what=" ".join(str(raw["what"]).split()),
                    run=tuple(str(o) for o in raw["run"]) if "run" in raw else None,
                    call=raw.get("call"),
                    args=dict(raw.get("args") or {}),
                    expect=raw.get("expect", "ok"),
                    bounds=tuple(str(b) for b in raw.get("bounds") or ()),
                    left_out=tuple(raw.get("left_out") or ()),
                    pending=raw.get("pending"),
                    note=" ".join(str(raw["note"]).split()) if raw.get("note") else None,
                    group=str(group["name"]),
                )
            )
    ids = [c.id for c in cases]
    dup = sorted({i for i in ids if ids.count(i) > 1})
    if dup:
        raise ValueError(f"hardcases.yaml: duplicate ids {dup}")
    return cases


# ---- evaluating bounds ------------------------------------------------------------------------


class _Ns:
    """Attribute access over a nested mapping (``metrics.psnr``); a missing name raises KeyError."""

    def __init__(self, data: Mapping[str, Any], path: str) -> None:
        self._data, self._path = data, path

    def __getattr__(self, name: str) -> Any:
        if name not in self._data:
            raise KeyError(f"{self._path}.{name}")
        value = self._data[name]
        return _Ns(value, f"{self._path}.{name}") if isinstance(value, Mapping) else value


def _evaluate(expr: str, values: Mapping[str, Any]) -> float:
    names = {k: (_Ns(v, k) if isinstance(v, Mapping) else v) for k, v in values.items()}

    def get(dotted: str, default: float) -> Any:  # a value that may be absent: get('metrics.ssim', -1)
        node: Any = values
        for part in dotted.split("."):
            if not isinstance(node, Mapping) or part not in node:
                return default
            node = node[part]
        return node

    builtins = {"abs": abs, "min": min, "max": max, "inf": math.inf, "get": get}
    try:
        out = eval(expr, {"__builtins__": builtins}, names)  # the catalogue is the project's own file
    except NameError as exc:
        raise KeyError(str(exc).split("'")[1] if "'" in str(exc) else str(exc)) from None
    return float(out)


def check_bounds(case: Case, values: Mapping[str, Any]) -> tuple[list[tuple[str, float | None, bool]], list[str]]:
    """Each bound's measured value (its left-hand side) and whether it holds; problems found."""
    measured: list[tuple[str, float | None, bool]] = []
    problems: list[str] = []
    for bound in case.bounds:
        m = BOUND.match(bound)
        if m is None:
            raise ValueError(f"hardcases.yaml: case {case.id!r}: bound {bound!r} is not 'LHS OP RHS'")
        lhs, op, rhs = m.groups()
        try:
            a, b = _evaluate(lhs, values), _evaluate(rhs, values)
        except KeyError as exc:
            measured.append((bound, None, False))
            problems.append(f"bound {bound!r}: {exc.args[0]} is not in the result")
            continue
        ok = math.isfinite(a) and _OPS[op](a, b)
        measured.append((bound, a, ok))
        if not ok:
            problems.append(f"bound {bound!r} not met: measured {a:.6g}")
    return measured, problems


# ---- checks every successful run must pass ----------------------------------------------------


def record_problems(record: dict[str, Any], warning_lines: list[str], left_out: tuple[str, ...]) -> list[str]:
    """The checks of issue 40 item 1 on a run that succeeded (``record`` is changed: non-finite
    values are removed from it as the runner does)."""
    problems = [
        f"RuntimeWarning: {w.split(':', 1)[1].strip()[:160]}" for w in warning_lines if w.startswith("RuntimeWarning")
    ]
    for line in drop_nonfinite(record):
        key = line.split("=", 1)[0]
        if key not in left_out:
            problems.append(f"left out: {line[:200]}")
    for key, value in record.get("metrics", {}).items():
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            continue
        if not math.isfinite(value):
            problems.append(f"metrics.{key}={value} is not finite")
        elif "ssim" in key and not -1.0 <= value <= 1.0:
            problems.append(f"metrics.{key}={value} is outside [-1, 1]")
        elif "rmse" in key and value < 0:
            problems.append(f"metrics.{key}={value} is negative")
    return problems
