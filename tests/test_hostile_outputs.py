"""Hostile outputs (issue 24, items 2, 4, 5 and 6): no writes through links, a deadline per job,
exit codes that tell the truth, and a full disk (docs/hostile.md, docs/sweeps.md)."""

from __future__ import annotations

import errno
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest

from conftest import script
from nirspi_pipe import outputfiles
from nirspi_pipe.app import jobs
from nirspi_pipe.app.jobcomposer import ComposedJob
from nirspi_pipe.outputfiles import JobLock, OutputError
from nirspi_pipe.records import RECORD_NAME, read_record, write_record

fork_only = pytest.mark.skipif(not hasattr(os, "fork"), reason="runners are forked")
linux_only = pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="finds a file's name in /proc/self/fd")

_SMALL = ["camera.resolution=16"]


def _tree(folder: Path) -> dict[str, bytes]:
    """Every file below ``folder`` with its content (what a write through a link would change)."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _lines(text: str) -> list[str]:
    return [ln for ln in text.splitlines() if ln.strip()]


# -- 2. no writes through links -------------------------------------------------------------------


def test_a_linked_folder_is_refused_and_a_linked_file_is_replaced(tmp_path: Path) -> None:
    """``atomic_write`` (every record, array, PNG, attempts and results file) refuses a folder
    that is a symbolic link, in one line naming it; a file that is one is replaced by the rename,
    and its target keeps its content."""
    target = tmp_path / "target"
    target.mkdir()
    (target / "mine.txt").write_text("keep")
    link = tmp_path / "job"
    link.symlink_to(target)
    with pytest.raises(OutputError) as info:
        write_record(link, {"meta": {"status": "ok"}})
    assert "symbolic link" in str(info.value) and str(link) in str(info.value) and "\n" not in str(info.value)
    assert _tree(target) == {"mine.txt": b"keep"}

    real = tmp_path / "real"
    real.mkdir()
    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    (real / RECORD_NAME).symlink_to(victim)
    write_record(real, {"meta": {"status": "ok"}})
    assert not (real / RECORD_NAME).is_symlink() and read_record(real / RECORD_NAME)["meta"]["status"] == "ok"
    assert victim.read_text() == "keep"

    (real / "summary.png").symlink_to(victim)  # written in place by matplotlib: the link goes first
    outputfiles.drop_links(real, ("summary.png", "mesh.ply"))
    assert not (real / "summary.png").exists() and victim.read_text() == "keep"


def test_the_tables_never_write_through_a_link(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The paper tables write their files in place (pandas, matplotlib): a linked file in
    ``tables/`` is removed first (its target kept), and a ``tables`` folder that is a link is
    refused in one line, with no table built."""
    from nirspi_pipe.app.results import build_tables

    victim = tmp_path / "victim.txt"
    victim.write_text("keep")
    sweep = tmp_path / "sweep"
    (sweep / "tables").mkdir(parents=True)
    (sweep / "tables" / "table2.csv").symlink_to(victim)
    build_tables(pd.DataFrame({"status": ["ok"]}), sweep, ["table2"])  # fails on this frame: after the links
    assert victim.read_text() == "keep" and not (sweep / "tables" / "table2.csv").is_symlink()

    other = tmp_path / "other"
    other.mkdir()
    shutil.rmtree(sweep / "tables")
    (sweep / "tables").symlink_to(other)
    assert build_tables(pd.DataFrame({"status": ["ok"]}), sweep, ["table2"]) == []
    assert list(other.iterdir()) == []
    assert "no table built: tables folder" in capsys.readouterr().err


def test_the_job_lock_never_follows_a_link(tmp_path: Path) -> None:
    """The lock file was opened with O_CREAT and truncated: a ``.lock`` linked to a file would
    have emptied it. Now the link is replaced; a job folder that is a link is refused."""
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    folder = tmp_path / "job"
    folder.mkdir()
    (folder / ".lock").symlink_to(victim)
    lock = JobLock(folder)
    assert lock.acquire(wait=False)
    lock.release()
    assert victim.read_text() == "precious" and not (folder / ".lock").is_symlink()

    linked = tmp_path / "linked"
    linked.symlink_to(folder)
    with pytest.raises(OutputError, match="job folder .*linked is a symbolic link"):
        JobLock(linked).acquire(wait=False)


