"""The installed console scripts, run in subprocesses from an empty temporary directory."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest

from conftest import NOISE_FREE

pytestmark = pytest.mark.slow


def _records(root: Path) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted(root.rglob("record.json"))]


def test_single_run_writes_record_arrays_and_pngs(cli) -> None:
    res = cli("nirspi-run", *NOISE_FREE, "camera.resolution=32", "hydra.run.dir=run")
    assert res.returncode == 0, res.stderr
    assert "SSIM" in res.stdout and "PSNR" in res.stdout and "solver=fwht" in res.stdout
    run = cli.cwd / "run"
    rec = json.loads((run / "record.json").read_text())
    assert set(rec) >= {"config", "choices", "metrics", "timings_ms", "derived", "meta"}
    assert rec["meta"]["status"] == "ok" and rec["meta"]["error"] is None
    assert set(rec["meta"]) >= {"config_hash", "seed", "versions", "git_sha"}
    assert rec["choices"]["scan"] == "basic" and rec["choices"]["solver"] == "fwht"
    assert rec["metrics"]["ssim"] > 0.9999 and rec["metrics"]["rmse"] < 1e-9
    assert rec["timings_ms"]["solver"] >= 0
    assert rec["config"]["camera"]["resolution"] == 32
    for name in ("arrays.npz", "reconstruction.png", "truth.png"):
        assert (run / name).is_file(), name


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["scan=nope"], "scan=nope"),
        (["camera.resolution=100"], "camera.resolution"),
        (["scene.reflectance=2"], "scene.reflectance"),
        (["scene.distance_mm=-3"], "scene.distance_mm"),
        (["scene.radius=3"], "scene.radius"),
    ],
)
def test_bad_input_is_one_line_without_traceback(cli, args: list[str], needle: str) -> None:
    res = cli("nirspi-run", *args)
    assert res.returncode == 2
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, res.stderr
    assert needle in lines[0] and "allowed" in lines[0]
    assert "Traceback" not in res.stderr + res.stdout


def test_multirun_two_jobs_and_results_table(cli) -> None:
    res = cli(
        "nirspi-run", "-m", "scan=basic", "solver=fwht", "seed=0,1", "camera.resolution=16", "hydra.sweep.dir=sweep"
    )
    assert res.returncode == 0, res.stderr
    sweep = cli.cwd / "sweep"
    assert len(_records(sweep)) == 2
    assert "2/2 jobs done" in res.stdout  # progress, printed by the sweeping process
    df = pd.read_parquet(sweep / "results.parquet")
    assert len(df) == 2 and (df["status"] == "ok").all()
    assert sorted(df["seed"]) == [0, 1]
    for col in (
        "scan",
        "solver",
        "scene",
        "metrics.ssim",
        "metrics.psnr",
        "timings_ms.solver",
        "timings_ms.total",
        "status",
    ):
        assert col in df.columns, col
    assert (sweep / "results.csv").is_file()


def test_failed_job_is_recorded_and_others_complete(cli) -> None:
    res = cli("nirspi-run", "-m", "scene.reflectance=0.5,1.5,0.2", "camera.resolution=16", "hydra.sweep.dir=sweep")
    assert res.returncode == 1, res.stderr  # the others complete, and the sweep says one failed
    assert "1 of 3 jobs did not finish ok (1 failed: 1x scene.reflectance=1.5" in res.stderr
    df = pd.read_parquet(cli.cwd / "sweep" / "results.parquet")
    assert list(df["status"]) == ["ok", "failed", "ok"]
    failed = df[df["status"] == "failed"].iloc[0]
    assert "scene.reflectance" in failed["error"]
    assert failed["scene.reflectance"] == 1.5
    assert df.loc[df["status"] == "ok", "metrics.ssim"].notna().all()


def test_joblib_launcher_and_collect(cli) -> None:
    res = cli(
        "nirspi-run",
        "-m",
        "hydra/launcher=joblib",
        "hydra.launcher.n_jobs=2",
        "seed=0,1",
        "camera.resolution=16",
        "output.images=false",
        "hydra.sweep.dir=sweep",
    )
    assert res.returncode == 0, res.stderr
    sweep = cli.cwd / "sweep"
    first = pd.read_parquet(sweep / "results.parquet")
    (sweep / "results.parquet").unlink()
    (sweep / "results.csv").unlink()
    res = cli("nirspi-collect", "sweep", "--quiet")
    assert res.returncode == 0, res.stderr
    again = pd.read_parquet(sweep / "results.parquet")
    pd.testing.assert_frame_equal(first, again)
    assert (again["status"] == "ok").all() and len(again) == 2


def test_collect_reports_missing_folder(cli) -> None:
    res = cli("nirspi-collect", "does-not-exist")
    assert res.returncode == 2 and "does-not-exist" in res.stderr


def test_bench_lists_benchmarks(cli) -> None:
    res = cli("nirspi-bench", "nope")
    assert res.returncode == 2 and "transform" in res.stderr
    res = cli("nirspi-bench", "transform", "--sizes", "16", "--repeat", "3")
    assert res.returncode == 0 and "ratio" in res.stdout


def test_sweep_resumes_and_keys_folders_by_config_hash(cli) -> None:
    args = [
        "nirspi-run",
        "-m",
        "seed=0,1",
        "scene.reflectance=0.5,1.5",
        "camera.resolution=16",
        "output.images=false",
        "hydra.sweep.dir=sweep",
    ]
    first = cli(*args)
    assert first.returncode == 1, first.stderr  # reflectance 1.5 fails: the sweep says so
    assert "2 of 4 jobs did not finish ok (2 failed" in first.stderr
    assert "4 to run" in first.stdout
    sweep = cli.cwd / "sweep"
    df = pd.read_parquet(sweep / "results.parquet")
    assert (df["job"] == df["config_hash"]).all()  # folder name = hash of the resolved config
    ok_mtimes = {
        p: p.stat().st_mtime for p in sweep.glob("*/record.json") if json.loads(p.read_text())["meta"]["status"] == "ok"
    }
    assert len(ok_mtimes) == 2
    again = cli(*args)
    assert again.returncode == 1, again.stderr  # the failed jobs ran again, and failed again
    assert "2 to run, 2 skipped (already complete)" in again.stdout
    for p, t in ok_mtimes.items():  # complete jobs were not recomputed
        assert p.stat().st_mtime == t
    df2 = pd.read_parquet(sweep / "results.parquet")
    assert list(df2["status"]) == list(df["status"]) and len(df2) == 4


def test_killed_job_shows_as_missing(cli) -> None:
    res = cli("nirspi-run", "-m", "seed=0,1,2", "camera.resolution=16", "output.images=false", "hydra.sweep.dir=sweep")
    assert res.returncode == 0, res.stderr
    sweep = cli.cwd / "sweep"
    victim = sorted(sweep.glob("*/record.json"))[0]
    victim.unlink()  # as if the job had been killed before writing its record
    res = cli("nirspi-collect", "sweep", "--quiet")
    assert res.returncode == 0, res.stderr
    df = pd.read_parquet(sweep / "results.parquet")
    assert sorted(df["status"]) == ["missing", "ok", "ok"]
    res = cli("nirspi-run", "-m", "seed=0,1,2", "camera.resolution=16", "output.images=false", "hydra.sweep.dir=sweep")
    assert "1 to run, 2 skipped" in res.stdout
    assert (pd.read_parquet(sweep / "results.parquet")["status"] == "ok").all()


def test_submitit_local_launcher(cli) -> None:
    res = cli(
        "nirspi-run",
        "-m",
        "hydra/launcher=submitit_local",
        "seed=0,1",
        "camera.resolution=16",
        "output.images=false",
        "hydra.sweep.dir=sweep",
        timeout=600,
    )
    assert res.returncode == 0, res.stderr
    df = pd.read_parquet(cli.cwd / "sweep" / "results.parquet")
    assert len(df) == 2 and (df["status"] == "ok").all()
    assert "2/2 jobs done" in res.stdout  # progress shows on the terminal under submitit too


def test_same_config_and_seed_are_bitwise_reproducible_across_processes(cli) -> None:
    args = ["camera.resolution=32", "source.effects.noise_rel=0.02", "seed=11", "scene=image"]
    a = cli("nirspi-run", *args, "hydra.run.dir=a")
    b = cli("nirspi-run", *args, "hydra.run.dir=b")
    assert a.returncode == 0 and b.returncode == 0, a.stderr + b.stderr
    ra = json.loads((cli.cwd / "a" / "record.json").read_text())
    rb = json.loads((cli.cwd / "b" / "record.json").read_text())
    assert ra["metrics"] == rb["metrics"]  # exact float equality
    assert ra["meta"]["config_hash"] == rb["meta"]["config_hash"]
    assert ra["meta"]["opencl_devices"]  # provenance names the OpenCL device (or why none)
    import numpy as np

    with np.load(cli.cwd / "a" / "arrays.npz") as fa, np.load(cli.cwd / "b" / "arrays.npz") as fb:
        assert np.array_equal(fa["reconstruction"], fb["reconstruction"])


def test_meta_experiment_runs_each_experiments_grid(cli) -> None:
    exp = cli.cwd / "extra" / "experiment"
    exp.mkdir(parents=True)
    (exp / "small_a.yaml").write_text(
        "# @package _global_\ncamera:\n  resolution: 8\nhydra:\n  sweeper:\n    params:\n      seed: 0,1\n"
    )
    (exp / "small_b.yaml").write_text(
        "# @package _global_\ncamera:\n  resolution: 16\nhydra:\n  sweeper:\n    params:\n"
        "      scene.reflectance: 0.2,0.4,0.6\n"
    )
    (exp / "both.yaml").write_text("# @package _global_\nhydra:\n  sweeper:\n    experiments: [small_a, small_b]\n")
    res = cli(
        "nirspi-run",
        "-m",
        "+experiment=both",
        "output.images=false",
        "hydra.sweep.dir=sweep",
        f"hydra.searchpath=[pkg://nirspi_pipe.experiments,file://{cli.cwd / 'extra'}]",
    )
    assert res.returncode == 0, res.stderr
    assert "sweep of 5 jobs" in res.stdout
    df = pd.read_parquet(cli.cwd / "sweep" / "results.parquet")
    assert list(df["experiment"]) == ["small_a"] * 2 + ["small_b"] * 3
    assert (df["status"] == "ok").all()
    res8 = [
        json.loads((cli.cwd / "sweep" / j / "record.json").read_text())["config"]["camera"]["resolution"]
        for j in df["job"]
    ]
    assert res8 == [8, 8, 16, 16, 16]
