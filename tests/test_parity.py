"""One parity harness (issue 27): every alternative back end of every stage family declared in
:mod:`nirspi_pipe.backends` against the family's reference, on the family's shared fixtures, within
the stated tolerances. A back end that cannot run here is skipped with its reason; the torch cases
carry the marker ``torch`` (deselected unless ``pytest -m torch``)."""

from __future__ import annotations

import warnings
from typing import Any

import pytest

from nirspi_pipe.backends.harness import Backend, Family, Tolerance, violations
from nirspi_pipe.backends.registry import REGISTRY


def _cases() -> list[Any]:
    out = []
    for family in REGISTRY.values():
        for alt in family.alternatives:
            marks = [getattr(pytest.mark, m) for m in alt.marks]
            for fixture in family.fixture_names:
                out.append(
                    pytest.param(family.name, alt.name, fixture, marks=marks, id=f"{family.name}-{alt.name}-{fixture}")
                )
    return out


_FIXTURES: dict[tuple[str, str], Any] = {}
_REFERENCE: dict[tuple[str, str], Any] = {}


def _quiet(backend: Backend, fixture: Any) -> Any:
    with warnings.catch_warnings():  # e.g. a remesher's notes on the mesh: not what is compared here
        warnings.simplefilter("ignore")
        return backend.run(fixture)


def _skip_unless_available(backend: Backend) -> None:
    why = backend.unavailable()
    if why is not None:
        pytest.skip(f"{backend.name}: {why}")


@pytest.mark.parametrize(("family_name", "alternative", "fixture_name"), _cases())
def test_alternative_agrees_with_reference(family_name: str, alternative: str, fixture_name: str) -> None:
    family = REGISTRY[family_name]
    alt = next(b for b in family.alternatives if b.name == alternative)
    _skip_unless_available(alt)
    _skip_unless_available(family.reference)
    key = (family_name, fixture_name)
    if key not in _FIXTURES:  # built and solved by the reference once for all alternatives
        _FIXTURES[key] = family.make_fixture(fixture_name)
        _REFERENCE[key] = _quiet(family.reference, _FIXTURES[key])
    fixture = _FIXTURES[key]
    bad = violations(family, fixture, _REFERENCE[key], _quiet(alt, fixture))
    assert not bad, f"{family_name}: {alternative} vs {family.reference.name} on {fixture_name}: " + "; ".join(bad)


def test_every_family_declares_what_the_harness_needs() -> None:
    for name, family in REGISTRY.items():
        assert family.name == name and family.alternatives and family.fixture_names
        names = [family.reference.name] + [b.name for b in family.alternatives]
        assert len(set(names)) == len(names), f"{name}: back-end names repeat"
        for key, tol in family.tolerances.items():
            assert tol.bound >= 0 and len(tol.source) > 20, f"{name}.{key}: a bound needs its source"


def test_violations_catches_a_bound_exceeded_nan_and_undeclared_measures() -> None:
    """The harness can fail: a discrepancy over its bound, a NaN, a measure without a bound and a
    bound without a measure are each reported."""
    got: dict[str, float] = {}
    fake = Family(
        name="fake",
        reference=Backend("a", lambda x: x, lambda: None),
        alternatives=(Backend("b", lambda x: x, lambda: None),),
        fixture_names=("one",),
        make_fixture=lambda name: name,
        compare=lambda fixture, a, b: dict(got),
        tolerances={"err": Tolerance(1e-9, "stated for this test only")},
    )
    got.update(err=1e-10)
    assert violations(fake, None, None, None) == []
    got.update(err=2e-9)
    assert violations(fake, None, None, None) == ["err = 2e-09 > 1e-09 (stated for this test only)"]
    got.update(err=float("nan"))
    assert len(violations(fake, None, None, None)) == 1
    got.clear()
    got.update(other=0.0)
    assert violations(fake, None, None, None) == ["other: no stated tolerance", "err: not measured by compare"]
