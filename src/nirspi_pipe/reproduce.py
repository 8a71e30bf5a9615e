"""Check regenerated tables against committed references, with stated tolerances.

``python -m nirspi_pipe.reproduce check SWEEP`` compares every ``SWEEP/tables/<name>.csv`` that
has a reference in ``experiments/reference/ci/<name>.csv``; ``update SWEEP`` rewrites the
references from a sweep (after a deliberate change of the model, say why in the commit).

Tolerances live in ``experiments/reference/ci/tolerances.yaml``::

    default: {rtol: 1.0e-6, atol: 1.0e-9}
    table2:  {rtol: 1.0e-3}

Columns that measure time (names containing ``time``, ``ms``, ``_s`` or ``per_s``) are never
compared: timings are not reproducible, everything else is.
"""

from __future__ import annotations

import argparse
import re
import shutil
import sys
from importlib import resources
from pathlib import Path

import numpy as np
import pandas as pd

from nirspi_pipe.errors import plain_value

__all__ = ["compare_tables", "reference_dir", "check", "update", "is_timing_column"]

_TIMING = re.compile(r"(time|(^|[_.])ms($|[_.])|_s$|per_s|wall)", re.IGNORECASE)


def is_timing_column(name: str) -> bool:
    """True for columns that hold timings (excluded from reproduction checks)."""
    return bool(_TIMING.search(str(name)))


def reference_dir() -> Path:
    """The installed ``experiments/reference/ci`` folder."""
    return Path(str(resources.files("nirspi_pipe.experiments"))) / "reference" / "ci"


def _tolerances(ref_dir: Path, name: str) -> tuple[float, float]:
    from omegaconf import OmegaConf  # start-up: loads omegaconf, yaml (47 ms here)

    tol = {"rtol": 1e-6, "atol": 1e-9}
    path = ref_dir / "tolerances.yaml"
    if path.is_file():
        spec = OmegaConf.to_container(OmegaConf.load(path))
        if not isinstance(spec, dict):
            raise ValueError(f"{path}: must be a mapping of table names to {{rtol, atol}}")
        tol.update(spec.get("default", {}) or {})
        tol.update(spec.get(name, {}) or {})
    return float(tol["rtol"]), float(tol["atol"])


def compare_tables(new: pd.DataFrame, ref: pd.DataFrame, rtol: float, atol: float) -> list[str]:
    """Differences between two tables, as readable lines (empty when they agree).

    Shapes and non-timing column names must match; numeric cells must satisfy
    ``|new − ref| ≤ atol + rtol·|ref|`` (NaN equals NaN); other cells must be equal.
    """
    problems: list[str] = []
    cols = [c for c in ref.columns if not is_timing_column(c)]
    missing = [c for c in cols if c not in new.columns]
    if missing:
        problems.append(f"missing columns {missing}")
    if len(new) != len(ref):
        problems.append(f"{len(new)} rows, reference has {len(ref)}")
        return problems
    for c in cols:
        if c in missing:
            continue
        a, b = new[c].reset_index(drop=True), ref[c].reset_index(drop=True)
        na, nb = pd.to_numeric(a, errors="coerce"), pd.to_numeric(b, errors="coerce")
        # numeric when every non-missing cell of both is a number (an all-NaN column is numeric:
        # with pandas 3, astype(str) keeps NaN and NaN != NaN would fail the string comparison)
        if nb.notna().sum() == b.notna().sum() and na.notna().sum() == a.notna().sum():
            av, bv = na.to_numpy(float), nb.to_numpy(float)
            ok = np.isclose(av, bv, rtol=rtol, atol=atol, equal_nan=True)
            for i in np.flatnonzero(~ok):
                problems.append(f"row {i} column {c}: {av[i]:.6g} vs reference {bv[i]:.6g}")
        else:
            for i in np.flatnonzero((a.astype(str) != b.astype(str)).to_numpy()):
                # plain values: 0.0, not np.float64(0.0) (issue 34)
                problems.append(f"row {i} column {c}: {plain_value(a[i])!r} vs reference {plain_value(b[i])!r}")
    return problems


def check(sweep: Path, ref_dir: Path | None = None) -> dict[str, list[str]]:
    """Compare each table of ``sweep/tables`` that has a reference. ``{name: problems}``."""
    ref_dir = ref_dir or reference_dir()
    results: dict[str, list[str]] = {}
    for ref_path in sorted(ref_dir.glob("*.csv")):
        name = ref_path.stem
        new_path = sweep / "tables" / f"{name}.csv"
        if not new_path.is_file():
            results[name] = [f"{new_path} was not produced"]
            continue
        rtol, atol = _tolerances(ref_dir, name)
        results[name] = compare_tables(pd.read_csv(new_path), pd.read_csv(ref_path), rtol, atol)
    return results


def update(sweep: Path, ref_dir: Path) -> list[str]:
    """Copy the tables of ``sweep`` that already have references (or all, if none do)."""
    ref_dir.mkdir(parents=True, exist_ok=True)
    names = [p.stem for p in ref_dir.glob("*.csv")] or [p.stem for p in (sweep / "tables").glob("*.csv")]
    for name in names:
        shutil.copyfile(sweep / "tables" / f"{name}.csv", ref_dir / f"{name}.csv")
    return names


def main(argv: list[str] | None = None) -> int:
    """``python -m nirspi_pipe.reproduce {check,update} SWEEP [--reference DIR]``."""
    parser = argparse.ArgumentParser(
        prog="python -m nirspi_pipe.reproduce",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("action", choices=["check", "update"])
    parser.add_argument("sweep", type=Path)
    parser.add_argument(
        "--reference",
        type=Path,
        default=None,
        help="reference folder (default: the installed experiments/reference/ci; "
        "for update, pass the repository's experiments/reference/ci)",
    )
    ns = parser.parse_args(argv)
    if ns.action == "update":
        target = ns.reference or Path("experiments/reference/ci")
        print("updated:", ", ".join(update(ns.sweep, target)))
        return 0
    results = check(ns.sweep, ns.reference)
    bad = 0
    for name, problems in results.items():
        print(f"{name}: {'ok' if not problems else f'{len(problems)} differences'}")
        for p in problems[:20]:
            print(f"  {p}")
        bad += bool(problems)
    return 1 if bad or not results else 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
