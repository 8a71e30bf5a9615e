"""The installed console scripts, run in subprocesses from an empty temporary directory."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest

pytestmark = pytest.mark.slow


def _records(root: Path) -> list[dict]:
    return [json.loads(p.read_text()) for p in sorted(root.rglob("record.json"))]


def test_single_run_writes_record_arrays_and_pngs(cli) -> None:
    res = cli("nirspi-run", "camera.resolution=32", "hydra.run.dir=run")
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
    res = cli("nirspi-run", "-m", "scan=basic", "solver=fwht", "seed=0,1", "camera.resolution=16",
              "hydra.sweep.dir=sweep")
    assert res.returncode == 0, res.stderr
    sweep = cli.cwd / "sweep"
    assert len(_records(sweep)) == 2
    df = pd.read_parquet(sweep / "results.parquet")
    assert len(df) == 2 and (df["status"] == "ok").all()
    assert sorted(df["seed"]) == [0, 1]
    for col in ("scan", "solver", "scene", "metrics.ssim", "metrics.psnr", "timings_ms.solver",
                "timings_ms.total", "status"):
        assert col in df.columns, col
    assert (sweep / "results.csv").is_file()


def test_failed_job_is_recorded_and_others_complete(cli) -> None:
    res = cli("nirspi-run", "-m", "scene.reflectance=0.5,1.5,0.2", "camera.resolution=16",
              "hydra.sweep.dir=sweep")
    assert res.returncode == 0, res.stderr
    df = pd.read_parquet(cli.cwd / "sweep" / "results.parquet")
    assert list(df["status"]) == ["ok", "failed", "ok"]
    failed = df[df["status"] == "failed"].iloc[0]
    assert "scene.reflectance" in failed["error"]
    assert failed["scene.reflectance"] == 1.5
    assert df.loc[df["status"] == "ok", "metrics.ssim"].notna().all()


def test_joblib_launcher_and_collect(cli) -> None:
    res = cli("nirspi-run", "-m", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", "seed=0,1",
              "camera.resolution=16", "output.images=false", "hydra.sweep.dir=sweep")
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
