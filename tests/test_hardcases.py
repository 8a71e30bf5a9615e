"""The hard-case catalogue (issue 40 item 1): every case of nirspi_pipe/data/hardcases.yaml, in
process, one test per case id. A case marked ``pending`` is expected to fail (strict xfail naming
who fixes it), so that the lead sees the day it starts to hold. docs/hardcases.md shows the
measured value of every bound (``python -m nirspi_pipe.hardcases --write-docs``)."""

from __future__ import annotations

import numpy as np
import pytest

from nirspi_pipe.hardcases.catalogue import Case, Outcome, check_bounds, load_cases, record_problems
from nirspi_pipe.hardcases.check import run_case

CASES = load_cases()


def _param(case: Case) -> object:
    marks = [pytest.mark.xfail(strict=True, reason=case.pending)] if case.pending else []
    return pytest.param(case, id=case.id, marks=marks)


@pytest.mark.parametrize("case", [_param(c) for c in CASES])
def test_hard_case(case: Case) -> None:
    outcome = run_case(case)
    assert outcome.holds, f"{case.id}: " + "; ".join(outcome.problems)


def test_catalogue_covers_the_issue() -> None:
    """At least 80 cases, each group of issue 40's list present, ids unique (load_cases checks)."""
    assert len(CASES) >= 80
    groups = {c.group for c in CASES}
    assert len(groups) >= 8
    refused = [c for c in CASES if c.refused]
    assert len(refused) >= 30 and all(c.run for c in refused)
    assert {c.call for c in CASES if c.call} >= {"rerun", "threads", "sensitivity", "power_crust", "sfs"}


# ---- the checker itself must be able to fail -----------------------------------------------------


def test_checks_catch_what_they_are_for() -> None:
    record = {"metrics": {"ssim": 1.5, "rmse": -0.1, "psnr": float("inf")}, "derived": {}, "info": {}}
    problems = record_problems(record, ["RuntimeWarning: overflow encountered in multiply"], ())
    text = "; ".join(problems)
    assert "RuntimeWarning" in text and "metrics.ssim=1.5 is outside [-1, 1]" in text
    assert "metrics.rmse=-0.1 is negative" in text and "left out: metrics.psnr=inf" in text
    assert record_problems({"metrics": {"psnr": float("nan")}}, [], ("metrics.psnr",)) == []


def test_bounds_measure_their_left_side() -> None:
    case = Case(
        id="x", what="x", run=(), bounds=("metrics.psnr >= 20", "abs(a - b) <= 1e-9", "get('metrics.no', -1) <= 0")
    )
    measured, problems = check_bounds(case, {"metrics": {"psnr": 19.0}, "a": 1.0, "b": 1.0})
    assert [v for _, v, _ in measured] == [19.0, 0.0, -1.0]
    assert problems == ["bound 'metrics.psnr >= 20' not met: measured 19"]
    _, problems = check_bounds(Case(id="y", what="y", run=(), bounds=("metrics.gone > 0",)), {"metrics": {}})
    assert problems == ["bound 'metrics.gone > 0': metrics.gone is not in the result"]


def test_a_refusal_must_name_the_key_the_user_set() -> None:
    """A refusal naming another key than the one the case set is a failure of the case."""
    case = Case(id="z", what="z", run=("camera.resolution=3",), expect={"refused": "scan.ratio"})
    outcome = run_case(case)
    assert outcome.status == "refused" and not outcome.holds
    assert "does not start with scan.ratio" in outcome.problems[0]
    assert isinstance(outcome, Outcome) and np.isfinite(outcome.seconds)


def test_command_line_refuses_unknown_ids_and_partial_docs(capsys: pytest.CaptureFixture[str]) -> None:
    from nirspi_pipe.hardcases.check import main

    assert main(["no-such-case"]) == 2
    assert "unknown case ids ['no-such-case']" in capsys.readouterr().err
    assert main(["--write-docs", "crust-cap"]) == 2  # docs/hardcases.md is written from every case only
    assert main(["crust-cap"]) == 0 and "holds" in capsys.readouterr().out
