"""One hard case run and checked (:func:`run_case`), and the command line
``python -m nirspi_pipe.hardcases`` (:func:`main`).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from nirspi_pipe.errors import ConfigError, NirspiError
from nirspi_pipe.hardcases.catalogue import Case, Outcome, check_bounds, load_cases, record_problems
from nirspi_pipe.hardcases.probes import PROBES, caught_warnings, record_values, run
from nirspi_pipe.hardcases.render import docs_stamp, fmt, lhs, render
from nirspi_pipe.readme_numbers import find_clone

__all__ = ["main", "run_case"]

_PROG = "python -m nirspi_pipe.hardcases"


# ---- running one case -------------------------------------------------------------------------


def _one_line(exc: BaseException) -> str:
    return str(exc)


def run_case(case: Case) -> Outcome:
    """Run ``case`` and check it: the expected outcome, the standard checks, its bounds."""
    out = Outcome(case)
    start, cpu = time.perf_counter(), time.process_time()
    with caught_warnings() as caught:
        try:
            if case.run is not None:
                result = run(list(case.run))
                out.values = record_values(result)
                if case.refused is None and case.failed is None:
                    out.problems += record_problems(out.values["record"], list(result.warnings), case.left_out)
            else:
                if case.call not in PROBES:
                    raise ValueError(f"hardcases.yaml: case {case.id!r}: unknown call {case.call!r}")
                out.values = PROBES[str(case.call)](case.args)
        except (ConfigError, ValueError) as exc:  # BadOverrides and ConfigError are ValueErrors
            out.status, out.message = "refused", _one_line(exc)
        except NirspiError as exc:
            out.status, out.message = "failed", _one_line(exc)
        except Exception as exc:  # noqa: BLE001 - a crash is what the catalogue looks for
            out.status, out.message = "error", f"{type(exc).__name__}: {exc}"
    out.seconds, out.cpu_seconds = time.perf_counter() - start, time.process_time() - cpu
    if case.call is not None and case.refused is None and case.failed is None:
        out.problems += [
            f"RuntimeWarning: {str(w.message)[:160]}" for w in caught if issubclass(w.category, RuntimeWarning)
        ]
    _check_expectation(out)
    if out.status == "ok" and case.refused is None and case.failed is None:
        measured, problems = check_bounds(case, out.values)
        out.measured, out.problems = measured, out.problems + problems
    return out


def _check_expectation(out: Outcome) -> None:
    case, msg = out.case, out.message
    if "\n" in msg:
        out.problems.append(f"message has {msg.count(chr(10)) + 1} lines: {msg[:200]!r}")
    if case.refused is not None:
        if out.status != "refused":
            out.problems.append(f"expected refused naming {case.refused}, got {out.status}: {msg[:200]}")
        elif not msg.startswith((f"{case.refused}=", f"{case.refused} ")):
            out.problems.append(f"refused, but the line does not start with {case.refused}: {msg[:200]}")
    elif case.failed is not None:
        if out.status != "failed":
            out.problems.append(f"expected a one-line failure holding {case.failed!r}, got {out.status}: {msg[:200]}")
        elif case.failed not in msg:
            out.problems.append(f"failed without {case.failed!r}: {msg[:200]}")
    elif out.status != "ok":
        out.problems.append(f"expected ok, got {out.status}: {msg[:300]}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog=_PROG, description="Run the hard-case catalogue (issue 40).")
    parser.add_argument("ids", nargs="*", help="only these case ids")
    parser.add_argument("--write-docs", action="store_true", help="write docs/hardcases.md (every case)")
    parser.add_argument("--out", type=Path, default=None, help="default: docs/hardcases.md of this clone")
    ns = parser.parse_args(argv)
    refusal = _docs_target(ns)
    cases = load_cases()
    if refusal is None and ns.ids:
        unknown = sorted(set(ns.ids) - {c.id for c in cases})
        refusal = f"unknown case ids {unknown}" if unknown else None
        cases = [c for c in cases if c.id in ns.ids]
    if refusal is not None:
        print(f"{_PROG}: {refusal}", file=sys.stderr)
        return 2
    outcomes = []
    for case in cases:
        o = run_case(case)
        outcomes.append(o)
        print(_progress_line(o))
    if ns.write_docs:
        _write_docs(outcomes, ns.out)
    return 0 if all(o.holds or o.case.pending for o in outcomes) else 1


def _docs_target(ns: argparse.Namespace) -> str | None:
    """Why ``--write-docs`` cannot run as asked (None when it can, or is not asked); sets
    ``ns.out`` to docs/hardcases.md of this clone when it is not given. Checked first: the run
    takes minutes."""
    if ns.write_docs and ns.ids:
        return "--write-docs runs every case; give no ids"
    if ns.write_docs and ns.out is None:
        clone = find_clone()
        if clone is None:
            return "not in a clone of nirspi-pipe; give --out FILE"
        ns.out = clone / "docs" / "hardcases.md"
    return None


def _progress_line(o: Outcome) -> str:
    """One case's line: its status, time, id and measured values (or message), its problems."""
    tag = "holds" if o.holds else ("pending" if o.case.pending else "FAILS")
    got = ", ".join(f"{lhs(b)}={fmt(v)}" for b, v, _ in o.measured) or o.message[:120]
    return f"{tag:7s} {o.seconds:6.2f}s {o.cpu_seconds:6.2f}cpu {o.case.id}: {got}" + (
        "" if o.holds else f"  [{'; '.join(o.problems)[:300]}]"
    )


def _write_docs(outcomes: list[Outcome], out: Path) -> None:
    """Write docs/hardcases.md (:func:`~nirspi_pipe.hardcases.render.render`) with the run's stamp."""
    wall, cpu = sum(o.seconds for o in outcomes), sum(o.cpu_seconds for o in outcomes)
    load = " / ".join(f"{x:.1f}" for x in os.getloadavg())
    stamp = (
        f"{docs_stamp()} The cases took {wall:.0f} s ({cpu:.0f} s of CPU) in one process; load average {load} after."
    )
    out.write_text(render(outcomes, stamp), encoding="utf-8")
    print(f"wrote {out}")