@pytest.mark.slow
def test_a_rerun_never_writes_into_a_linked_job_folder(cli) -> None:
    """A sweep's rerun where one job folder was replaced by a link to another folder: the job is
    refused (one line naming the link), nothing appears in the link's target, the other jobs
    run, its row is failed, and the sweep exits 1."""
    args = ["nirspi-run", "-m", "seed=0,1,2", *_SMALL, "hydra.sweep.dir=sweep", "hydra.sweeper.resume=false"]
    first = cli(*args)
    assert first.returncode == 0, first.stderr
    sweep = cli.cwd / "sweep"
    victim_key = sorted(p.name for p in sweep.iterdir() if p.is_dir())[0]
    elsewhere = cli.cwd / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / "mine.txt").write_text("keep")
    shutil.rmtree(sweep / victim_key)
    (sweep / victim_key).symlink_to(elsewhere)
    before = {p.name: p.stat().st_mtime_ns for p in sweep.glob("*/record.json")}
    again = cli(*args)
    assert again.returncode == 1, again.stdout + again.stderr
    assert _tree(elsewhere) == {"mine.txt": b"keep"}  # nothing written through the link
    assert "1 refused (job folder is a symbolic link)" in again.stdout
    assert f"job folder {Path('sweep') / victim_key} is a symbolic link" in again.stderr
    assert "Traceback" not in again.stderr
    df = pd.read_parquet(sweep / "results.parquet").set_index("job")
    assert df.loc[victim_key, "status"] == "failed" and "symbolic link" in df.loc[victim_key, "error"]
    assert (df.drop(index=victim_key)["status"] == "ok").all()
    after = {p.name: p.stat().st_mtime_ns for p in sweep.glob("*/record.json")}
    assert set(after) == set(before) and all(after[k] > before[k] for k in after)  # the others reran


@pytest.mark.slow
def test_a_single_run_refuses_a_linked_output_folder(cli) -> None:
    """``hydra.run.dir`` that is a link: one line, exit 1, nothing written into its target (not
    even Hydra's ``.hydra/``). A ``summary.png`` linked to a file in a real run folder: replaced,
    the file kept."""
    elsewhere = cli.cwd / "elsewhere"
    elsewhere.mkdir()
    (cli.cwd / "run").symlink_to(elsewhere)
    res = cli("nirspi-run", *_SMALL, "hydra.run.dir=run")
    assert res.returncode == 1
    assert _lines(res.stderr) == [
        "nirspi-run: error: output folder (hydra.run.dir) run is a symbolic link (to "
        f"{elsewhere}); refused: nothing is written through links (remove the link, or choose another folder)"
    ]
    assert list(elsewhere.iterdir()) == []

    real = cli.cwd / "real"
    real.mkdir()
    victim = cli.cwd / "victim.txt"
    victim.write_text("keep")
    (real / "summary.png").symlink_to(victim)
    res = cli("nirspi-run", *_SMALL, "hydra.run.dir=real")
    assert res.returncode == 0, res.stderr
    assert victim.read_text() == "keep"
    assert (real / "summary.png").is_file() and not (real / "summary.png").is_symlink()


# -- 4. a deadline per job: tests/test_launcher.py::test_a_hanging_job_is_killed_at_its_deadline ----


@pytest.mark.slow
def test_the_deadline_reaches_the_launcher_from_the_command_line(cli) -> None:
    """``hydra.launcher.timeout_s`` set below any job's duration (a 16x16 job's pipeline alone
    took 42-148 ms in ``wall_s``): every job is a failed row naming the deadline, exit 1."""
    res = cli("nirspi-run", "-m", "seed=0,1", *_SMALL, "hydra.sweep.dir=sweep", "hydra.launcher.timeout_s=0.001")
    assert res.returncode == 1
    df = pd.read_parquet(cli.cwd / "sweep" / "results.parquet")
    assert len(df) == 2 and (df["status"] == "failed").all()
    assert df["error"].str.contains("deadline of 0.001 s (hydra.launcher.timeout_s)", regex=False).all()
    assert "2 of 2 jobs did not finish ok (2 failed: 2x job killed after its deadline" in res.stderr


