"""Records you can trust (issue 12): atomic writes, disk-full and unwritable outputs, per-job
locks, content-aware job keys, provenance decided from the package's own location, crash records
and a strict ``sweep.json`` reader."""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from nirspi_pipe import jobkey, outputfiles, provenance
from nirspi_pipe.app.jobcomposer import expand_grid
from nirspi_pipe.app.jobs import crash_message, run_sweep_job
from nirspi_pipe.app.sweepfile import SweepFileError, load_sweep_file
from nirspi_pipe.jobkey import InputHasher, input_files, job_key_of
from nirspi_pipe.outputfiles import JobLock, OutputError
from nirspi_pipe.provenance import code_identity
from nirspi_pipe.records import RECORD_NAME, read_record, write_record


def _leftovers(folder: Path) -> list[str]:
    return [p.name for p in folder.iterdir() if p.name.endswith(".tmp")]


# -- atomic writes ------------------------------------------------------------------------------


def test_concurrent_writers_never_tear_a_record(tmp_path: Path) -> None:
    """Two writers rewriting one record while a reader reads it: every read parses (the issue saw
    ~1 % torn or empty reads with the fixed ``record.json.tmp`` name)."""
    stop = threading.Event()
    errors: list[BaseException] = []

    def writer(tag: int) -> None:
        payload = {"meta": {"status": "ok", "writer": tag}, "metrics": {f"m{i}": i for i in range(300)}}
        try:
            for _ in range(150):
                write_record(tmp_path, payload)
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=writer, args=(t,)) for t in (1, 2)]
    for t in threads:
        t.start()
    reads = 0
    deadline = time.monotonic() + 60
    while any(t.is_alive() for t in threads) and time.monotonic() < deadline:
        try:
            rec = read_record(tmp_path / RECORD_NAME)
        except FileNotFoundError:
            continue
        assert rec["meta"]["status"] == "ok" and len(rec["metrics"]) == 300
        reads += 1
    stop.set()
    for t in threads:
        t.join(timeout=60)
    assert not errors, errors
    assert reads > 0
    assert _leftovers(tmp_path) == []


