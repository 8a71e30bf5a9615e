"""The ``objective`` key: what a job returns to an optimising sweeper, and the Pareto front."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from nirspi_pipe.app.objective import (
    ObjectiveError,
    directions_of,
    objective_names,
    objective_values,
    pareto_mask,
)
from nirspi_pipe.app.results import mark_pareto
from nirspi_pipe.jobkey import config_hash, job_key_of


def test_names_take_a_key_or_a_list_of_record_keys() -> None:
    assert objective_names(None) == []
    assert objective_names("metrics.psnr") == ["metrics.psnr"]
    assert objective_names(["metrics.psnr", "timings_ms.total", "info.solver.iterations"]) == [
        "metrics.psnr",
        "timings_ms.total",
        "info.solver.iterations",
    ]


@pytest.mark.parametrize(
    "bad", ["psnr", "metrics", "config.seed", "metrics.psnr;rm", [], ["metrics.psnr", "metrics.psnr"], [3], 3.0]
)
def test_a_bad_objective_is_one_line_naming_the_key(bad: object) -> None:
    with pytest.raises(ObjectiveError, match=r"^objective") as info:
        objective_names(bad)
    assert "\n" not in str(info.value) and "allowed" in str(info.value)


def test_directions_one_per_objective() -> None:
    assert directions_of(["maximize", "minimize"], 2) == ["maximize", "minimize"]
    assert directions_of("minimize", 1) == ["minimize"]
    assert directions_of(None, 2) == []
    with pytest.raises(ObjectiveError, match="1 direction"):
        directions_of("minimize", 2)
    with pytest.raises(ObjectiveError, match="'up'"):
        directions_of(["up", "minimize"], 2)


def _record(status: str = "ok", **metrics: float) -> dict:
    return {
        "config": {"objective": ["metrics.psnr", "timings_ms.solver"]},
        "metrics": metrics,
        "timings_ms": {"solver": 1.5},
        "meta": {"status": status},
    }


def test_values_come_from_the_record() -> None:
    assert objective_values(_record(psnr=30.25)) == [30.25, 1.5]
    one = _record(psnr=30.25)
    one["config"]["objective"] = "metrics.psnr"
    assert objective_values(one) == 30.25


@pytest.mark.parametrize(
    "record",
    [_record("failed", psnr=30.0), _record(psnr=math.nan), _record(psnr=math.inf), _record(), _record("missing")],
    ids=["failed", "nan", "inf", "absent", "missing"],
)
def test_a_failed_or_valueless_job_returns_none(record: dict) -> None:
    # hydra-optuna-sweeper 1.3 tells Optuna a trial whose value is not float-castable FAIL and
    # goes on; a NaN would make optuna 2.10's Study.tell raise (see test_optuna.py)
    assert objective_values(record) is None


def test_the_objective_does_not_move_a_job_or_its_seed() -> None:
    config = {"seed": None, "scan": {"ratio": 0.5}, "objective": None}
    with_objective = {**config, "objective": ["metrics.psnr", "timings_ms.solver"]}
    without = {k: v for k, v in config.items() if k != "objective"}
    assert config_hash(config) == config_hash(with_objective) == config_hash(without)
    assert job_key_of(config, {"a": "1"}) == job_key_of(with_objective, {"a": "1"})
    assert config_hash({**config, "seed": 1}) != config_hash(config)  # the rest still counts


def _dominates(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(np.all(a <= b) and np.any(a < b))


@settings(max_examples=200, deadline=None)
@given(
    arrays(
        np.float64, st.tuples(st.integers(1, 25), st.just(3)), elements=st.sampled_from([0.0, 1.0, 2.0, 2.5, np.nan])
    ),
    st.lists(st.sampled_from(["minimize", "maximize"]), min_size=3, max_size=3),
)
def test_the_front_is_exactly_the_non_dominated_finite_rows(values: np.ndarray, directions: list[str]) -> None:
    mask = pareto_mask(values, directions)
    cost = values * np.array([1.0 if d == "minimize" else -1.0 for d in directions])
    finite = np.isfinite(cost).all(axis=1)
    for i in range(len(values)):
        dominated = any(_dominates(cost[j], cost[i]) for j in range(len(values)) if finite[j])
        assert mask[i] == (finite[i] and not dominated), (i, values, directions)


def test_pareto_column_only_on_ok_rows() -> None:
    frame = pd.DataFrame(
        {
            "status": ["ok", "ok", "failed", "ok"],
            "metrics.psnr": [30.0, 25.0, 99.0, 20.0],
            "timings_ms.solver": [10.0, 1.0, 0.1, 5.0],
        }
    )
    marked = mark_pareto(frame, ["metrics.psnr", "timings_ms.solver"], ["maximize", "minimize"])
    assert marked["pareto"].tolist() == [True, True, False, False]


def test_repeats_of_a_configuration_are_on_the_front_by_their_median() -> None:
    # config a repeated three times: one lucky timing (1 ms) among slow ones (20, 21 ms); config b
    # once at 10 ms with the same PSNR. Row by row the lucky repeat would win; by medians b does.
    frame = pd.DataFrame(
        {
            "job": ["a0", "a1", "a2", "b0", "c0"],
            "status": ["ok", "ok", "ok", "ok", "failed"],
            "config_hash": ["a", "a", "a", "b", "c"],
            "metrics.psnr": [30.0, 30.0, 30.0, 30.0, np.nan],
            "timings_ms.solver": [1.0, 20.0, 21.0, 10.0, np.nan],
        }
    )
    marked = mark_pareto(frame, ["metrics.psnr", "timings_ms.solver"], ["maximize", "minimize"])
    assert marked["pareto"].tolist() == [False, False, False, True, False]
    # each row its own configuration (no config_hash): the lucky row wins
    alone = mark_pareto(
        frame.drop(columns="config_hash"), ["metrics.psnr", "timings_ms.solver"], ["maximize", "minimize"]
    )
    assert alone["pareto"].tolist() == [True, False, False, False, False]