# -- 5. exit codes ----------------------------------------------------------------------------------


@pytest.mark.slow
def test_failed_jobs_exit_non_zero_unless_allowed(cli) -> None:
    """One job of three fails: exit 1 and one line naming how many and why; with
    ``hydra.sweeper.allow_failures=true`` the same sweep exits 0 (its rows unchanged)."""
    args = ["nirspi-run", "-m", "scene.reflectance=0.5,1.5,0.2", *_SMALL, "output.images=false"]
    res = cli(*args, "hydra.sweep.dir=a")
    assert res.returncode == 1
    last = _lines(res.stderr)[-1]
    assert last.startswith("nirspi-run: error: 1 of 3 jobs did not finish ok (1 failed: 1x scene.reflectance=1.5")
    assert last.endswith("; hydra.sweeper.allow_failures=true exits 0")
    allowed = cli(*args, "hydra.sweep.dir=b", "hydra.sweeper.allow_failures=true")
    assert allowed.returncode == 0, allowed.stderr
    assert list(pd.read_parquet(cli.cwd / "b" / "results.parquet")["status"]) == ["ok", "failed", "ok"]
    bad = cli(*args, "hydra.sweep.dir=c", "hydra.sweeper.allow_failures=maybe")
    assert bad.returncode != 0 and "hydra.sweeper.allow_failures='maybe'" in bad.stderr


