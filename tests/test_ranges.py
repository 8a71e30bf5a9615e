"""Declarative ranges (issue 42, item 2): one function checks every stage field's declared range,
and the error names the key and the allowed values in one line."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated

import pytest
from hypothesis import given
from hypothesis import strategies as st

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.ranges import OneOf, Range, check_ranges, describe, field_ranges


@dataclass(frozen=True)
class _Probe:
    a: Annotated[float, Range(0.0, 1.0, "a fraction")] = 0.5
    b: Annotated[float, Range(0.0, None, "a time in s", lo_open=True)] = 1.0
    c: Annotated[float | None, Range(None, 5.0, "a level", hi_open=True)] = None
    n: Annotated[int, Range(1, 64, "a count", integer=True)] = 2
    name: Annotated[str, OneOf(("x", "y"))] = "x"
    free: float = 3.0

    def __post_init__(self) -> None:
        check_ranges(self)


def test_the_declared_ranges_are_read_from_the_annotations() -> None:
    assert [n for n, *_ in field_ranges(_Probe)] == ["a", "b", "c", "n", "name"]
    assert list(describe(_Probe)) == [
        "a: a fraction in [0, 1]",
        "b: a time in s > 0",
        "c: a level < 5, or null",
        "n: a count in [1, 64]",
        "name: one of ['x', 'y']",
    ]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"a": 1.5}, "a=1.5 is not allowed; allowed: a fraction in [0, 1]"),
        ({"a": math.nan}, "a=nan is not allowed; allowed: a fraction in [0, 1]"),
        ({"b": 0.0}, "b=0.0 is not allowed; allowed: a time in s > 0"),
        ({"b": math.inf}, "b=inf is not allowed; allowed: a time in s > 0"),
        ({"c": 5.0}, "c=5.0 is not allowed; allowed: a level < 5, or null"),
        ({"n": 2.5}, "n=2.5 is not allowed; allowed: a count in [1, 64]"),
        ({"a": True}, "a=True is not allowed; allowed: a fraction in [0, 1]"),
        ({"name": "z"}, "name='z' is not allowed; allowed: one of ['x', 'y']"),
    ],
)
def test_a_value_out_of_range_is_one_line_naming_the_key(kwargs: dict, message: str) -> None:
    with pytest.raises(ConfigError) as err:
        _Probe(**kwargs)
    assert str(err.value) == message and err.value.key == next(iter(kwargs))


def test_none_and_undeclared_fields_pass() -> None:
    assert _Probe(c=None, free=-1e300).free == -1e300


@given(
    lo=st.floats(-1e6, 1e6),
    width=st.floats(0, 1e6),
    lo_open=st.booleans(),
    hi_open=st.booleans(),
    v=st.floats(allow_nan=True, allow_infinity=True),
)
def test_contains_is_the_interval(lo: float, width: float, lo_open: bool, hi_open: bool, v: float) -> None:
    hi = lo + width
    r = Range(lo, hi, lo_open=lo_open, hi_open=hi_open)
    inside = math.isfinite(v) and (v > lo if lo_open else v >= lo) and (v < hi if hi_open else v <= hi)
    assert r.contains(v) == inside


def test_background_light_declares_its_ranges() -> None:
    from nirspi_pipe.physics.light import Background

    keys = {n for n, *_ in field_ranges(Background)}
    assert {"klux", "mains_hz", "surround_reflectance", "wander_time_s"} <= set(keys)
    with pytest.raises(
        ConfigError, match=r"^klux=150\.0 is not allowed; allowed: an illuminance in kLux in \[0, 100\]$"
    ):
        Background(klux=150.0)


def test_docs_ranges_is_what_the_declarations_say() -> None:
    """docs/ranges.md is regenerated from the declarations (python -m nirspi_pipe.rangedocs --write-docs)."""
    from pathlib import Path

    from nirspi_pipe.rangedocs import markdown

    docs = Path(__file__).resolve().parents[1] / "docs" / "ranges.md"
    assert docs.read_text(encoding="utf-8") == markdown(), "run: python -m nirspi_pipe.rangedocs --write-docs"


def test_rangedocs_refuses_an_unknown_group_in_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    from nirspi_pipe.rangedocs import main

    assert main(["fgo"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown group 'fgo'" in err and "fog" in err


def test_the_stage_error_prints_what_the_docs_list() -> None:
    from nirspi_pipe.physics.fog import MeasuredFog

    with pytest.raises(ConfigError) as err:
        MeasuredFog(extent_mm=0.0)
    line = next(ln for ln in describe(MeasuredFog) if ln.startswith("extent_mm:"))
    assert str(err.value).endswith("allowed: " + line.split(": ", 1)[1])
    assert MeasuredFog(extent_mm=math.inf).extent_mm == math.inf


def test_a_whole_float_in_an_integer_field_becomes_an_int() -> None:
    p = _Probe(n=4.0)  # type: ignore[arg-type]
    assert p.n == 4 and type(p.n) is int


@dataclass(frozen=True)
class _Keyed:
    rel: Annotated[float, Range(-0.9, 1.0, "a relative change", key="led_droop_rel")] = 0.0

    def __post_init__(self) -> None:
        check_ranges(self)


def test_a_range_with_its_own_key_names_the_key_the_user_set() -> None:
    """An effect built from ``source.effects.led_droop_rel`` keeps it as ``rel``: the error and the
    docs name the config key, not the field."""
    with pytest.raises(ConfigError) as exc:
        _Keyed(rel=2.0)
    assert exc.value.key == "led_droop_rel" and "[-0.9, 1]" in str(exc.value)
    assert list(describe(_Keyed)) == ["led_droop_rel: a relative change in [-0.9, 1]"]


@given(st.floats(allow_nan=True, allow_infinity=True))
def test_check_value_agrees_with_the_field_check(x: float) -> None:
    """A function's argument checked against the same declaration refuses exactly what the
    dataclass field refuses, with the same words."""
    from nirspi_pipe.ranges import check_value

    spec = field_ranges(_Keyed)[0][1]
    assert isinstance(spec, Range)
    try:
        _Keyed(rel=x)
        field_error = None
    except ConfigError as exc:
        field_error = str(exc)
    try:
        check_value(x, spec)
        value_error = None
    except ConfigError as exc:
        value_error = str(exc)
    assert field_error == value_error