def test_disk_full_is_one_line_and_leaves_the_old_record(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    write_record(tmp_path, {"meta": {"status": "ok"}, "metrics": {"a": 1.0}})

    class Full:
        def __init__(self, fd: int, mode: str) -> None:
            self.fh = open(fd, mode)  # closed in __exit__

        def __enter__(self) -> Full:
            return self

        def __exit__(self, *exc: object) -> None:
            self.fh.close()

        def write(self, data: bytes) -> int:
            self.fh.write(data[: len(data) // 2])  # half of it reaches the disk, then ENOSPC
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(outputfiles.os, "fdopen", Full)
    with pytest.raises(OutputError) as info:
        write_record(tmp_path, {"meta": {"status": "ok"}, "metrics": {"a": 2.0}})
    message = str(info.value)
    assert "\n" not in message and str(tmp_path / RECORD_NAME) in message and "no space left" in message
    monkeypatch.undo()
    assert read_record(tmp_path / RECORD_NAME)["metrics"] == {"a": 1.0}  # no half-written record
    assert _leftovers(tmp_path) == []


def test_unwritable_folder_is_one_line(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("a file where a folder should be")
    with pytest.raises(OutputError) as info:
        write_record(blocker / "job", {"meta": {}})
    assert "\n" not in str(info.value) and str(blocker / "job" / RECORD_NAME) in str(info.value)
    if os.geteuid() != 0:  # root ignores permission bits
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        try:
            with pytest.raises(OutputError, match="ro/record.json"):
                write_record(ro, {"meta": {}})
        finally:
            ro.chmod(0o700)


def test_cli_single_run_into_an_unwritable_place_is_one_line(cli) -> None:
    (cli.cwd / "blocker").write_text("x")
    res = cli("nirspi-run", "camera.resolution=16", "hydra.run.dir=blocker/run", timeout=300)
    assert res.returncode != 0
    assert "Traceback" not in res.stderr, res.stderr[-2000:]


# -- locks ----------------------------------------------------------------------------------------


_HOLD = """
import sys, time
from pathlib import Path
from nirspi_pipe.outputfiles import JobLock
lock = JobLock(Path(sys.argv[1]))
assert lock.acquire()
print("held", flush=True)
time.sleep(60)
"""


def test_job_lock_excludes_and_is_never_stale(tmp_path: Path) -> None:
    holder = subprocess.Popen([sys.executable, "-c", _HOLD, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        lock = JobLock(tmp_path)
        assert not lock.acquire(wait=False)  # held by another process
        holder.send_signal(signal.SIGKILL)  # dies without releasing anything
        holder.wait(timeout=30)
        assert lock.acquire(wait=False)  # the kernel released it: no stale lock
        lock.release()
    finally:
        if holder.poll() is None:
            holder.kill()
            holder.wait(timeout=30)


# -- content-aware keys ---------------------------------------------------------------------------


def test_input_files_change_the_job_key(tmp_path: Path) -> None:
    rec = tmp_path / "rec.npz"
    rec.write_bytes(b"first recording")
    config = {
        "source": {"path": str(rec), "nested": [{"weights": "rec.npz"}]},
        "scene": {"path": "skimage:camera"},
        "hydra": {"x": str(rec)},
    }
    found = input_files(config, base=tmp_path)
    assert set(found) == {"source.path", "source.nested[0].weights"}  # any key; hydra node left out
    hasher = InputHasher()
    key1 = job_key_of(config, hasher.hashes(config, base=tmp_path))
    assert key1 == job_key_of(config, InputHasher().hashes(config, base=tmp_path))  # deterministic
    assert job_key_of({"a": 1}, {}) == jobkey.config_hash({"a": 1})  # no inputs: the config hash
    st = rec.stat()
    rec.write_bytes(b"other recording")  # same size and path, new content
    os.utime(rec, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000))
    key2 = job_key_of(config, hasher.hashes(config, base=tmp_path))
    assert key2 != key1


def test_input_hashes_are_cached_by_size_and_mtime(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    f = tmp_path / "w.npz"
    f.write_bytes(b"x" * 1000)
    hasher = InputHasher()
    first = hasher.digest(f)
    opened: list[str] = []
    real_open = open
    monkeypatch.setattr("builtins.open", lambda p, *a, **k: (opened.append(str(p)), real_open(p, *a, **k))[1])
    assert hasher.digest(f) == first and opened == []  # cached: not read again


# -- provenance -----------------------------------------------------------------------------------


def _git_available() -> bool:
    return shutil.which("git") is not None


@pytest.mark.skipif(not _git_available(), reason="git is not installed")
def test_provenance_never_runs_git_in_the_callers_directory(tmp_path: Path) -> None:
    """Inside an unrelated repository whose fsmonitor hook would leave a mark, provenance names
    the package's own code and runs nothing of that repository."""
    other = tmp_path / "other"
    other.mkdir()
    marker = tmp_path / "fsmonitor-ran"
    hook = tmp_path / "hook.sh"
    hook.write_text(f"#!/bin/sh\ntouch {marker}\n")
    hook.chmod(0o755)
    env = {
        **os.environ,
        "GIT_AUTHOR_NAME": "t",
        "GIT_AUTHOR_EMAIL": "t@t",
        "GIT_COMMITTER_NAME": "t",
        "GIT_COMMITTER_EMAIL": "t@t",
    }
    for cmd in (["init", "-q"], ["config", "core.fsmonitor", str(hook)], ["commit", "-q", "--allow-empty", "-m", "x"]):
        subprocess.run(["git", *cmd], cwd=other, check=True, env=env, capture_output=True)
    other_sha = subprocess.run(
        ["git", "rev-parse", "HEAD"], cwd=other, capture_output=True, text=True, env=env
    ).stdout.strip()
    marker.unlink(missing_ok=True)
    code = "import json; from nirspi_pipe.provenance import code_identity; print(json.dumps(code_identity()))"
    out = subprocess.run([sys.executable, "-c", code], cwd=other, capture_output=True, text=True, timeout=120, env=env)
    assert out.returncode == 0, out.stderr
    ident = json.loads(out.stdout)
    assert ident["git_sha"] != other_sha
    assert not marker.exists(), "git ran the caller's repository's fsmonitor hook"
    assert ident["source_hash"] and ident["version"]
    pkg = provenance.package_root()
    own = subprocess.run(["git", "-C", str(pkg), "rev-parse", "HEAD"], capture_output=True, text=True)
    tracked = provenance._checkout_of(pkg) is not None
    assert ident["git_sha"] == (own.stdout.strip() if tracked else None)
    assert ident["code"] == (
        f"git:{ident['git_sha'][:12]}" + ("+dirty" if ident["git_dirty"] else "")
        if tracked
        else f"src:{ident['source_hash']}"
    )


def test_git_runs_only_with_the_package_root(monkeypatch: pytest.MonkeyPatch) -> None:
    calls: list[tuple[list[str], object]] = []
    real = subprocess.run

    def spy(cmd, *a, **k):  # type: ignore[no-untyped-def]
        calls.append((list(cmd), k.get("cwd")))
        return real(cmd, *a, **k)

    monkeypatch.setattr(provenance.subprocess, "run", spy)
    code_identity.cache_clear()
    try:
        code_identity()
    finally:
        code_identity.cache_clear()
    for cmd, cwd in calls:
        assert cmd[0] == "git" and cmd[1] == "-C" and "core.fsmonitor=false" in cmd
        root = Path(cmd[2])
        assert cwd == root and provenance.package_root().is_relative_to(root)


def test_a_copied_package_is_not_a_checkout(tmp_path: Path) -> None:
    """An installed copy (here: the package copied out of its checkout) gets no git SHA."""
    copy = tmp_path / "site-packages" / "nirspi_pipe"
    shutil.copytree(provenance.package_root(), copy, ignore=shutil.ignore_patterns("__pycache__"))
    assert provenance._checkout_of(copy) is None
    # inside an unrelated checkout, an untracked copy still is not part of it
    if _git_available():
        subprocess.run(["git", "init", "-q"], cwd=tmp_path, check=True)
        assert provenance._checkout_of(copy) is None


# -- crash records, sweep.json ------------------------------------------------------------------


def test_crash_messages_name_the_signal_or_exit_code() -> None:
    msg, fields = crash_message(signal.SIGSEGV)  # waitpid status of a child killed by SIGSEGV
    assert "SIGSEGV (11)" in msg and fields["signal"] == 11
    msg, fields = crash_message(signal.SIGKILL)
    assert "SIGKILL" in msg and "out of memory" in msg
    msg, fields = crash_message(3 << 8)  # exited with code 3
    assert "code 3" in msg and fields["exit_code"] == 3


@pytest.mark.skipif(not hasattr(os, "fork"), reason="crash isolation needs os.fork")
@pytest.mark.parametrize("how", ["segv", "exit", "kill", "raise", "ok"])
def test_run_sweep_job_survives_its_child(tmp_path: Path, how: str) -> None:
    from omegaconf import OmegaConf

    from conftest import crash_as

    def execute(cfg, out_dir, choices, overrides, job_num, attempt=None):  # type: ignore[no-untyped-def]
        crash_as(how)
        write_record(out_dir, {"meta": {"status": "ok", "attempt": attempt}})
        return {}

    cfg = OmegaConf.create({"a": 1})
    for attempt in (1, 2):
        rec = run_sweep_job(execute, cfg, tmp_path / "job", {}, ["a=1"], job_num=0)
        meta = read_record(tmp_path / "job" / RECORD_NAME)["meta"]
        assert meta == rec["meta"] and meta["attempt"] == attempt
        assert json.loads((tmp_path / "job" / "attempts.json").read_text())["attempts"] == attempt
        if how == "ok":
            assert meta["status"] == "ok"
        else:
            assert meta["status"] == "failed" and meta["error_type"] == "JobCrash"
            expected = {"segv": "SIGSEGV", "exit": "code 5", "kill": "SIGKILL", "raise": "code 70"}[how]
            assert expected in meta["error"]


@pytest.mark.parametrize(
    "text, needle",
    [
        ("{", "not readable JSON"),
        ("[]", "expected a JSON object"),
        ("{}", "expected a 'jobs' list"),
        ('{"jobs": [{"key": "../../etc"}]}', "jobs[0] needs a 'key'"),
        ('{"jobs": [1]}', "jobs[0]"),
        ('{"jobs": [], "started": "yesterday"}', "'started' must be a number"),
        ("[" * 100000, "not readable JSON"),
    ],
)
def test_malformed_sweep_file_is_named(tmp_path: Path, text: str, needle: str) -> None:
    (tmp_path / "sweep.json").write_text(text)
    with pytest.raises(SweepFileError) as info:
        load_sweep_file(tmp_path)
    assert needle in str(info.value) and str(tmp_path / "sweep.json") in str(info.value)
    assert "\n" not in str(info.value)


def test_collect_on_a_malformed_sweep_file_is_one_line(cli) -> None:
    (cli.cwd / "sweep").mkdir()
    (cli.cwd / "sweep" / "sweep.json").write_text('{"started": 1}')
    res = cli("nirspi-collect", "sweep", "--quiet", timeout=120)
    assert res.returncode == 2
    assert res.stderr.strip().count("\n") == 0 and "sweep.json" in res.stderr and "Traceback" not in res.stderr


def test_grid_expansion_is_hydras() -> None:
    from hydra.core.override_parser.overrides_parser import OverridesParser

    parsed = OverridesParser.create().parse_overrides(["a=1,2", "b=x", "+c=range(0,3)", "d=choice(u,v)"])
    jobs = expand_grid(parsed)
    assert len(jobs) == 2 * 1 * 3 * 2
    assert jobs[0] == ["a=1", "b=x", "+c=0", "d=u"] and jobs[-1] == ["a=2", "b=x", "+c=2", "d=v"]


def test_a_key_given_twice_takes_its_last_value_as_in_hydra() -> None:
    """An experiment's ``seed: range(0,20)`` and ``seed=0,1`` on the command line: 2 seeds, not
    the product of both lists (40 grid entries, issue 25's report of a 40,960-job keying)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    args = ["seed=range(0,20)", "scan=a,b", "seed=0,1"]
    parsed = OverridesParser.create().parse_overrides(args)
    jobs = expand_grid(parsed)
    assert jobs == [["seed=0", "scan=a"], ["seed=0", "scan=b"], ["seed=1", "scan=a"], ["seed=1", "scan=b"]]