@pytest.mark.slow
def test_a_launcher_that_cannot_start_exits_non_zero(cli, tmp_path: Path) -> None:
    """``hydra/launcher=slurm`` where there is no ``srun``: the launcher is not retried in vain,
    every job is a missing row, and the sweep exits 1 naming how many and why."""
    bin_dir = tmp_path / "bin"  # PATH without srun (a CI machine may have SLURM): git for provenance
    bin_dir.mkdir()
    if shutil.which("git"):
        (bin_dir / "git").symlink_to(shutil.which("git"))  # type: ignore[arg-type]
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{bin_dir}", MPLBACKEND="Agg")
    res = subprocess.run(
        [script("nirspi-run"), "-m", "hydra/launcher=slurm", "seed=0,1", *_SMALL, "hydra.sweep.dir=sweep"],
        cwd=cli.cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert res.returncode == 1, res.stdout + res.stderr
    assert res.stderr.count("the launcher failed") == 2  # the warning, then the reason in the error
    assert "launching the 2 jobs without a record again" not in res.stdout
    last = _lines(res.stderr)[-1]
    assert last.startswith("nirspi-run: error: 2 of 2 jobs did not finish ok (2 missing: 2x no record")
    assert 'the launcher failed 1 time(s): RuntimeError: Could not detect "srun"' in last
    assert (pd.read_parquet(cli.cwd / "sweep" / "results.parquet")["status"] == "missing").all()


# -- 6. disk full -----------------------------------------------------------------------------------


def _fake_execute(config, out_dir, choices, overrides, job_num, attempt=None):  # type: ignore[no-untyped-def]
    write_record(out_dir, {"meta": {"status": "ok", "attempt": attempt}})
    return {}


@fork_only
def test_a_job_whose_folder_cannot_be_written_fails_alone(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """In-process: the disk is full when the launcher counts one job's attempt (``attempts.json``,
    which used to end the whole sweep with no ``results.parquet``): that job is a failed
    (unwritten) record naming the file, the others run."""
    import nirspi_pipe.app.launcher as launcher

    real = jobs._bump_attempts

    def full_for_job1(folder: Path) -> int:
        if Path(folder).name == "job1":
            raise outputfiles._write_failure(Path(folder) / "attempts.json", OSError(errno.ENOSPC, "No space left"))
        return real(folder)

    monkeypatch.setattr(launcher, "_execute", _fake_execute)
    monkeypatch.setattr(jobs, "_bump_attempts", full_for_job1)
    monkeypatch.setattr(jobs, "unwritten_jobs", [])
    items = [(tmp_path / f"job{i}", i, ComposedJob({}, {}, [])) for i in range(3)]
    returns = launcher.NirspiLauncherBase(n_jobs=2)._run(items, tmp_path, None, False)
    metas = [r.return_value["meta"] for r in returns]
    assert [m["status"] for m in metas] == ["ok", "failed", "ok"]
    assert metas[1]["error"] == f"cannot write {tmp_path / 'job1' / 'attempts.json'}: no space left on device"
    assert not (tmp_path / "job1" / RECORD_NAME).exists()
    assert [d.name for d, _ in jobs.unwritten_jobs] == ["job1"]


#: ``nirspi-run`` with a full disk for the files whose names match ``NIRSPI_TEST_FULL`` (a
#: regular expression): ``atomic_write``'s temporary file ``.<name>.<random>.tmp`` gets ENOSPC on
#: its first write, as a full file system gives it. Every other file is written.
_FULL_DISK = r"""
import errno, os, re, sys

full = re.compile(os.environ["NIRSPI_TEST_FULL"])
real_fdopen = os.fdopen


class Full:
    def __init__(self, fh):
        self.fh = fh

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.fh.close()

    def write(self, data):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def fdopen(fd, *args, **kwargs):
    fh = real_fdopen(fd, *args, **kwargs)
    try:
        name = os.path.basename(os.readlink(f"/proc/self/fd/{fd}"))
    except OSError:
        return fh
    temp = re.fullmatch(r"\.(.+)\.[^.]+\.tmp", name)
    return Full(fh) if temp and full.fullmatch(temp.group(1)) else fh


os.fdopen = fdopen
from nirspi_pipe.app.cli import run

sys.argv[0] = "nirspi-run"
run()
"""


def _run_full(cwd: Path, full: str, *args: str) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k not in ("HYDRA_FULL_ERROR", "NIRSPI_TRACEBACK")}
    env.update(MPLBACKEND="Agg", NIRSPI_TEST_FULL=full)
    return subprocess.run(
        [sys.executable, "-c", _FULL_DISK, *args], cwd=cwd, env=env, capture_output=True, text=True, timeout=300
    )


@pytest.mark.slow
@linux_only
def test_disk_full_in_a_single_run_is_one_line_naming_what_exists(tmp_path: Path) -> None:
    """A full disk for ``arrays.npz``: one line naming it, exit 1, and no ``error.txt`` named or
    left (an older run's is removed with the record it belonged to); for every file: one line."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "error.txt").write_text("an older run's traceback")
    res = _run_full(tmp_path, r"arrays\.npz", *_SMALL, "hydra.run.dir=run")
    assert res.returncode == 1
    message = f"nirspi-run: error: cannot write {run.resolve() / 'arrays.npz'}: no space left on device"
    assert _lines(res.stderr) == [message]
    assert not (run / "error.txt").exists() and not (run / "arrays.npz").exists()
    assert read_record(run / RECORD_NAME)["meta"]["error_type"] == "OutputError"

    res = _run_full(tmp_path, r".*", *_SMALL, "hydra.run.dir=run2")
    assert res.returncode == 1
    lines = _lines(res.stderr)
    assert len(lines) == 1 and lines[0].endswith("no space left on device"), res.stderr
    assert "Traceback" not in res.stderr and "error.txt" not in res.stderr


@pytest.mark.slow
@linux_only
def test_disk_full_in_a_sweep_is_one_line_per_job_and_results_are_written(tmp_path: Path) -> None:
    """No PNG can be written: the jobs with images fail (one line each, naming the file, no
    traceback), the jobs without run; ``results.parquet`` holds them all; exit 1 with the count.
    Then no record or attempt count can be written at all: every job is a missing row,
    ``results.parquet`` is still written, no traceback."""
    res = _run_full(
        tmp_path, r".*\.png", "-m", "seed=0,1", "output.images=true,false", *_SMALL, "hydra.sweep.dir=sweep"
    )
    assert res.returncode == 1, res.stderr
    assert "Traceback" not in res.stdout + res.stderr, res.stdout + res.stderr
    df = pd.read_parquet(tmp_path / "sweep" / "results.parquet")
    images = df["job"].map(lambda j: json.loads((tmp_path / "sweep" / j / RECORD_NAME).read_text())["config"])
    with_images = images.map(lambda c: c["output"]["images"])
    assert list(df.loc[~with_images, "status"]) == ["ok", "ok"]
    assert df.loc[~with_images, "metrics.ssim"].notna().all()
    assert list(df.loc[with_images, "status"]) == ["failed", "failed"]
    assert df.loc[with_images, "error"].str.fullmatch(r"cannot write \S+\.png: no space left on device").all()
    assert _lines(res.stderr)[-1].startswith("nirspi-run: error: 2 of 4 jobs did not finish ok (2 failed: 1x cannot")

    res = _run_full(tmp_path, r"record\.json|attempts\.json", "-m", "seed=0,1", *_SMALL, "hydra.sweep.dir=sweep2")
    assert res.returncode == 1
    assert "Traceback" not in res.stdout + res.stderr, res.stdout + res.stderr
    df = pd.read_parquet(tmp_path / "sweep2" / "results.parquet")
    assert list(df["status"]) == ["missing", "missing"]
    errors = [ln for ln in _lines(res.stdout + res.stderr) if "no space left on device" in ln and "failed:" in ln]
    assert len(errors) == 2 and all("attempts.json" in ln for ln in errors), res.stderr
    assert _lines(res.stderr)[-1].startswith("nirspi-run: error: 2 of 2 jobs did not finish ok (2 missing")


def test_timeout_s_is_checked() -> None:
    from nirspi_pipe.app.launcher import DEFAULT_TIMEOUT_S, NirspiLauncherBase
    from nirspi_pipe.errors import ConfigError

    assert NirspiLauncherBase().timeout_s == DEFAULT_TIMEOUT_S == 1800
    assert NirspiLauncherBase(timeout_s=None).timeout_s is None
    for bad in (0, -1, float("nan"), float("inf"), True, "10"):
        with pytest.raises(ConfigError, match="hydra.launcher.timeout_s"):
            NirspiLauncherBase(timeout_s=bad)  # type: ignore[arg-type]


@pytest.fixture
def full_disk(tmp_path: Path):  # type: ignore[no-untyped-def]
    """A 256 KiB tmpfs filled to the last byte (root only, where mounting is allowed; else skipped)."""
    disk = tmp_path / "disk"
    disk.mkdir()
    mount = shutil.which("mount")
    if mount is None or os.geteuid() != 0:
        pytest.skip("mounting a small tmpfs needs root")
    done = subprocess.run([mount, "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(disk)], capture_output=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.decode(errors='replace').strip()}")
    try:
        with open(disk / "filler", "wb", buffering=0) as fh:  # unbuffered: nothing left to flush
            for size in (4096, 1):
                try:
                    while True:
                        fh.write(b"\0" * size)
                except OSError as exc:
                    assert exc.errno == errno.ENOSPC
        assert shutil.disk_usage(disk).free == 0
        yield disk
    finally:
        subprocess.run(["umount", str(disk)], capture_output=True)


@pytest.mark.slow
def test_a_really_full_disk_is_one_line(full_disk: Path) -> None:
    """A real full file system (no injection): a single run and a sweep each end with one line
    naming the file that could not be written, exit 1, no traceback (Hydra's own ``.hydra/``
    writes used to give one before nirspi-pipe's code ran: ``hydra.output_subdir`` is now null)."""
    env = {k: v for k, v in os.environ.items() if k not in ("HYDRA_FULL_ERROR", "NIRSPI_TRACEBACK")}
    env["MPLBACKEND"] = "Agg"
    for args, name in (
        ([*_SMALL, "hydra.run.dir=run"], "run/record.json"),
        (["-m", "seed=0,1", *_SMALL, "hydra.sweep.dir=sweep"], "sweep/multirun.yaml"),
    ):
        res = subprocess.run(
            [script("nirspi-run"), *args], cwd=full_disk, env=env, capture_output=True, text=True, timeout=300
        )
        assert res.returncode == 1, res.stderr
        lines = _lines(res.stderr)
        assert len(lines) == 1 and "Traceback" not in res.stdout, res.stdout + res.stderr
        assert lines[0].startswith("nirspi-run: error: cannot write ") and lines[0].endswith(
            f"{name}: no space left on device"
        ), lines
