"""A real SLURM cluster (issue 12, item 9): a small sweep under ``hydra/launcher=slurm`` (submitit),
stopped half-way with ``scancel``, resumed, gives the metrics of a local run, job by job.

Needs a SLURM cluster reachable from this machine (``.ci/slurm-setup.sh`` starts a single-node one
on 127.0.0.1, as root) and a folder that its nodes share with this process (the test's temporary
folder: true on a single node). Skips, naming the reason, when there is none.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import time
import uuid
from pathlib import Path

import pandas as pd
import pytest

from conftest import run_cli, script

GRID = ["seed=0,1,2,3,4,5", "camera.resolution=16", "output.images=false"]


def _slurm_unavailable() -> str | None:
    """Why SLURM cannot run this test here, or None."""
    missing = [t for t in ("sinfo", "sbatch", "squeue", "scancel") if shutil.which(t) is None]
    if missing:
        return f"SLURM client tools not found ({', '.join(missing)}); as root, run .ci/slurm-setup.sh"
    try:
        import hydra_plugins.hydra_submitit_launcher  # noqa: F401
    except ImportError:
        return "hydra-submitit-launcher is not installed"
    try:
        res = subprocess.run(["sinfo", "-h", "-o", "%T"], check=False, capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.SubprocessError) as exc:
        return f"sinfo failed: {exc}"
    states = res.stdout.split()
    if res.returncode != 0 or not any(s.rstrip("*~#") in ("idle", "mixed", "allocated") for s in states):
        why = (res.stderr.strip().splitlines() or [f"node states {states}"])[0]
        return f"no usable SLURM node ({why}); as root, run .ci/slurm-setup.sh"
    return None


def _our_jobs(name: str) -> list[str]:
    res = subprocess.run(
        ["squeue", "-h", "-n", name, "-o", "%i"], check=False, capture_output=True, text=True, timeout=20
    )
    return res.stdout.split()


def _ok_records(sweep: Path) -> int:
    n = 0
    for rec in sweep.glob("*/record.json"):
        try:
            n += json.loads(rec.read_text())["meta"]["status"] == "ok"
        except (OSError, ValueError, KeyError):
            pass
    return n


def _metrics(sweep: Path) -> pd.DataFrame:
    frame = pd.read_parquet(sweep / "results.parquet").set_index("job").sort_index()
    return frame[[c for c in frame.columns if c.startswith("metrics.")]]


@pytest.mark.slow
def test_slurm_sweep_cancelled_half_way_resumes_to_the_local_metrics(tmp_path: Path) -> None:
    reason = _slurm_unavailable()
    if reason:
        pytest.skip(reason)
    name = f"nirspi-test-{uuid.uuid4().hex[:8]}"  # scancel only this test's jobs
    slurm = [
        *GRID,
        "hydra/launcher=slurm",
        f"hydra.launcher.name={name}",
        "hydra.launcher.timeout_min=10",
        "hydra.launcher.cpus_per_task=1",
        "hydra.launcher.mem_gb=1",
        "hydra.launcher.array_parallelism=1",
        "hydra.sweep.dir=slurm",
    ]
    sweep = tmp_path / "slurm"
    env = {k: v for k, v in os.environ.items() if k not in ("HYDRA_FULL_ERROR", "NIRSPI_TRACEBACK")}
    env["MPLBACKEND"] = "Agg"
    proc = subprocess.Popen(
        [script("nirspi-run"), "-m", *slurm],
        cwd=tmp_path,
        env=env,
        text=True,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 300
        while _ok_records(sweep) < 2 and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.5)
        done = _ok_records(sweep)
        # half-way: stop the sweeping process, then cancel its jobs on the cluster
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=60)
        for _ in range(60):
            jobs = _our_jobs(name)
            if not jobs:
                break
            subprocess.run(["scancel", *jobs], check=False, capture_output=True, timeout=20)
            time.sleep(1)
        assert not _our_jobs(name), "scancel left jobs behind"
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        subprocess.run(["scancel", "-n", name], check=False, capture_output=True, timeout=20)
    first = proc.stdout.read() if proc.stdout else ""
    assert 2 <= done < 6, f"expected to stop half-way, {done} of 6 jobs had finished:\n{first[-2000:]}"
    remaining = 6 - _ok_records(sweep)
    assert remaining > 0, "every job had finished before the cancel"

    resumed = run_cli(["nirspi-run", "-m", *slurm], tmp_path, timeout=600)
    assert resumed.returncode == 0, resumed.stdout[-2000:] + resumed.stderr[-2000:]
    assert f"{remaining} to run, {6 - remaining} skipped" in resumed.stdout, resumed.stdout[-2000:]
    local = run_cli(["nirspi-run", "-m", *GRID, "hydra/launcher=basic", "hydra.sweep.dir=local"], tmp_path)
    assert local.returncode == 0, local.stderr[-2000:]

    on_slurm, here = _metrics(sweep), _metrics(tmp_path / "local")
    assert len(on_slurm) == 6 and list(on_slurm.index) == list(here.index)  # same job keys
    assert (pd.read_parquet(sweep / "results.parquet")["status"] == "ok").all()
    pd.testing.assert_frame_equal(on_slurm, here, check_exact=True)


def test_the_skip_names_what_is_missing(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(shutil, "which", lambda name: None)
    reason = _slurm_unavailable()
    assert reason is not None and "sinfo" in reason and ".ci/slurm-setup.sh" in reason
