"""Optuna studies that last (issue 43): the storage allow-list, the search space, repeats and
objectives checked against a record (fast, pure), and through the CLI a study resumed in its
SQLite database and a misspelled objective refused before any trial (slow)."""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nirspi_pipe.app.searchspace import check_objective_keys, dimension_of, median_values, repeat_key
from nirspi_pipe.app.storage import StorageError, check_storage, storage_url

optuna = pytest.importorskip("optuna", reason="pip install '.[optuna]'")


# -- storage ---------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "url",
    [
        None,
        "postgresql://user:pw@127.0.0.1:5432/studies",
        "postgresql+psycopg2://db.lab/studies",
        "mysql://user@127.0.0.1/studies",
        "mysql+pymysql://user@127.0.0.1/studies",
    ],
)
def test_servers_and_null_are_allowed(url: str | None) -> None:
    assert check_storage(url, "/tmp/any") is None


@pytest.mark.parametrize(
    ("url", "needle"),
    [
        ("redis://127.0.0.1/0", "scheme"),
        ("file:///etc/passwd", "scheme"),
        ("/tmp/study.db", "scheme"),
        ("sqlite://", "sqlite:///<path>"),
        ("sqlite:///s/../x.db", "'..'"),
        ("sqlite:///s/x.db?mode=ro", "without a query"),
        ("sqlite:///elsewhere/x.db", "inside the sweep folder"),
        ("sqlite:///s", "inside the sweep folder"),
        ("sqlite:///:memory:", "'..'"),
        (42, "not a URL"),
        ("sqlite:///s/x\n.db", "not a URL"),
    ],
)
def test_refused_storage_says_why(url: object, needle: str, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    why = check_storage(url, "s")
    assert why is not None and needle in why


def test_sqlite_inside_the_sweep_folder_is_allowed_but_not_through_a_link(tmp_path: Path) -> None:
    sweep = tmp_path / "sweep"
    (sweep / "db").mkdir(parents=True)
    assert check_storage(f"sqlite:///{sweep}/db/study.db", sweep) is None
    outside = tmp_path / "outside"
    outside.mkdir()
    os.symlink(outside, sweep / "link")
    why = check_storage(f"sqlite:///{sweep}/link/study.db", sweep)
    assert why is not None and "symbolic link" in why


@settings(max_examples=60, deadline=None)
@given(st.lists(st.sampled_from(["a", "b", "..", ".", "c.db"]), min_size=1, max_size=5))
def test_a_sqlite_file_outside_the_sweep_folder_is_never_allowed(parts: list[str]) -> None:
    sweep = Path("/srv/runs/sweep")
    url = "sqlite:///" + str(sweep / "/".join(parts))
    target = Path(os.path.normpath(sweep / "/".join(parts)))
    if check_storage(url, sweep) is None:
        assert ".." not in parts and sweep in target.parents


def test_the_default_storage_is_sqlite_in_the_sweep_folder_named_after_the_study(tmp_path: Path) -> None:
    assert storage_url(None, tmp_path / "s", "s") == f"sqlite:///{tmp_path}/s/s.db"
    with pytest.raises(StorageError, match="hydra.sweeper.study_name"):
        storage_url(None, tmp_path / "s", "../up")
    with pytest.raises(StorageError, match=r"hydra.sweeper.storage='redis://x' is not allowed .*allowed: null"):
        storage_url("redis://x", tmp_path / "s", "s")


# -- the search space ------------------------------------------------------------------------------


def _dims(*texts: str):
    from hydra.core.override_parser.overrides_parser import OverridesParser

    return [dimension_of(o) for o in OverridesParser.create().parse_overrides(list(texts))]


def test_hydra_sweeps_become_optuna_dimensions() -> None:
    choice, rng, frng, ivl, logi, iint, fixed = _dims(
        "solver=choice(fwht,lstsq)",
        "seed=range(0,5)",
        "x=range(0.0,1.0,0.25)",
        "scan.ratio=interval(0.25,1.0)",
        "solver.damp=tag(log,interval(0.0001,0.1))",
        "n=interval(1,4)",
        "camera.resolution=8",
    )
    assert fixed is None
    assert (choice.kind, choice.choices) == ("categorical", ("fwht", "lstsq"))
    assert (rng.kind, rng.low, rng.high, rng.step) == ("int", 0, 4, 1)  # range's stop is exclusive
    assert (frng.kind, frng.low, frng.high, frng.step) == ("float", 0.0, 0.75, 0.25)
    assert (ivl.kind, ivl.low, ivl.high, ivl.log) == ("float", 0.25, 1.0, False)
    assert (logi.kind, logi.log) == ("float", True)
    assert (iint.kind, iint.low, iint.high) == ("float", 1.0, 4.0)  # Hydra's interval is always of floats
    study = optuna.create_study(sampler=optuna.samplers.RandomSampler(seed=0))
    for _ in range(30):
        trial = study.ask()
        v = [d.suggest(trial) for d in (choice, rng, frng, ivl, logi, iint)]
        assert v[0] in ("fwht", "lstsq") and v[1] in range(5) and v[2] in (0.0, 0.25, 0.5, 0.75)
        assert 0.25 <= v[3] <= 1.0 and 1e-4 <= v[4] <= 0.1 and 1.0 <= v[5] <= 4.0
        study.tell(trial, 0.0)


@pytest.mark.parametrize("text", ["seed=range(5,5)", "x=interval(1.0,0.5)", "x=tag(log,interval(0.0,1.0))"])
def test_an_empty_space_is_refused(text: str) -> None:
    with pytest.raises(ValueError, match="empty"):
        _dims(text)


# -- repeats and objectives ------------------------------------------------------------------------


def _rec(status: str = "ok", **metrics: float) -> dict:
    return {"meta": {"status": status}, "metrics": metrics, "timings_ms": {"solver": metrics.get("t", 1.0)}}


def test_a_trial_is_the_median_of_its_repeats_and_fails_with_any_repeat() -> None:
    recs = [_rec(psnr=10.0, t=5.0), _rec(psnr=10.0, t=21.0), _rec(psnr=10.0, t=4.3)]
    assert median_values(recs, ["metrics.psnr", "timings_ms.solver"]) == [10.0, 5.0]
    assert median_values([*recs, _rec("failed")], ["metrics.psnr"]) is None
    assert median_values([*recs, None], ["metrics.psnr"]) is None
    assert median_values([_rec(psnr=float("nan"))], ["metrics.psnr"]) is None
    assert median_values(recs, ["metrics.ssim"]) is None


def test_repeats_have_their_own_keys() -> None:
    key = "0123456789abcdef"
    keys = [repeat_key(key, r) for r in range(4)]
    assert keys[0] == key and len(set(keys)) == 4
    assert all(len(k) == 16 and int(k, 16) >= 0 for k in keys)


def test_sweep_json_leaves_out_jobs_abandoned_without_a_record(tmp_path: Path) -> None:
    """CI at aeae266: a Ctrl-C'd trial's job stayed listed in sweep.json, so the resumed study
    counted its missing record as a failed job and exited 1. The same for the crash record the
    launcher writes for a job Ctrl-C stopped (its runner's exit 130, or the launcher's SIGTERM):
    listed, it made the resumed study exit 1 as well."""
    import json
    import subprocess
    import sys
    from types import SimpleNamespace

    from nirspi_pipe.app.study import _HOST, StudySweeperBase

    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()  # a pid of this host that no longer runs (reuse within this test is unlikely)
    study = optuna.create_study(directions=["maximize"])
    states = {}
    for name, attrs in {
        "done": {},
        "interrupted": {"interrupted": True},
        "interrupted-with-record": {"interrupted": True},
        "interrupted-exit-130": {"interrupted": True},
        "interrupted-sigterm": {"interrupted": True},
        "dead-worker": {"worker": [_HOST, gone.pid], "running": True},
        "other-host": {"worker": ["another-host", 1], "running": True},
    }.items():
        trial = study.ask()
        key = f"{trial.number:016x}"
        trial.set_user_attr("jobs", [key])
        for k, v in attrs.items():
            if k != "running":
                trial.set_user_attr(k, v)
        if name in ("done", "interrupted-with-record"):
            (tmp_path / key).mkdir()
            (tmp_path / key / "record.json").write_text("{}")
        if name.startswith("interrupted-") and name != "interrupted-with-record":  # JobCrash records of a stop
            crash = {"exit_code": 130, "signal": None} if name.endswith("130") else {"exit_code": -15, "signal": 15}
            (tmp_path / key).mkdir()
            meta = {"status": "failed", "error_type": "JobCrash", **crash}
            (tmp_path / key / "record.json").write_text(json.dumps({"meta": meta}))
        if not attrs.get("running"):
            study.tell(trial, 1.0) if name == "done" else study.tell(trial, state=optuna.trial.TrialState.FAIL)
        states[key] = name
    me = SimpleNamespace(max_attempts=1, n_trials=5)
    StudySweeperBase._write_sweep_file(me, tmp_path, study, 0.0, "sqlite:///x.db")  # type: ignore[arg-type]
    listed = {states[j["key"]] for j in json.loads((tmp_path / "sweep.json").read_text())["jobs"]}
    # another host's running trial may be alive: it stays listed (its worker writes its record)
    assert listed == {"done", "interrupted-with-record", "other-host"}


def test_a_misspelled_objective_is_named_with_the_nearest_keys() -> None:
    rec = _rec(psnr=1.0, ssim=0.5)
    assert check_objective_keys(["metrics.psnr", "timings_ms.solver"], rec) is None
    line = check_objective_keys(["metrics.ssmi", "timings_ms.solvr"], rec)
    assert line is not None and "\n" not in line
    assert (
        "'metrics.ssmi' (did you mean metrics.ssim" in line
        and "'timings_ms.solvr' (did you mean timings_ms.solver" in line
    )


# -- through the CLI -------------------------------------------------------------------------------

TINY = [
    "preset=null",
    "camera.resolution=8",
    "fog=none",
    "illumination=none",
    "detector=ideal",
    "output.images=false",
    "output.arrays=false",
]
STUDY = [
    "hydra/sweeper=optuna",
    "hydra/sweeper/sampler=random",
    "hydra.sweeper.sampler.seed=2",
    "hydra.sweeper.n_jobs=2",
    "hydra.sweeper.direction=[maximize,minimize]",
    *TINY,
    "solver=choice(fwht,lstsq)",
    "scan.ratio=interval(0.25,1.0)",
    "hydra.sweep.dir=sweep",
]


def _trials(db: Path) -> list[tuple[int, str]]:
    with sqlite3.connect(db) as con:
        return list(con.execute("select number, state from trials order by number"))


def _complete(db: Path) -> int:
    """Finished trials in a study being written (0 while Optuna creates its tables)."""
    try:
        return sum(s == "COMPLETE" for _, s in _trials(db)) if db.exists() else 0
    except sqlite3.OperationalError:
        return 0


@pytest.mark.slow
def test_the_same_command_continues_the_study(cli) -> None:
    import pandas as pd

    two = "objective=[metrics.psnr,timings_ms.solver]"
    first = cli("nirspi-run", "-m", *STUDY, two, "hydra.sweeper.n_trials=3")
    assert first.returncode == 0, first.stderr
    sweep = Path(cli.cwd) / "sweep"
    assert "0 of 3 trials finished or running, 3 to run" in first.stdout
    assert [s for _, s in _trials(sweep / "sweep.db")] == ["COMPLETE"] * 3
    records = {p: p.stat().st_mtime_ns for p in sweep.glob("*/record.json")}
    jobs = set(pd.read_parquet(sweep / "results.parquet")["job"])
    assert len(jobs) == 3  # scan.ratio is continuous: three configurations
    again = cli("nirspi-run", "-m", *STUDY, two, "hydra.sweeper.n_trials=3")
    assert again.returncode == 0, again.stderr
    assert "3 of 3 trials finished or running, 0 to run" in again.stdout
    assert {p: p.stat().st_mtime_ns for p in sweep.glob("*/record.json")} == records  # nothing ran again
    more = cli("nirspi-run", "-m", *STUDY, two, "hydra.sweeper.n_trials=5")
    assert more.returncode == 0, more.stderr
    assert "3 of 5 trials finished or running, 2 to run" in more.stdout
    trials = _trials(sweep / "sweep.db")
    assert [n for n, _ in trials] == [0, 1, 2, 3, 4] and {s for _, s in trials} == {"COMPLETE"}
    df = pd.read_parquet(sweep / "results.parquet")  # both runs' trials (a repeated config is one row)
    assert jobs <= set(df["job"]) and len(df) == 5
    assert df["pareto"].any()


@pytest.mark.slow
@pytest.mark.parametrize(
    "objective", ["objective=[metrics.ssmi,timings_ms.solver]", "objective=[metrics.psnr,timings_ms.solvr]"]
)
def test_a_misspelled_objective_is_refused_before_any_trial(cli, objective: str) -> None:
    res = cli("nirspi-run", "-m", *STUDY, objective, "hydra.sweeper.n_trials=4")
    assert res.returncode == 2, res.stdout + res.stderr
    errors = [ln for ln in res.stderr.splitlines() if ln.startswith("nirspi-run: error:")]
    assert len(errors) == 1 and "did you mean" in errors[0] and "Traceback" not in res.stderr
    sweep = Path(cli.cwd) / "sweep"
    assert _trials(sweep / "sweep.db") == []  # the study holds no trial
    assert len(list(sweep.glob("*/record.json"))) == 1  # the one job the check ran


@pytest.mark.slow
def test_a_storage_outside_the_sweep_folder_is_refused_in_one_line(cli) -> None:
    res = cli(
        "nirspi-run", "-m", *STUDY, "objective=[metrics.psnr,timings_ms.solver]",
        "hydra.sweeper.storage=sqlite:///elsewhere.db",
    )  # fmt: skip
    assert res.returncode == 2, res.stdout + res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "hydra.sweeper.storage" in lines[0] and "inside the sweep folder" in lines[0]
    assert not (Path(cli.cwd) / "elsewhere.db").exists()


@pytest.mark.slow
def test_repeats_run_each_trial_k_times_and_optuna_is_told_the_median(cli) -> None:
    import pandas as pd

    res = cli(
        "nirspi-run", "-m", *[a for a in STUDY if not a.startswith("scan.ratio")],
        "objective=[metrics.psnr,timings_ms.solver]", "hydra.sweeper.n_trials=2", "hydra.sweeper.repeats=3",
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    assert "3 repeats each (median)" in res.stdout
    sweep = Path(cli.cwd) / "sweep"
    df = pd.read_parquet(sweep / "results.parquet")
    study = optuna.load_study(study_name="sweep", storage=f"sqlite:///{sweep}/sweep.db")
    for trial in study.trials:
        rows = df[df["job"].isin(trial.user_attrs["jobs"])]
        assert len(rows) == 3 and rows["config_hash"].nunique() == 1 and rows["job"].nunique() == 3
        assert trial.values == pytest.approx([rows["metrics.psnr"].median(), rows["timings_ms.solver"].median()])
    # the pareto column is per configuration: all its repeats or none
    assert (df.groupby("config_hash")["pareto"].nunique() == 1).all() and df["pareto"].any()


@pytest.mark.slow
def test_trials_asked_together_with_one_configuration_run_it_once(cli) -> None:
    import json

    import pandas as pd

    # the random sampler with seed 3 draws fista_tv three times (optuna 2.10.1); the objective
    # check's job is lstsq (the first choice), so the three trials asked at once share one new folder
    res = cli(
        "nirspi-run", "-m",
        *[a for a in STUDY if not a.startswith(("scan.ratio", "solver=", "hydra.sweeper.sampler.seed", "camera."))],
        "hydra.sweeper.sampler.seed=3", "solver=choice(lstsq,fista_tv)", "camera.resolution=32",
        "objective=[metrics.psnr,timings_ms.solver]",
        "hydra.sweeper.n_trials=3", "hydra.sweeper.n_jobs=3",
    )  # fmt: skip
    assert res.returncode == 0, res.stderr
    sweep = Path(cli.cwd) / "sweep"
    df = pd.read_parquet(sweep / "results.parquet")
    assert df["solver"].tolist() == ["fista_tv"] and (df["status"] == "ok").all()
    record = json.loads((sweep / df["job"][0] / "record.json").read_text())
    assert record["meta"]["attempt"] == 1  # run once for the three trials
    assert [s for _, s in _trials(sweep / "sweep.db")] == ["COMPLETE"] * 3


@pytest.mark.slow
def test_ctrl_c_says_what_finished_and_how_to_resume(cli) -> None:
    import shlex
    import signal
    import subprocess
    import time

    import pandas as pd

    from conftest import script

    sweep = Path(cli.cwd) / "sweep"
    args = [*STUDY, "objective=[metrics.psnr,timings_ms.solver]", "hydra.sweeper.n_trials=40", "hydra.sweeper.n_jobs=1"]
    env = {k: v for k, v in os.environ.items() if k not in ("HYDRA_FULL_ERROR", "NIRSPI_TRACEBACK")}
    proc = subprocess.Popen(
        [script("nirspi-run"), "-m", *args], cwd=cli.cwd, env=env, text=True,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True,
    )  # fmt: skip
    deadline = time.monotonic() + 200
    while time.monotonic() < deadline and proc.poll() is None:  # bounded: until two trials finished
        if _complete(sweep / "sweep.db") >= 2:
            break
        time.sleep(0.5)
    os.killpg(proc.pid, signal.SIGINT)  # what a terminal's Ctrl-C does: the whole foreground group
    _out, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    lines = [ln for ln in err.splitlines() if ln.startswith("nirspi-run: interrupted:")]
    assert len(lines) == 1 and "Traceback" not in err, err
    finished = sum(s == "COMPLETE" for _, s in _trials(sweep / "sweep.db"))
    assert f"{finished} trials finished ok" in lines[0] and "sweep.db" in lines[0]
    df = pd.read_parquet(sweep / "results.parquet")
    assert (df["status"] == "ok").sum() >= 2
    resume = shlex.split(lines[0].split("resume: ", 1)[1])
    assert resume[0] == "nirspi-run" and "hydra.sweeper.n_trials=40" in resume
    more = [f"hydra.sweeper.n_trials={finished + 1}" if a == "hydra.sweeper.n_trials=40" else a for a in resume]
    again = cli(*more)  # the command it printed, asking for one more trial than finished
    assert again.returncode == 0, again.stderr
    assert f"{finished} of {finished + 1} trials finished or running, 1 to run" in again.stdout
