"""The parity harness's types: a back end, a tolerance with its source, a family of back ends of one
stage, and the check of one comparison against its bounds (:func:`violations`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

__all__ = ["Backend", "Family", "Tolerance", "violations"]


@dataclass(frozen=True)
class Backend:
    """One implementation of a stage.

    Attributes:
        name: short id (``numpy``, ``opencl``, ...), used in test ids.
        run: fixture → output (the output type is the family's).
        unavailable: None when the back end can run here, else the one-line reason it cannot.
        marks: pytest markers its parity cases carry (``torch``: deselected unless ``-m torch``).
    """

    name: str
    run: Callable[[Any], Any]
    unavailable: Callable[[], str | None]
    marks: tuple[str, ...] = ()

    def available(self) -> bool:
        """True when :attr:`unavailable` gives no reason."""
        return self.unavailable() is None


@dataclass(frozen=True)
class Tolerance:
    """Upper bound of one discrepancy (``compare``'s value must be ``<= bound``) and its source:
    what it was measured on and how, or which design requirement it states."""

    bound: float
    source: str


@dataclass(frozen=True)
class Family:
    """The back ends of one stage.

    Attributes:
        name: the stage family (``sfs``, ``omp``, ``fsrcnn``, ``remesh``).
        reference: the back end the others must agree with.
        alternatives: the other back ends.
        fixture_names: ids of the shared fixtures.
        make_fixture: fixture id → the input every back end's ``run`` takes.
        compare: ``(fixture, reference output, alternative output)`` → discrepancy by name; its
            keys are exactly those of ``tolerances``.
        tolerances: bound on each discrepancy.
    """

    name: str
    reference: Backend
    alternatives: tuple[Backend, ...]
    fixture_names: tuple[str, ...]
    make_fixture: Callable[[str], Any]
    compare: Callable[[Any, Any, Any], dict[str, float]]
    tolerances: Mapping[str, Tolerance] = field(default_factory=dict)


def violations(family: Family, fixture: Any, reference_out: Any, alternative_out: Any) -> list[str]:
    """Each discrepancy above its bound, as ``name = value > bound (source)``; empty when all hold.
    A discrepancy that ``compare`` gives without a bound (or a bound it does not give) is reported
    too, so that the two never drift apart."""
    got = family.compare(fixture, reference_out, alternative_out)
    out = [f"{k}: no stated tolerance" for k in sorted(set(got) - set(family.tolerances))]
    out += [f"{k}: not measured by compare" for k in sorted(set(family.tolerances) - set(got))]
    for key, tol in family.tolerances.items():
        if key in got and not got[key] <= tol.bound:  # NaN fails
            out.append(f"{key} = {got[key]:.3g} > {tol.bound:g} ({tol.source})")
    return out
