"""One checked plan (issue 42, items 1 and 6): a job's config is converted to plain data once and
each of its ``_target_`` strings is checked against the allow-list once; the stages are built
from that plan without converting a node or checking a target again.

Before (at cf90d56 and still at 5911ebf), one default job made 29 conversions (``plain_config``
calls from outside itself) and 123 allow-list checks in the runner for its 24 targets: every
``build`` and ``check_types`` converted its node again and checked its targets again. At 27f888e
a whole default ``nirspi-run`` still made 35 checks (the app's schema catalogue checked 11 targets
that the job's plan then checked again), and 55 with a value override (the app's type check of
the overridden config checked its targets again)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

import nirspi_pipe.instantiate as instantiate
import nirspi_pipe.targets as targets
from nirspi_pipe.errors import ConfigError
from nirspi_pipe.execute import execute_job
from nirspi_pipe.instantiate import Plan, plain_config

#: A default job at a tiny resolution (the defaults' 16 ``_target_`` nodes; 24 before the metrics
#: stopped carrying copies of the scene, source and upscaler, issue 42 item 3).
DEFAULT = ["camera.resolution=16", "output.images=false"]


class Counts:
    """Calls of the allow-list check (and the strings checked), of the converter (outermost calls
    only) and of the import by string, counted through the module attributes every caller reads.
    The process's record of passed strings starts empty (as in a new process)."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.checks = 0
        self.checked: list[Any] = []
        self.conversions = 0
        self.imports = 0
        self._depth = 0
        check, convert, locate = targets.check_target, instantiate.plain_config, targets.locate

        def counted_check(target: Any, key: str) -> None:
            self.checks += 1
            self.checked.append(target)
            check(target, key)

        def counted_convert(node: Any) -> Any:
            self.conversions += self._depth == 0
            self._depth += 1
            try:
                return convert(node)
            finally:
                self._depth -= 1

        def counted_locate(target: str) -> Any:
            self.imports += 1
            return locate(target)

        monkeypatch.setattr(targets, "_PASSED", [])  # no verdict of an earlier check in this process
        for module in (targets, instantiate):
            monkeypatch.setattr(module, "check_target", counted_check, raising=False)
            monkeypatch.setattr(module, "locate", counted_locate, raising=False)
        monkeypatch.setattr(instantiate, "plain_config", counted_convert)


@pytest.fixture(scope="module")
def composed() -> Any:
    from nirspi_pipe.app.api import compose

    cfg, _ = compose(DEFAULT)
    return cfg


def _targets(config: Any) -> list[str]:
    return [v for _, v in targets.find_targets(config, "")]


