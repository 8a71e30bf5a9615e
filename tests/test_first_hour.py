"""A new user's first hour (issue 43, item 7): the small stumbles, each checked as a user meets it."""

from __future__ import annotations

from typing import Any

from nirspi_pipe.app.results import records_to_frame, tables_by_experiment


def _record(tables: list[str], overrides: list[str], seed: int = 0) -> dict[str, Any]:
    return {
        "meta": {"status": "ok", "seed": seed, "overrides": overrides},
        "choices": {"experiment": "table2", "scene": "sphere"},
        "config": {"tables": tables, "seed": seed, "scene": {"distance_mm": 200.0}},
        "metrics": {"psnr": 20.0},
    }


def test_tables_override_to_none_builds_no_table() -> None:
    """``tables=[]`` on the command line: no table (it was the table named "[]", which failed)."""
    frame = records_to_frame([("a", _record([], ["+experiment=table2", "tables=[]"]))])
    assert frame.loc[0, "tables"] == ""
    assert tables_by_experiment(frame) == {}


def test_tables_override_names_the_tables() -> None:
    """``tables=[table2,table3]``: those tables, not one table named "['table2', 'table3']"."""
    rec = _record(["table2", "table3"], ["+experiment=table2", "tables=[table2,table3]", "scene.distance_mm=200"])
    frame = records_to_frame([("a", rec), ("b", _record(["table2", "table3"], ["tables=[table2,table3]"], seed=1))])
    assert tables_by_experiment(frame) == {"table2": ["table2", "table3"]}
    assert list(frame["seed"]) == [0, 1]
    assert list(frame["scene.distance_mm"].iloc[:1]) == [200.0]
