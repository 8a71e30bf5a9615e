"""Issue 41, what is judged before launch, per sweeper and launcher (docs/hostile.md, "What Hydra
runs, per job").

Hydra's own launchers (basic, joblib, submitit) compose each job (``load_sweep_config``), create
its folder, configure its logging and write ``.hydra/`` before the task function, and so before
the job gate there. What they will compose must therefore be judged before Hydra starts:

* every combination of swept config groups from a user's folder is composed as the launcher
  composes the job and checked (two option files can pick, together, what neither picks alone:
  a defaults list that interpolates another group's choice);
* the nirspi sweeper checks each composed job before it launches anything, also in its forked
  keying workers (a refusal there used to leave the pool waiting forever);
* Hydra's submitit launcher (``submitit_local``) runs clean sweeps and gets no job whose node is
  refused;
* the input hasher reads no byte of a file over the read budget (a sparse 16 GB file).
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from nirspi_pipe.app import entry
from nirspi_pipe.app.entry import check_invocation
from nirspi_pipe.app.flags import Refused

VICTIM_TEXT = "precious\n"
CONF = Path(__file__).resolve().parents[1] / "conf"


@pytest.fixture(scope="module", autouse=True)
def _plugins() -> None:
    from nirspi_pipe.app.plugins import activate
    from nirspi_pipe.app.registration import register_hydra_plugins

    activate()
    register_hydra_plugins()


def _combination_folder(root: Path, victim: Path) -> Path:
    """A ``-cd`` folder where ``+experiment=a`` and ``metrics=x`` are each harmless, and together
    choose ``hydra/hydra_logging=x``, a logging config that truncates ``victim``. (Hydra's own
    logging: conf/config.yaml chooses ``hydra/job_logging`` itself, and the primary config's
    choice wins over an option file's, so an option file cannot reach that group.)"""
    conf = root / "conf"
    for sub in ("experiment", "metrics", "hydra/hydra_logging"):
        (conf / sub).mkdir(parents=True)
    (conf / "experiment" / "a.yaml").write_text(
        "# @package _global_\ndefaults:\n  - override /metrics: default\n"
        "  - override /hydra/hydra_logging: ${metrics}\nseed: 3\n"
    )
    (conf / "experiment" / "b.yaml").write_text("# @package _global_\nseed: 4\n")
    (conf / "metrics" / "x.yaml").write_text((CONF / "metrics" / "default.yaml").read_text())
    (conf / "hydra" / "hydra_logging" / "x.yaml").write_text(
        f"version: 1\nhandlers:\n  f:\n    class: logging.FileHandler\n    filename: {victim}\n    mode: w\n"
        "root:\n  handlers: [f]\n"
    )
    return conf


def _hydra_pair(launcher: str = "basic") -> list[str]:
    return ["-m", f"hydra/launcher={launcher}", "hydra/sweeper=basic", "camera.resolution=8"]


# ------------------------------------------------------------------ layer 1: combinations of swept groups


@pytest.mark.slow  # 11-20 s at load 4-6: each check composes every value and combination
def test_swept_groups_are_checked_in_combination(tmp_path: Path) -> None:
    """Each value alone passes; the combination that picks the user's logging config is refused
    in one line, before Hydra; without the combination check it passed (it was the hole)."""
    conf = _combination_folder(tmp_path, tmp_path / "VICTIM")
    base = [*_hydra_pair(), "-cd", str(conf)]
    check_invocation([*base, "+experiment=a,b"])
    check_invocation([*base, "metrics=x,default"])
    with pytest.raises(Refused) as err:
        check_invocation([*base, "+experiment=a,b", "metrics=x,default"])
    assert "hydra/hydra_logging=x" in str(err.value) and "\n" not in str(err.value)


@pytest.mark.slow  # 11-20 s at load 4-6: each check composes every value and combination
def test_combinations_past_the_bound_are_refused_with_hydras_pair_only(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Over :data:`entry.MAX_CHECKED_COMBINATIONS` combinations, Hydra's own sweeper and launcher
    are refused (one line naming the way out); the nirspi launcher, which checks each job before it
    starts, is not (it composes no combination here)."""
    conf = _combination_folder(tmp_path, tmp_path / "VICTIM")
    monkeypatch.setattr(entry, "MAX_CHECKED_COMBINATIONS", 3)
    sweep = ["+experiment=a,b", "metrics=x,default"]  # 4 combinations
    with pytest.raises(Refused) as err:
        check_invocation([*_hydra_pair(), "-cd", str(conf), *sweep])
    assert "4 combinations" in str(err.value) and "nirspi" in str(err.value)
    composed: list[list[str]] = []
    real = entry.compose_config
    monkeypatch.setattr(entry, "compose_config", lambda name, ovs: composed.append(list(ovs)) or real(name, ovs))
    check_invocation(["-m", "hydra/launcher=nirspi", "camera.resolution=8", "-cd", str(conf), *sweep])
    assert not any("+experiment=a" in ovs and "metrics=x" in ovs for ovs in composed)


# ------------------------------------------------------------------ the input hasher, bounded


def test_the_input_hasher_reads_no_byte_of_a_file_over_the_read_budget(tmp_path: Path) -> None:
    """A sparse 16 GB file (no disk used) costs no read: its entry says it was not hashed and
    gives its size; a file within the budget is hashed in full (every byte read once, then
    cached); a FIFO swapped in where a file was is an 'unreadable' entry, never a hang."""
    from nirspi_pipe.jobkey import InputHasher

    sparse = tmp_path / "sparse.bin"
    with open(sparse, "wb") as fh:
        fh.truncate(16 << 30)
    small = tmp_path / "small.bin"
    small.write_bytes(b"x" * 5000)
    hasher = InputHasher()
    out = hasher.hashes({"scene": {"path": str(sparse)}, "source": {"path": str(small)}})
    assert out["scene.path"].startswith("not hashed: 17179869184 bytes, over the read budget")
    assert len(out["source.path"]) == 64 and hasher.bytes_read == 5000
    hasher.hashes({"source": {"path": str(small)}})
    assert hasher.bytes_read == 5000  # cached
    tight = InputHasher(budget=4999)
    assert tight.hashes({"p": str(small)})["p"].startswith("not hashed: 5000 bytes") and tight.bytes_read == 0
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    assert InputHasher().hashes({"p": str(fifo)}) == {}  # not an input (input_files)
    from nirspi_pipe.safeio import UnsafeInputError

    with pytest.raises(UnsafeInputError):
        InputHasher().digest(fifo)  # named directly (swapped in after input_files): refused, no block


# ------------------------------------------------------------------ end to end, real launchers


def _env() -> dict[str, str]:
    env = {**os.environ, "MPLBACKEND": "Agg", "OPENBLAS_NUM_THREADS": "1"}
    env.pop("NIRSPI_TRACEBACK", None)
    return env


def _cli(args: list[str], cwd: Path, timeout: float = 240) -> subprocess.CompletedProcess[str]:
    from conftest import script

    return subprocess.run(
        [script("nirspi-run"), *args], cwd=cwd, capture_output=True, text=True, timeout=timeout, env=_env()
    )


_NO_COMBINATIONS = textwrap.dedent(
    """
    import sys
    from nirspi_pipe.app import cli, entry
    entry._check_group_combinations = lambda *a, **k: None  # layer 1's combinations off
    cli.run(sys.argv[1:])
    """
)


@pytest.mark.slow
@pytest.mark.parametrize("launcher", ["basic", "joblib", "submitit_local", "nirspi sweeper + basic"])
def test_a_combination_of_swept_groups_is_refused_before_hydras_launchers(launcher: str, tmp_path: Path) -> None:
    """The combination way through ``nirspi-run -m``: one line, exit 2, the victim keeps its
    content, nothing written (before this check, Hydra's basic launcher truncated the victim).
    With the nirspi sweeper, its own gate refuses the combination before launching anything
    even with layer 1's combination check switched off in the child."""
    victim = tmp_path / "VICTIM"
    victim.write_text(VICTIM_TEXT)
    conf = _combination_folder(tmp_path, victim)
    work = tmp_path / "work"
    work.mkdir()
    sweep = ["-cd", str(conf), "hydra.sweep.dir=sweep", "+experiment=a,b", "metrics=x,default"]
    if launcher.startswith("nirspi sweeper"):
        (tmp_path / "probe.py").write_text(_NO_COMBINATIONS)
        args = ["-m", "hydra/launcher=basic", "camera.resolution=8", *sweep]
        res = subprocess.run(
            [sys.executable, str(tmp_path / "probe.py"), *args],
            cwd=work,
            capture_output=True,
            text=True,
            timeout=240,
            env=_env(),
        )
        written = [p for p in work.rglob("*") if p.name != "multirun.yaml" and p.is_file()]
    else:
        res = _cli([*_hydra_pair(launcher), *sweep], work)
        written = list(work.iterdir())
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1 and "hydra/hydra_logging=x" in lines[0], res.stderr[-2000:]
    assert "allowed: default, disabled, hydra_debug, none" in lines[0], lines[0]  # also from the job gate in an app
    assert victim.read_text() == VICTIM_TEXT and not written


@pytest.mark.slow
def test_submitit_local_refuses_a_planted_override_and_runs_a_clean_sweep(tmp_path: Path) -> None:
    """``hydra/launcher=submitit_local``: a planted ``hydra.overrides.hydra`` (a log file and a
    job folder above the sweep) is one line, exit 2, nothing written; a clean two-job sweep
    writes its records, and nothing outside its sweep folder."""
    victim = tmp_path / "VICTIM"
    victim.write_text(VICTIM_TEXT)
    work = tmp_path / "work"
    work.mkdir()
    planted = f'hydra.overrides.hydra=["hydra.job_logging.handlers.file.filename={victim}","hydra.sweep.subdir=../.."]'
    res = _cli([*_hydra_pair("submitit_local"), "hydra.sweep.dir=sweep", planted, "seed=0,1"], work)
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1 and lines[0].startswith("nirspi-run: error:"), res.stderr[-2000:]
    assert victim.read_text() == VICTIM_TEXT and not list(work.iterdir())
    res = _cli([*_hydra_pair("submitit_local"), "hydra.sweep.dir=sweep", "seed=0,1"], work, timeout=400)
    assert res.returncode == 0, res.stderr[-2000:]
    assert sorted(p.parent.name for p in work.rglob("record.json")) == ["0", "1"]
    assert [p.name for p in work.iterdir()] == ["sweep"] and victim.read_text() == VICTIM_TEXT


_LAYER_TWO_ONLY = textwrap.dedent(
    """
    import sys
    from nirspi_pipe.app import cli, composition, entry, hydranode
    entry.check_override_places = hydranode.check_override_places = lambda parsed: None  # layer 1 off: the job gate alone
    composition.check_filled_by_hydra = lambda *a, **k: None
    cli.run(sys.argv[1:])
    """
)


@pytest.mark.slow
def test_the_nirspi_sweepers_gate_stops_a_sweep_keyed_in_parallel(tmp_path: Path) -> None:
    """Layer 2 alone in the nirspi sweeper with one of Hydra's launchers and two sets of jobs
    (keyed in forked workers): one line, exit 2, before any job; it used to hang (the worker
    exited with SystemExit and the pool waited for its result)."""
    (tmp_path / "probe.py").write_text(_LAYER_TWO_ONLY)
    args = [
        "-m",
        "hydra/launcher=basic",
        "hydra.sweep.dir=sweep/deep",
        "camera.resolution=8",
        'hydra.overrides.hydra=["hydra.sweep.subdir=../../../escaped"]',
        "scene=cube,sphere",
    ]
    res = subprocess.run(
        [sys.executable, "probe.py", *args], cwd=tmp_path, capture_output=True, text=True, timeout=120, env=_env()
    )
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1 and "job refused" in lines[0], res.stderr[-2000:]
    assert not (tmp_path / "escaped").exists() and not list(tmp_path.rglob("record.json"))


@pytest.mark.parametrize("multirun", [False, True])
def test_the_link_cleanup_makes_no_folder_named_by_the_clock(
    multirun: bool, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Hydra's default run and sweep folders are named by the clock when Hydra starts
    (``${now:…}``): the cleanup before Hydra makes none (it made one, a second or more before
    Hydra made the run's, and left it empty beside it); a folder given by name is made and
    cleaned."""
    from nirspi_pipe.app import cli

    monkeypatch.chdir(tmp_path)
    inv = check_invocation([*(["-m"] if multirun else []), "camera.resolution=8"])
    cli._hydra_files_without_links(inv.config, multirun)
    assert not list(tmp_path.iterdir())
    key = "hydra.sweep.dir" if multirun else "hydra.run.dir"
    inv = check_invocation([*(["-m"] if multirun else []), "camera.resolution=8", f"{key}=named"])
    (tmp_path / "named" / ".hydra").mkdir(parents=True)
    (tmp_path / "named" / ".hydra" / "config.yaml").symlink_to(tmp_path / "elsewhere")
    cli._hydra_files_without_links(inv.config, multirun)
    assert not (tmp_path / "named" / ".hydra" / "config.yaml").is_symlink()
