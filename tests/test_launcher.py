"""The ``nirspi`` launcher: runner processes, crash isolation, equality with the joblib launcher."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from conftest import crash_as
from nirspi_pipe.app.jobcomposer import ComposedJob
from nirspi_pipe.errors import ConfigError
from nirspi_pipe.records import RECORD_NAME, read_record, write_record

fork_only = pytest.mark.skipif(not hasattr(os, "fork"), reason="runners are forked")


def _fake_execute(config, out_dir, choices, overrides, job_num, attempt=None):  # type: ignore[no-untyped-def]
    """What a job does, by ``config["how"]``: crash in one of several ways, or write an ok record
    naming the runner's pid (to see runners reused and replaced)."""
    crash_as(config["how"])
    write_record(out_dir, {"meta": {"status": "ok", "attempt": attempt, "pid": os.getpid(), "num": job_num}})
    return {}


@fork_only
def test_crashing_jobs_take_only_themselves_down(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Jobs that segfault, exit, are SIGKILLed or raise each get a failed record naming what
    happened; every other job runs, on runners that are reused and replaced after each crash."""
    import nirspi_pipe.app.launcher as launcher

    monkeypatch.setattr(launcher, "_execute", _fake_execute)
    hows = ["ok", "segv", "ok", "kill", "ok", "exit", "raise", "ok", "ok", "ok"]
    items = [(tmp_path / f"job{i}", i, ComposedJob({"how": how}, {}, [f"how={how}"])) for i, how in enumerate(hows)]
    returns = launcher.NirspiLauncherBase(n_jobs=2)._run(items, tmp_path, None, False)
    assert len(returns) == len(hows)
    expected = {"segv": "SIGSEGV", "kill": "SIGKILL", "exit": "code 5", "raise": "code 70"}
    pids = set()
    for (out_dir, num, _job), how, ret in zip(items, hows, returns, strict=True):
        meta = read_record(out_dir / RECORD_NAME)["meta"]
        assert ret.return_value["meta"] == meta
        assert json.loads((out_dir / "attempts.json").read_text())["attempts"] == 1
        if how == "ok":
            assert meta["status"] == "ok" and meta["num"] == num
            pids.add(meta["pid"])
            assert meta["pid"] != os.getpid()
        else:
            assert meta["status"] == "failed" and meta["error_type"] == "JobCrash", how
            assert expected[how] in meta["error"], (how, meta["error"])
            assert meta["overrides"] == [f"how={how}"] and meta["job_num"] == num
    # 6 ok jobs on 2 runners at a time: reused (fewer pids than jobs), replaced after crashes
    assert 2 <= len(pids) < hows.count("ok") + 1
    assert not any(p.name.startswith(".") and p.suffix == ".tmp" for p in tmp_path.rglob("*"))


def _hanging_execute(config, out_dir, choices, overrides, job_num, attempt=None):  # type: ignore[no-untyped-def]
    """A job that hangs when ``config["how"] == "hang"`` (blocked 10 minutes), else a quick ok one."""
    import time

    if config["how"] == "hang":
        time.sleep(600)
    return _fake_execute(config, out_dir, choices, overrides, job_num, attempt)


@fork_only
def test_a_hanging_job_is_killed_at_its_deadline(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A job still running ``timeout_s`` after it was sent is killed with its runner: a failed
    record naming the deadline (``JobTimeout``); the jobs after it run on a fresh runner, and the
    sweep ends at the deadline rather than after the hang (the hanging job, left alone, would
    finish after 600 s with an ok record; a failed record killed by signal 9 shows it was cut)."""
    import nirspi_pipe.app.launcher as launcher

    monkeypatch.setattr(launcher, "_execute", _hanging_execute)
    hows = ["ok", "hang", "ok", "ok", "ok"]
    items = [(tmp_path / f"job{i}", i, ComposedJob({"how": how}, {}, [f"how={how}"])) for i, how in enumerate(hows)]
    returns = launcher.NirspiLauncherBase(n_jobs=1, timeout_s=2)._run(items, tmp_path, None, False)
    metas = [read_record(out_dir / RECORD_NAME)["meta"] for out_dir, _num, _job in items]
    assert [r.return_value["meta"] for r in returns] == metas
    assert [m["status"] for m in metas] == ["ok", "failed", "ok", "ok", "ok"]
    late = metas[1]
    assert late["error"] == "job killed after its deadline of 2 s (hydra.launcher.timeout_s)"
    assert late["error_type"] == "JobTimeout" and late["timeout_s"] == 2 and late["signal"] == 9
    assert late["overrides"] == ["how=hang"] and late["job_num"] == 1
    # one runner at a time: the one before the hang, then a fresh one for the rest
    assert metas[0]["pid"] != metas[2]["pid"] and metas[2]["pid"] == metas[3]["pid"] == metas[4]["pid"]


@fork_only
def test_a_job_locked_elsewhere_waits_and_runs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A job whose folder another process holds is run after the others, once the lock is free."""
    import subprocess
    import sys

    import nirspi_pipe.app.launcher as launcher

    monkeypatch.setattr(launcher, "_execute", _fake_execute)
    items = [(tmp_path / f"job{i}", i, ComposedJob({"how": "ok"}, {}, [])) for i in range(3)]
    (tmp_path / "job1").mkdir()
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time; from nirspi_pipe.outputfiles import JobLock; "
            f"JobLock({str(tmp_path / 'job1')!r}).acquire(); print('held', flush=True); time.sleep(1.5)",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        launcher.NirspiLauncherBase(n_jobs=2)._run(items, tmp_path, None, False)
        assert holder.poll() is not None  # job1 ran after the holder let go, not beside it
    finally:
        holder.wait(timeout=30)
    for out_dir, _num, _job in items:
        assert read_record(out_dir / RECORD_NAME)["meta"]["status"] == "ok"


@pytest.mark.parametrize("bad", [0, -2, 1.5, True, "2"])
def test_bad_n_jobs_is_one_line(bad: object) -> None:
    from nirspi_pipe.app.launcher import NirspiLauncherBase

    with pytest.raises(ConfigError) as info:
        NirspiLauncherBase(n_jobs=bad)  # type: ignore[arg-type]
    assert "hydra.launcher.n_jobs" in str(info.value) and "allowed" in str(info.value)


@pytest.mark.slow
def test_same_numbers_as_the_joblib_launcher(cli) -> None:
    """The default launcher runs the configs the sweeper composed (no second composition): its
    records hold the same config, choices, overrides and metrics, bit for bit, as joblib's."""
    grid = ["nirspi-run", "-m", "+experiment=table3_ci", "scan=basic,spiral", "illumination.klux=5"]
    for launcher_args, folder in (([], "nirspi"), (["hydra/launcher=joblib"], "joblib")):
        res = cli(*grid, *launcher_args, f"hydra.sweep.dir={folder}", timeout=600)
        assert res.returncode == 0, res.stderr
        # the command line's scan list replaces the experiment's (Hydra's rule): 2 jobs, each run once
        assert "sweep of 2 jobs" in res.stdout and "2 to run" in res.stdout, res.stdout
    ours = {p.parent.name: read_record(p) for p in (cli.cwd / "nirspi").glob("*/record.json")}
    theirs = {p.parent.name: read_record(p) for p in (cli.cwd / "joblib").glob("*/record.json")}
    assert len(ours) == 2 and set(ours) == set(theirs)
    for key, rec in ours.items():
        other = theirs[key]
        for part in ("config", "choices", "metrics", "derived"):
            assert rec[part] == other[part], (key, part)
        for field in ("overrides", "job_key", "config_hash", "status", "inputs"):
            assert rec["meta"][field] == other["meta"][field], (key, field)


@pytest.mark.slow
def test_another_sweeper_composes_through_hydra_and_runs_on_runners(cli) -> None:
    """With Hydra's basic sweeper the launcher composes each job itself (``launch``): numbered
    folders, the task overrides and job numbers Hydra gives, every job ok."""
    res = cli(
        "nirspi-run",
        "-m",
        "hydra/sweeper=basic",
        "seed=0,1",
        "camera.resolution=16",
        "output.images=false",
        "hydra.sweep.dir=sweep",
    )
    assert res.returncode == 0, res.stderr
    assert "2/2 jobs done" in res.stdout
    for num in (0, 1):
        rec = read_record(cli.cwd / "sweep" / str(num) / RECORD_NAME)
        assert rec["meta"]["status"] == "ok" and rec["meta"]["job_num"] == num
        assert rec["meta"]["overrides"][0] == f"seed={num}" and rec["config"]["seed"] == num


_WARM_THEN_RUN = r"""
import json, sys, warnings
warnings.simplefilter("ignore")
from hydra import compose, initialize_config_module
from nirspi_pipe.app.configs import CONFIG_MODULE, CONFIG_NAME, scan_indices
from nirspi_pipe.instantiate import plain_config
import nirspi_pipe.metrics as m
composed = "scipy.stats" in sys.modules
with initialize_config_module(CONFIG_MODULE, version_base="1.3"):
    cfg = plain_config(compose(CONFIG_NAME, overrides=json.loads(sys.argv[1])))
from nirspi_pipe.execute import warm_up
failed = warm_up([cfg])
before = set(sys.modules)
from nirspi_pipe.pipeline import run_pipeline
run_pipeline(cfg, scan_indices=scan_indices)
print(json.dumps({"composed": composed, "failed": failed, "new": sorted(set(sys.modules) - before)}))
"""

#: Modules a job may still load after the warm-up: pyopencl's context is made in the job's own
#: process by design (stages.WarmsUp: no threads before a fork) and loads these on first use;
#: the read-out's range model is imported by the forward model's read-out effect, which has no
#: warm-up of its own (its own class, not a stage's, imports it).
_LOADED_BY_THE_JOB = ("pyopencl", "pytools", "platformdirs", "encodings.", "nirspi_pipe.physics.range_model")


@pytest.mark.parametrize(
    "overrides",
    [
        [],
        [
            "preset=device",
            "fog=chamber",
            "sfs=lax_friedrichs",
            "itof=cw4",
            "fusion=itof",
            "upscale=fsrcnn",
            "metrics=upscale",
        ],
        ["fog=chamber", "sfs=lax_friedrichs", "sfs.backend=auto"],
    ],
    ids=["default", "device-fog-itof-fsrcnn", "sfs-auto"],
)
def test_a_job_loads_nothing_its_stages_warm_up_did_not(overrides: list[str]) -> None:
    """The launcher warms the stages up without naming a module (``nirspi_pipe.execute.warm_up``
    calls each ``_target_``'s own ``warm_up``): after it, running the job imports nothing more
    than the listed per-process modules; composing a config leaves scipy.stats unloaded."""
    import json
    import subprocess
    import sys

    ov = ["camera.resolution=16", *overrides]
    out = subprocess.run(
        [sys.executable, "-c", _WARM_THEN_RUN, json.dumps(ov)], capture_output=True, text=True, timeout=300, check=True
    )
    got = json.loads(out.stdout.splitlines()[-1])
    assert got["failed"] == [] and got["composed"] is False, got
    late = [m for m in got["new"] if not m.startswith(_LOADED_BY_THE_JOB)]
    assert late == [], f"loaded by the job after the warm-up: {late}"


def test_warm_up_is_called_per_distinct_target_and_reports_failures(monkeypatch: pytest.MonkeyPatch) -> None:
    """``warm_up`` calls a class's hook once per distinct parameters, reads nested targets, never
    imports a target outside the allow-list, and reports a failing hook as a line."""
    from nirspi_pipe.execute import warm_up
    from nirspi_pipe.sfs.models import LaxFriedrichsSFS

    calls: list[dict[str, object]] = []
    # monkeypatch restores the class as it was (its hook is inherited from SweepingSFS)
    monkeypatch.setattr(LaxFriedrichsSFS, "warm_up", classmethod(lambda cls, params: calls.append(dict(params))))
    node = {"_target_": "nirspi_pipe.sfs.models.LaxFriedrichsSFS", "backend": "numpy"}
    failed = warm_up(
        [{"sfs": node}, {"sfs": dict(node)}, {"a": [{"b": {**node, "tol": 0.1}}]}, {"x": {"_target_": "os.system"}}]
    )
    assert failed == [] and calls == [{"backend": "numpy"}, {"backend": "numpy", "tol": 0.1}]

    def boom(cls: type, params: object) -> None:
        raise RuntimeError("no compiler")

    monkeypatch.setattr(LaxFriedrichsSFS, "warm_up", classmethod(boom))
    assert warm_up([{"sfs": node}]) == ["nirspi_pipe.sfs.models.LaxFriedrichsSFS: RuntimeError: no compiler"]


_RUNNER_FIRST_SOLVE = r"""
import json, os, signal, warnings
from pathlib import Path
warnings.simplefilter("ignore")
from nirspi_pipe.execute import warm_up
from nirspi_pipe.sfs import opencl as ocl

warm_up([{"sfs": {"_target_": "nirspi_pipe.sfs.models.LaxFriedrichsSFS", "backend": "auto"}}])
contexts = ocl._context.cache_info().currsize
cache = Path(os.environ["POCL_CACHE_DIR"])
r, w = os.pipe()
pid = os.fork()
if pid == 0:  # a runner: builds its job's stages, then runs them
    signal.alarm(60)
    from nirspi_pipe.scene.objects import Sphere
    from nirspi_pipe.sfs.models import LaxFriedrichsSFS
    from nirspi_pipe.types import Camera, Image2D

    cam = Camera(resolution=32)
    img = Image2D(Sphere().render(cam).radiance)
    LaxFriedrichsSFS(backend="numpy").solve(img, cam)  # first calls outside OpenCL
    stage = LaxFriedrichsSFS(backend="auto")
    cached = sorted(str(p.relative_to(cache)) for p in cache.rglob("*") if p.is_file())
    built = ocl._program.cache_info().misses
    for _ in range(2):
        out = stage.solve(img, cam)
    new = sorted(set(str(p.relative_to(cache)) for p in cache.rglob("*.so")) - set(cached))
    report = {"backend": out.info["backend"], "cached": len(cached), "new": new,
              "builds": ocl._program.cache_info().misses - built}
    os.write(w, json.dumps(report).encode())
    os._exit(0)
os.close(w)
child = os.read(r, 4096).decode()
print(json.dumps({"contexts": contexts, "status": os.waitpid(pid, 0)[1], "child": json.loads(child or "null")}))
"""


@fork_only
def test_runner_warms_opencl_up_after_the_fork(tmp_path: Path) -> None:
    """The warm-up makes no OpenCL context in the sweeping process: one made before ``fork``
    leaves the child's first launch hanging (PoCL's worker threads are not forked; measured:
    killed by the 20 s alarm, whether the parent had only built the kernel or launched it too).
    So each runner warms up when it builds its first job's stages, and that job's SFS solves
    compile nothing (empty kernel caches: the old code's first solve took 315 ms then 2 ms in the
    table 6 sweep). Counted, not timed: no program build and no new PoCL work-group function
    (``.so`` in ``POCL_CACHE_DIR``) during the runner's solves."""
    import subprocess
    import sys

    from nirspi_pipe.sfs import opencl as ocl

    if not ocl.opencl_available():
        pytest.skip("no OpenCL device here builds float64 kernels")
    env = dict(os.environ, POCL_CACHE_DIR=str(tmp_path / "pocl"), XDG_CACHE_HOME=str(tmp_path / "xdg"))
    run = subprocess.run(
        [sys.executable, "-c", _RUNNER_FIRST_SOLVE], env=env, capture_output=True, text=True, timeout=180, check=True
    )
    got = json.loads(run.stdout.strip().splitlines()[-1])
    assert got["contexts"] == 0 and got["status"] == 0, got
    child = got["child"]
    assert child["backend"] == "opencl", got
    if not child["cached"]:
        pytest.skip("the OpenCL platform here is not PoCL with its kernel cache: its compilations cannot be counted")
    assert child["builds"] == 0 and child["new"] == [], f"the runner's first SFS solves compiled: {child}"