def test_a_default_job_checks_each_target_once_and_converts_once(
    composed: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    n_targets = len(_targets(plain_config(composed)))
    counts = Counts(monkeypatch)
    record = execute_job(composed, tmp_path, {}, DEFAULT)  # the composed OmegaConf node, as Hydra hands it
    assert record["meta"]["status"] == "ok", record["meta"].get("error")
    assert counts.conversions == 1
    assert counts.checks == len(set(_targets(plain_config(composed)))) <= n_targets <= 30  # each string once
    assert counts.imports == len(set(_targets(plain_config(composed))))  # each class imported once


@pytest.mark.parametrize(
    "overrides",
    [[], ["camera.resolution=16", "scene.distance_mm=250", "output.images=false"]],
    ids=["default", "value-overrides"],
)
def test_a_nirspi_run_checks_each_target_once_in_all(
    overrides: list[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``nirspi-run``'s order in one process, as in a new process: the app composes the config
    (its schema catalogue reads the composed options' targets), checks it before it launches Hydra
    (with a value override, the type check of the overridden config too:
    app.validate._check_types), Hydra composes the job again, the task makes its plan and runs it.
    Every target string is checked once in all; at 27f888e the default made 35 checks (11 of the
    catalogue, then 24 of the plan) and the value overrides 55."""
    from nirspi_pipe.app import configs
    from nirspi_pipe.app.entry import check_invocation

    monkeypatch.setattr(configs, "_GENERATED", {})  # the catalogue's schemas made again, as in a new process
    counts = Counts(monkeypatch)
    invocation = check_invocation([*overrides, f"hydra.run.dir={tmp_path}"])
    job = {k: v for k, v in invocation.config.items() if k != "hydra"}  # the task's config, without Hydra's node
    plan = Plan.of(job).check()  # the task's plan of the job Hydra composes again (app.cli._hydra_task)
    record = execute_job(plan, tmp_path, {}, overrides)
    assert record["meta"]["status"] == "ok", record["meta"].get("error")
    names = _targets(plan.config)
    assert len(counts.checked) == len(set(counts.checked))  # no string checked twice
    assert set(names) <= set(counts.checked)  # and every one of the job's checked
    assert counts.checks <= 30


def test_a_recorded_verdict_needs_the_same_string_and_the_same_allow_list(
    composed: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A string passed once is not compared again; any other string is, and a new allow-list
    (here one without the scan's class) drops the record: the verdicts are those of check_target."""
    counts = Counts(monkeypatch)
    Plan(plain_config(composed)).check()
    checks = counts.checks
    Plan(plain_config(composed)).check()
    assert counts.checks == checks
    changed = plain_config(composed)
    changed["scan"]["_target_"] = "os.system"
    with pytest.raises(ConfigError, match=r"^scan\._target_='os\.system' is not allowed"):
        Plan(changed).check()
    with pytest.raises(ConfigError, match=r"^solver\._target_='os\.system' is not allowed"):
        targets.resolve("os.system", "solver._target_")  # a refusal is never recorded
    monkeypatch.setattr(targets, "PROJECT_TARGETS", targets.PROJECT_TARGETS - {"nirspi_pipe.patterns.orders.Basic"})
    with pytest.raises(ConfigError, match=r"^scan\._target_='nirspi_pipe\.patterns\.orders\.Basic' is not allowed"):
        Plan(plain_config(composed)).check()


def test_a_plan_made_at_the_boundary_is_neither_converted_nor_checked_again(
    composed: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    plan = Plan.of(composed).check()  # what a front end does at its boundary
    counts = Counts(monkeypatch)
    record = execute_job(plan, tmp_path, {}, DEFAULT)
    assert record["meta"]["status"] == "ok", record["meta"].get("error")
    assert (counts.conversions, counts.checks) == (0, 0)


def test_the_plan_is_checked_before_anything_is_built(
    composed: Any, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A refused target anywhere in the plan (here the fog model inside the source) fails the job
    with the allow-list's one line naming its key before any stage class is imported or built."""
    config = plain_config(composed)
    config["source"]["effects"]["fog"]["_target_"] = "os.system"
    counts = Counts(monkeypatch)
    record = execute_job(config, tmp_path, {}, DEFAULT)
    assert counts.imports == 0
    assert record["meta"]["status"] == "failed"
    assert record["meta"]["error"].startswith("source.effects.fog._target_='os.system' is not allowed; allowed:")


def test_a_plan_rechecks_a_target_it_did_not_check(composed: Any) -> None:
    """The plan skips the check only for the strings its own walk passed."""
    plan = Plan.of(composed).check()
    with pytest.raises(ConfigError, match=r"^solver\._target_='os\.system' is not allowed"):
        plan.resolve("os.system", "solver._target_")
    assert plan.resolve("nirspi_pipe.solvers.fwht.FWHTSolver", "solver._target_").__name__ == "FWHTSolver"


def test_a_node_built_alone_is_converted_and_checked_once(monkeypatch: pytest.MonkeyPatch) -> None:
    node = {"_target_": "nirspi_pipe.types.Camera", "resolution": 8}
    counts = Counts(monkeypatch)
    camera = instantiate.build(node, "camera")
    assert camera.resolution == 8
    assert (counts.conversions, counts.checks, counts.imports) == (1, 1, 1)
