"""Optuna's sweeps through the installed CLI (``pip install '.[optuna]'``, part of ``[test]``):
single- and multi-objective, its sweep syntax, failed trials, and the results of any sweep."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from conftest import NOISE_FREE

pytestmark = pytest.mark.slow
pytest.importorskip("hydra_plugins.hydra_optuna_sweeper", reason="pip install '.[optuna]'")

#: A tiny, fast job: 8² patterns, clear air, the 64² study's camera without the device preset.
TINY = ["preset=null", "camera.resolution=8", *NOISE_FREE, "output.images=false", "output.arrays=false"]
TWO = ["objective=[metrics.psnr,timings_ms.solver]", "hydra.sweeper.direction=[maximize,minimize]"]


def _results(sweep: Path) -> pd.DataFrame:
    return pd.read_parquet(sweep / "results.parquet")


def test_multi_objective_sweep_returns_objectives_and_marks_the_front(cli) -> None:
    res = cli(
        "nirspi-run",
        "-m",
        "hydra/sweeper=optuna",
        "hydra/sweeper/sampler=random",
        "hydra.sweeper.sampler.seed=3",
        "hydra.sweeper.n_trials=6",
        "hydra.sweeper.n_jobs=3",
        *TINY,
        *TWO,
        "solver=choice(fwht,lstsq)",
        "scan=choice(basic,spiral)",
        "scan.ratio=interval(0.25,1.0)",
        "hydra.sweep.dir=sweep",
    )
    assert res.returncode == 0, res.stderr
    sweep = Path(cli.cwd) / "sweep"
    df = _results(sweep)
    assert len(df) == 6 and (df["status"] == "ok").all()
    assert "pareto" in df.columns and df["pareto"].dtype == bool and df["pareto"].any()
    assert (sweep / "front.png").is_file()
    # what Optuna was told is what the records hold: its Pareto solutions are our pareto rows
    solutions = yaml.safe_load((sweep / "optimization_results.yaml").read_text())["solutions"]
    told = np.array(sorted(tuple(s["values"]) for s in solutions), dtype=float)
    ours = np.array(sorted(map(tuple, df[df["pareto"]][["metrics.psnr", "timings_ms.solver"]].to_numpy())))
    assert told.shape == ours.shape and told.shape[1:] == (2,)
    np.testing.assert_allclose(told, ours, rtol=1e-9)
    assert df["scan.ratio"].between(0.25, 1.0).all() and df["scan.ratio"].nunique() > 1


def test_a_failed_trial_is_a_failed_row_and_the_study_goes_on(cli) -> None:
    # fista_tv refuses a negative TV weight when the job builds it; Optuna's random sampler with
    # seed 5 draws (lam, scan) = (-1, spiral), (-1, basic), (0.01, spiral), (0.01, basic) here
    res = cli(
        "nirspi-run",
        "-m",
        "hydra/sweeper=optuna",
        "hydra/sweeper/sampler=random",
        "hydra.sweeper.sampler.seed=5",
        "hydra.sweeper.n_trials=4",
        "hydra.sweeper.n_jobs=2",
        *TINY,
        *TWO,
        "solver=fista_tv",
        "solver.lam=choice(0.01,-1.0)",
        "scan=choice(basic,spiral)",
        "hydra.sweep.dir=sweep",
    )
    sweep = Path(cli.cwd) / "sweep"
    assert (sweep / "results.parquet").is_file(), res.stdout + res.stderr
    df = _results(sweep)
    assert len(df) == 4 and sorted(df["status"]) == ["failed", "failed", "ok", "ok"]
    assert sorted(df["scan"] + df["solver.lam"].astype(str)) == ["basic-1.0", "basic0.01", "spiral-1.0", "spiral0.01"]
    assert (df[df["status"] == "failed"]["solver.lam"] == -1.0).all()
    assert not df[df["status"] == "failed"]["pareto"].any()
    assert "Traceback" not in res.stderr
    # the study finished (its results file), then the sweep says why it exits 1, in one line
    solutions = yaml.safe_load((sweep / "optimization_results.yaml").read_text())["solutions"]
    assert 1 <= len(solutions) <= 2
    assert res.returncode == 1
    errors = [ln for ln in res.stderr.splitlines() if ln.startswith("nirspi-run: error:")]
    assert len(errors) == 1 and "2 of 4 jobs did not finish ok" in errors[0] and "max_failure_rate" in errors[0]


def test_single_objective_with_the_whole_sweep_syntax_and_hydras_own_launcher(cli) -> None:
    # interval, tag(log, interval), range and choice; hydra/launcher=basic runs each job through
    # Hydra's run_job: the objective then comes from the results callback's on_job_end
    res = cli(
        "nirspi-run",
        "-m",
        "hydra/sweeper=optuna",
        "hydra/launcher=basic",
        "hydra.sweeper.sampler.seed=1",
        "hydra.sweeper.n_trials=3",
        "hydra.sweeper.n_jobs=1",
        "hydra.sweeper.direction=maximize",
        "objective=metrics.psnr",
        *TINY,
        "solver=lstsq",
        "solver.damp=tag(log,interval(0.0001,0.1))",
        "scan.ratio=interval(0.3,0.9)",
        "seed=range(0,5)",
        "camera.resolution=choice(8,16)",
        "hydra.sweep.dir=sweep",
    )
    assert res.returncode == 0, res.stderr
    sweep = Path(cli.cwd) / "sweep"
    df = _results(sweep)
    assert len(df) == 3 and (df["status"] == "ok").all()
    assert df["solver.damp"].between(1e-4, 0.1).all() and df["seed"].isin(range(5)).all()
    best = yaml.safe_load((sweep / "optimization_results.yaml").read_text())["best_value"]
    assert best == pytest.approx(df["metrics.psnr"].max())
    assert df["pareto"].sum() >= 1 and df.loc[df["pareto"], "metrics.psnr"].max() == pytest.approx(best)
    assert not (sweep / "front.png").exists()  # one objective: no front to draw


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        ([], "objective"),  # Optuna optimises what objective names: it must be set
        (["objective=[metrics.psnr,timings_ms.solver]"], "1 direction(s) for 2 objective(s)"),
        (["objective=psnr"], "objective: 'psnr' is not allowed"),
    ],
)
def test_an_unusable_objective_stops_before_any_job(cli, args: list[str], needle: str) -> None:
    res = cli("nirspi-run", "-m", "hydra/sweeper=optuna", "hydra.sweeper.n_trials=2", *TINY, *args, "hydra.sweep.dir=s")
    assert res.returncode == 2, res.stdout + res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and needle in lines[0], res.stderr
    assert not list((Path(cli.cwd) / "s").rglob("record.json"))


def test_a_single_objective_study_where_every_trial_failed(cli) -> None:
    # every trial fails (the same configuration, one keyed job folder): the study ends, the results
    # callback writes the table and exits 1 in one line naming the failures (hydra-optuna-sweeper
    # raised Optuna's "No trials are completed yet" before the table was written)
    res = cli(
        "nirspi-run",
        "-m",
        "hydra/sweeper=optuna",
        "hydra.sweeper.n_trials=2",
        "hydra.sweeper.direction=maximize",
        "objective=metrics.psnr",
        *TINY,
        "solver=fista_tv",
        "solver.lam=-1.0",
        "hydra.sweep.dir=sweep",
    )
    assert res.returncode == 1
    assert "Traceback" not in res.stderr and "No trials are completed yet" not in res.stderr
    errors = [ln for ln in res.stderr.splitlines() if ln.startswith("nirspi-run: error:")]
    assert len(errors) == 1 and "did not finish ok" in errors[0] and "max_failure_rate" in errors[0]
    sweep = Path(cli.cwd) / "sweep"
    df = _results(sweep)
    assert set(df["status"]) == {"failed"} and not df["pareto"].any()
    assert not (sweep / "optimization_results.yaml").exists()  # no trial completed: no best one


def test_max_failure_rate_decides_the_exit_code(cli) -> None:
    # the random sampler with seed 0 draws the two weights -1.0 then 0.01 (optuna 2.10.1): one of two fails
    res = cli(
        "nirspi-run",
        "-m",
        "hydra/sweeper=optuna",
        "hydra/sweeper/sampler=random",
        "hydra.sweeper.sampler.seed=0",
        "hydra.sweeper.n_jobs=1",
        "hydra.sweeper.n_trials=2",
        "hydra.sweeper.max_failure_rate=0.5",
        "hydra.sweeper.direction=maximize",
        "objective=metrics.psnr",
        *TINY,
        "solver=fista_tv",
        "solver.lam=choice(0.01,-1.0)",
        "hydra.sweep.dir=sweep",
    )
    assert res.returncode == 0, res.stderr
    df = _results(Path(cli.cwd) / "sweep")
    assert sorted(df["status"]) == ["failed", "ok"] and df["pareto"].tolist() == list(df["status"] == "ok")


def test_the_grid_sampler_is_refused_in_one_line(cli) -> None:
    # optuna 2.10's GridSampler stops the study from outside Study.optimize once its grid is used
    # up, which crashed the plugin's sweep with a traceback: refused before any job runs
    res = cli("nirspi-run", "-m", "hydra/sweeper=optuna", "hydra/sweeper/sampler=grid", "objective=metrics.psnr", *TINY)
    assert res.returncode == 2, res.stderr
    line = res.stderr.strip().splitlines()[-1]
    assert "hydra/sweeper/sampler=grid is not allowed" in line and "plain -m sweep" in line
