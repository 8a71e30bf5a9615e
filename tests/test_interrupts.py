"""Ctrl-C is never lost (:mod:`nirspi_pipe.app.ctrlc`): a ``SIGINT`` that lands inside an
``os.fork`` callback, where Python drops the ``KeyboardInterrupt`` ("Exception ignored in"), still
stops the launcher (fast, in-process) and a study, which then says what finished and how to resume
(slow, through the CLI). CI at 81cf288: a study interrupted while forking a runner ran on and
exited 0."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path

import pytest

from nirspi_pipe.app import ctrlc
from nirspi_pipe.app.jobcomposer import ComposedJob
from nirspi_pipe.records import RECORD_NAME, read_record

fork_only = pytest.mark.skipif(not hasattr(os, "fork"), reason="runners are forked")

# -- a SIGINT delivered inside the fork callbacks of the n-th fork ----------------------------------
# os.register_at_fork cannot be undone: the callbacks stay registered, disarmed (0) outside the tests.
_FORKS = {"n": 0, "parent_at": 0, "child_at": 0}
_CHILD_PID_FILE: list[Path] = []


def _count_fork() -> None:
    _FORKS["n"] += 1


def _sigint_in_parent() -> None:
    if _FORKS["n"] == _FORKS["parent_at"]:
        os.kill(os.getpid(), signal.SIGINT)  # the handler runs here, inside the callback


def _sigint_in_child() -> None:
    if _FORKS["n"] == _FORKS["child_at"]:
        if _CHILD_PID_FILE:
            _CHILD_PID_FILE[0].write_text(str(os.getpid()))
        os.kill(os.getpid(), signal.SIGINT)


if hasattr(os, "register_at_fork"):
    os.register_at_fork(before=_count_fork, after_in_parent=_sigint_in_parent, after_in_child=_sigint_in_child)


@pytest.fixture
def terminal_sigint() -> Iterator[None]:
    """Python's default SIGINT handling (a terminal's process; a test worker may ignore SIGINT),
    forks counted from here, and the fork callbacks disarmed afterwards."""
    from nirspi_pipe.provenance import provenance

    provenance()  # its OpenCL query forks once per process (cached): not one of the forks counted
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    _FORKS.update(n=0, parent_at=0, child_at=0)
    try:
        yield
    finally:
        _FORKS.update(n=0, parent_at=0, child_at=0)
        _CHILD_PID_FILE.clear()
        signal.signal(signal.SIGINT, before)


def _job(config, out_dir, choices, overrides, job_num, attempt=None):  # type: ignore[no-untyped-def]
    """A quick job: ``how == "exit"`` ends its runner (a fresh runner is forked), else an ok record."""
    from nirspi_pipe.records import write_record

    if config["how"] == "exit":
        os._exit(5)
    write_record(out_dir, {"meta": {"status": "ok", "attempt": attempt, "pid": os.getpid()}})
    return {}


def _items(tmp_path: Path, hows: list[str]) -> list[tuple[Path, int, ComposedJob]]:
    return [(tmp_path / f"job{i}", i, ComposedJob({"how": h}, {}, [f"how={h}"])) for i, h in enumerate(hows)]


@fork_only
def test_a_ctrl_c_inside_a_fork_callback_stops_the_launcher(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, terminal_sigint: None
) -> None:
    """The runner after a crash is forked with a SIGINT delivered in logging's place (the parent's
    fork callback): the launcher raises KeyboardInterrupt before it sends another job (before the
    fix it ran all six), and SIGINT is Python's default again afterwards."""
    import nirspi_pipe.app.launcher as launcher

    monkeypatch.setattr(launcher, "_execute", _job)
    items = _items(tmp_path, ["ok", "exit", "ok", "ok", "ok", "ok"])
    _FORKS["parent_at"] = 2  # fork 1: the first runner; fork 2: the one replacing it after "exit"
    with pytest.raises(KeyboardInterrupt):
        launcher.NirspiLauncherBase(n_jobs=1)._run(items, tmp_path, None, False)
    assert _FORKS["n"] == 2  # no runner forked after the interrupt
    assert read_record(tmp_path / "job0" / RECORD_NAME)["meta"]["status"] == "ok"
    assert read_record(tmp_path / "job1" / RECORD_NAME)["meta"]["exit_code"] == 5
    assert not any((out_dir / RECORD_NAME).exists() for out_dir, _, _ in items[2:])
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


@fork_only
def test_a_ctrl_c_inside_a_runners_fork_callback_stops_that_runner(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, terminal_sigint: None
) -> None:
    """A SIGINT that reaches a runner in its own fork callback stops it as one at any other moment
    does (exit 130, the code of a process ended by Ctrl-C), so that runner runs no job (before the
    fix it ran them all). The launcher, not interrupted, runs every job: each on a fresh runner, or
    a crash record of the stopped one naming code 130."""
    import nirspi_pipe.app.launcher as launcher

    monkeypatch.setattr(launcher, "_execute", _job)
    items = _items(tmp_path, ["ok", "ok", "ok"])
    _CHILD_PID_FILE.append(tmp_path / "stopped.pid")
    _FORKS["child_at"] = 1
    launcher.NirspiLauncherBase(n_jobs=1)._run(items, tmp_path, None, False)
    stopped = int((tmp_path / "stopped.pid").read_text())
    metas = [read_record(out_dir / RECORD_NAME)["meta"] for out_dir, _, _ in items]
    assert all(m.get("pid") != stopped for m in metas)
    assert all(m["status"] == "ok" or m["exit_code"] == ctrlc.INTERRUPTED_EXIT for m in metas), metas
    assert [m["status"] for m in metas[1:]] == ["ok", "ok"]


