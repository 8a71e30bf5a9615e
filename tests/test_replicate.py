"""Replication on new seeds in one command: ``nirspi-run -m +experiment=paper 'seed=range(20,30)'``
(or ``seed=20,21,...``) runs every listed experiment's grid on those seeds and writes the report."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pandas as pd
import pytest

from test_sweeper import _sweeper_for, hydra_loader  # noqa: F401 - the loader fixture


def _seeds_by_experiment(grid: list[list[str]]) -> dict[str, Counter]:
    out: dict[str, Counter] = {}
    for job in grid:
        exp = next(o.split("=", 1)[1] for o in job if o.startswith("+experiment="))
        seeds = [o.split("=", 1)[1] for o in job if o.startswith("seed=")]
        out.setdefault(exp, Counter()).update(seeds or ["(none)"])
    return out


@pytest.mark.parametrize("sweep", ["seed=20,21,22", "seed=range(20,23)", "seed=choice(20,21,22)"])
def test_a_command_line_seed_sweep_replaces_every_experiments_seeds(hydra_loader, sweep: str) -> None:  # noqa: F811
    sweeper = _sweeper_for(hydra_loader, "paper_ci")
    base = sweeper._expand(["+experiment=paper_ci"])
    grid = sweeper._expand(["+experiment=paper_ci", sweep])
    before, after = _seeds_by_experiment(base), _seeds_by_experiment(grid)
    assert set(after) == set(before) == {"table2_ci", "table3_ci", "table4_ci", "figure9_ci"}
    for exp, seeds in after.items():
        # each experiment's own grid, once per new seed: its seed list (or seed: null) replaced
        assert set(seeds) == {"20", "21", "22"}, exp
        assert sum(seeds.values()) == 3 * sum(before[exp].values()) // len(before[exp]), exp
        assert len(set(seeds.values())) == 1, exp  # every seed gets the same jobs


def test_a_plain_override_still_applies_to_every_experiment(hydra_loader) -> None:  # noqa: F811
    sweeper = _sweeper_for(hydra_loader, "paper_ci")
    grid = sweeper._expand(["+experiment=paper_ci", "seed=7"])
    assert all("seed=7" in job for job in grid)
    # the override comes after each experiment's own seed value, so Hydra composes seed 7
    assert all([o for o in job if o.startswith("seed=")][-1] == "seed=7" for job in grid)


@pytest.mark.slow
def test_one_command_replicates_the_tables_on_new_seeds(cli) -> None:
    res = cli(
        "nirspi-run",
        "-m",
        "+experiment=paper_ci",
        "hydra.sweeper.experiments=[table4_ci,figure9_ci]",
        "seed=20,21",
        "hydra.sweep.dir=sweep",
    )
    assert res.returncode == 0, res.stderr
    sweep = Path(cli.cwd) / "sweep"
    df = pd.read_parquet(sweep / "results.parquet")
    assert (df["status"] == "ok").all()
    assert df.groupby("experiment")["seed"].apply(lambda s: sorted(set(s))).to_dict() == {
        "figure9_ci": [20, 21],
        "table4_ci": [20, 21],
    }
    report = (sweep / "report.md").read_text()
    assert "2 seeds" in report
    for name in ("table4.md", "figure9.md"):
        assert (sweep / "tables" / name).is_file(), name
