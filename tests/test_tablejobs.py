"""A sweep's tables built side by side (nirspi_pipe.app.tablejobs): the same files and lines as one
after another, in the experiments' order, and a child that dies costs nothing."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pandas as pd
import pytest

from nirspi_pipe.app.tablejobs import build_parts

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="forks")


def _writer(frame: pd.DataFrame, sweep: Path, names: list[str]) -> list[str]:
    """A stand-in for results.build_tables: one file per name, holding the frame's sum and the pid."""
    (sweep / "tables").mkdir(exist_ok=True)
    for name in names:
        (sweep / "tables" / f"{name}.md").write_text(f"{name}: {int(frame['x'].sum())}\n")
        print(f"table {name} built in {os.getpid()}")
    return list(names)


def _parts() -> list[tuple[pd.DataFrame, list[str]]]:
    return [
        (pd.DataFrame({"x": range(3)}), ["small"]),
        (pd.DataFrame({"x": range(100)}), ["big_a", "big_b"]),  # submitted first (rows × tables)
        (pd.DataFrame({"x": range(10)}), ["middle"]),
    ]


def _files(folder: Path) -> dict[str, str]:
    return {p.name: p.read_text() for p in sorted(folder.iterdir())}


def test_side_by_side_equals_one_after_another(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    serial, parallel = tmp_path / "serial", tmp_path / "parallel"
    serial.mkdir()
    parallel.mkdir()
    assert build_parts(_parts(), serial, _writer, workers=1) == ["small", "big_a", "big_b", "middle"]
    out_serial = capfd.readouterr().out
    assert build_parts(_parts(), parallel, _writer, workers=2) == ["small", "big_a", "big_b", "middle"]
    out_parallel = capfd.readouterr().out
    assert _files(serial / "tables") == _files(parallel / "tables")
    names = [line.split()[1] for line in out_parallel.splitlines()]
    assert names == ["small", "big_a", "big_b", "middle"]  # the parts' order, whoever finished first
    assert {line.rsplit(" ", 1)[1] for line in out_serial.splitlines()} == {str(os.getpid())}
    assert str(os.getpid()) not in {line.rsplit(" ", 1)[1] for line in out_parallel.splitlines()}


def _dies_once(frame: pd.DataFrame, sweep: Path, names: list[str]) -> list[str]:
    """Kills the child that builds ``big_a`` (as a segfault would); the parent then builds it."""
    if "big_a" in names and os.getpid() != int(os.environ["NIRSPI_TEST_PARENT"]):
        sys.stdout.flush()
        os._exit(139)
    return _writer(frame, sweep, names)


def test_a_dead_child_costs_only_a_rebuild(
    tmp_path: Path, capfd: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("NIRSPI_TEST_PARENT", str(os.getpid()))
    built = build_parts(_parts(), tmp_path, _dies_once, workers=2)
    assert sorted(built) == ["big_a", "big_b", "middle", "small"]
    assert sorted(_files(tmp_path / "tables")) == ["big_a.md", "big_b.md", "middle.md", "small.md"]
    err = capfd.readouterr().err
    assert "tables big_a, big_b were not built side by side (a table process died); building them here" in err


def test_one_part_is_built_here(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    assert build_parts(_parts()[:1], tmp_path, _writer, workers=4) == ["small"]
    assert capfd.readouterr().out.strip().endswith(str(os.getpid()))