# -- the guard itself -------------------------------------------------------------------------------


def test_a_recorded_ctrl_c_is_raised_at_the_next_check_and_at_the_end(terminal_sigint: None) -> None:
    with pytest.raises(KeyboardInterrupt), ctrlc.guarded():
        os.kill(os.getpid(), signal.SIGINT)  # recorded, not raised: outside an interruptible block
        assert ctrlc.pending() is not None
        with pytest.raises(KeyboardInterrupt):
            ctrlc.check()
        with pytest.raises(KeyboardInterrupt), ctrlc.interruptible():
            pass  # raised on entry
    assert ctrlc.pending() is None and signal.getsignal(signal.SIGINT) is signal.default_int_handler
    with ctrlc.guarded(), ctrlc.guarded():  # nested: nothing recorded, nothing raised
        ctrlc.check()
    with pytest.raises(KeyboardInterrupt), ctrlc.guarded(), ctrlc.interruptible():
        os.kill(os.getpid(), signal.SIGINT)  # inside an interruptible block: raised at once
        pytest.fail("not raised at once")


def test_an_ignored_sigint_stays_ignored(terminal_sigint: None) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # nohup, or a background job of a script
    with ctrlc.guarded():
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
        os.kill(os.getpid(), signal.SIGINT)
        ctrlc.check()
    assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN


# -- a study through the CLI ------------------------------------------------------------------------

_STUDY = [
    "hydra/sweeper=optuna",
    "hydra/sweeper/sampler=random",
    "hydra.sweeper.sampler.seed=2",
    "hydra.sweeper.direction=[maximize,minimize]",
    "preset=null",
    "camera.resolution=8",
    "fog=none",
    "illumination=none",
    "detector=ideal",
    "output.images=false",
    "output.arrays=false",
    "solver=choice(fwht,lstsq)",
    "scan.ratio=interval(0.25,1.0)",
    "hydra.sweep.dir=sweep",
    "objective=[metrics.psnr,timings_ms.solver]",
    "hydra.sweeper.n_trials=6",
    "hydra.sweeper.n_jobs=1",
]

#: ``nirspi-run`` with a SIGINT sent to itself inside the parent's callback of its first fork
#: after two trials finished (the third trial's runner: a batch is one trial here).
_BOOT = textwrap.dedent(
    """
    import os, signal, sqlite3, sys
    fired = []
    def hit():
        if fired or not os.path.exists("sweep/sweep.db"):
            return
        with sqlite3.connect("sweep/sweep.db", timeout=30) as con:
            done = con.execute("select count(*) from trials where state = 'COMPLETE'").fetchone()[0]
        if done >= 2:
            fired.append(done)
            os.kill(os.getpid(), signal.SIGINT)
    os.register_at_fork(after_in_parent=hit)
    from nirspi_pipe.app.cli import run
    sys.argv = ["nirspi-run", *sys.argv[1:]]
    run()
    """
)


@pytest.mark.slow
@fork_only
def test_a_study_interrupted_inside_a_fork_callback_ends_and_resumes(cli) -> None:
    """Interrupted while forking the third trial's runner: two trials finished, the third is
    marked interrupted before its job ran; exit 130, one line, and its resume command (asking for
    one trial more than finished) runs exactly one. Before the fix the study ran all six trials
    and exited 0."""
    import shlex
    import sqlite3

    pytest.importorskip("optuna", reason="pip install '.[optuna]'")
    env = {k: v for k, v in os.environ.items() if k not in ("HYDRA_FULL_ERROR", "NIRSPI_TRACEBACK")}
    env.update(MPLBACKEND="Agg")
    proc = subprocess.run(
        [sys.executable, "-c", _BOOT, "-m", *_STUDY], cwd=cli.cwd, env=env, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 130, proc.stdout[-2000:] + proc.stderr[-2000:]
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("nirspi-run: interrupted:")]
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert "2 trials finished ok and 0 failed of 6" in lines[0]
    sweep = Path(cli.cwd) / "sweep"
    with sqlite3.connect(sweep / "sweep.db") as con:
        states = [s for (s,) in con.execute("select state from trials order by number")]
    assert states == ["COMPLETE", "COMPLETE", "FAIL"]  # the third: marked interrupted, not counted
    listed = json.loads((sweep / "sweep.json").read_text())["jobs"]
    assert sorted(j["trial"] for j in listed) == [0, 1]
    resume = shlex.split(lines[0].split("resume: ", 1)[1])
    assert resume[0] == "nirspi-run" and "hydra.sweeper.n_trials=6" in resume
    again = cli(*[("hydra.sweeper.n_trials=3" if a == "hydra.sweeper.n_trials=6" else a) for a in resume])
    assert again.returncode == 0, again.stderr
    assert "2 of 3 trials finished or running, 1 to run" in again.stdout
