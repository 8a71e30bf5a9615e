"""Issue 32: one checked entry path that fails closed (docs/hostile.md, "Configs").

In-process checks of :func:`nirspi_pipe.app.entry.check_invocation` for many spellings of each
way in, then a few grouped subprocess runs through the installed ``nirspi-run`` (single run,
``-m`` with the nirspi, basic and joblib launchers) and the Python API from another working
directory. A payload marker must never appear, a victim file keeps its contents, and nothing is
written outside the output folder.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from nirspi_pipe.app import allowlist
from nirspi_pipe.app.entry import check_invocation
from nirspi_pipe.app.flags import FLAGS, Refused, parse_args
from nirspi_pipe.app.hydranode import check_kind

VICTIM_TEXT = "precious\n"


@pytest.fixture(scope="module", autouse=True)
def _plugins() -> None:
    from nirspi_pipe.app.plugins import activate
    from nirspi_pipe.app.registration import register_hydra_plugins

    activate()
    register_hydra_plugins()


def _refused(args: list[str], *expected: str) -> str:
    with pytest.raises(Refused) as err:
        check_invocation(args)
    text = str(err.value)
    assert "\n" not in text, text
    for part in expected:
        assert part in text, text
    return text


# ------------------------------------------------------------------ flags, matched exactly

ABBREVIATIONS = ["--experimental-r", "--experimental-rerun", "--exp", "--run", "-r", "--hel", "--multi", "--cf", "--"]


@pytest.mark.parametrize("flag", [*ABBREVIATIONS, "--config-path", "-cp", "--unknown", "-x", "-mm", "---help"])
def test_flags_not_spelled_exactly_are_refused(flag: str) -> None:
    with pytest.raises(Refused) as err:
        parse_args([flag, "x.pickle", "seed=1"])
    assert "\n" not in str(err.value) and flag.split("=")[0] in str(err.value)


@pytest.mark.parametrize(
    "args, message",
    [
        (["-m", "-m"], "given twice"),
        (["--cfg=jo"], "--cfg='jo' is not allowed; allowed: job, hydra, all"),
        (["--info=evil"], "--info='evil' is not allowed"),
        (["-m", "--cfg", "job"], "cannot be combined"),
        (["--resolve"], "--resolve is only allowed with --cfg or --help"),
        (["-cn", "../../etc/x"], "--config-name='../../etc/x' is not allowed"),
        (["-p", "a;b", "--cfg", "job"], "--package='a;b' is not allowed"),
        (["-cd"], "-cd needs a value"),
        (["-m=1"], "-m takes no value"),
    ],
)
def test_flag_values_are_checked(args: list[str], message: str) -> None:
    with pytest.raises(Refused, match=message.replace("(", r"\(").replace("[", r"\[")):
        parse_args(args)


def test_every_flag_of_the_table_is_canonical_for_hydra() -> None:
    flags, overrides = parse_args(["-c", "job", "-p", "scene", "--resolve", "seed=1"])
    assert flags == {"--cfg": "job", "--package": "scene", "--resolve": None} and overrides == ["seed=1"]
    inv = check_invocation(["-c", "job", "-p", "scene", "--resolve", "seed=1"])
    assert inv.hydra_argv == ("--cfg=job", "--package=scene", "--resolve", "seed=1")
    assert all(canonical.startswith("--") for canonical, _ in FLAGS.values())


# ------------------------------------------------------------------ Hydra's node: allow-listed keys

#: Ways into Hydra's node, each refused whatever flag comes with it.
HYDRA_ATTACKS = [
    "+hydra.callbacks.logging={_target_:logging.FileHandler,filename:VICTIM,mode:w}",
    "+hydra.callbacks.evil={_target_:os.system,command:touch MARK}",
    "+hydra.hydra_logging.handlers.x={class:io.FileIO,file:VICTIM,mode:w}",
    "+hydra.hydra_logging.handlers.x={():site.addsitedir,sitedir:.}",
    "hydra.job_logging.handlers.file.filename=VICTIM",
    "hydra.job_logging.handlers.file.mode=w",
    "+hydra.job.env_set.LD_PRELOAD=lib.so",
    "hydra.job.env_copy=[HOME]",
    "hydra.output_subdir=../../X",
    "hydra.output_subdir=/tmp/X",
    "hydra.job.name=../../X",
    "hydra.job.chdir=true",
    "hydra.searchpath=[pkg://os]",
    "hydra.searchpath=[file:///no/such/folder]",
    "~hydra.callbacks.collect",
    "hydra.help.template=x",
    "hydra/job_logging=evil",
    "hydra/env=default,other",
    # issue 32, tried again: a whole logging config inline, folders through an interpolation
    "hydra.job_logging={version:1,handlers:{f:{class:logging.FileHandler,filename:VICTIM}},root:{handlers:[f]}}",
    "+hydra.job_logging.handlers.f={class:logging.FileHandler,filename:VICTIM,mode:w}",
    "hydra.output_subdir=${oc.env:HOME}",
    "hydra.job.name=${oc.env:HOME}",
]


@pytest.mark.parametrize("attack", HYDRA_ATTACKS)
@pytest.mark.parametrize("flags", [[], ["--help"]])
def test_hydra_settings_outside_the_allow_list_are_refused(attack: str, flags: list[str]) -> None:
    _refused([*flags, attack])


@pytest.mark.parametrize("attack", HYDRA_ATTACKS[:4])
@pytest.mark.parametrize(
    "flags",
    [
        ["-h"],
        ["--hydra-help"],
        ["--cfg", "hydra"],
        ["--cfg=all", "--resolve"],
        ["-c", "job", "-p", "hydra"],
        ["--info"],
        *[["--info", value] for value in FLAGS["--info"][1][1]],
        ["-i=searchpath"],
        ["-m"],
    ],
)
def test_hydra_settings_are_refused_for_every_flag(attack: str, flags: list[str]) -> None:
    _refused([*flags, attack])


@pytest.mark.parametrize(
    "args, message",
    [
        (["-m", "seed=0,1", "hydra/sweeper=basic", "hydra.sweep.subdir=../../X"], "hydra.sweep.subdir='../../X'"),
        (["-m", "seed=0,1", "hydra.sweep.subdir=/abs"], "hydra.sweep.subdir='/abs'"),
        (["-m", "seed=0,1", "hydra.sweep.subdir=${hydra.job.override_dirname}"], "hydra.sweep.subdir="),
        (["hydra.launcher.submitit_folder=/tmp/x", "hydra/launcher=slurm"], "hydra.launcher.submitit_folder"),
        (["hydra/launcher=basic,joblib", "-m"], "sweeping Hydra's own settings"),
        (["-m", "+hydra.sweeper.custom_search_space=os.system"], "hydra.sweeper.custom_search_space"),
        (["-m", "+hydra.sweeper.params.solver._target_=os.system"], "os.system"),
        (["-m", "+hydra.sweeper.params.scan='basic,nope'"], "scan=nope is not an option"),
        (["-m", "+hydra.sweeper.params.scan=basic,nope"], "sweeping Hydra's own settings"),
        (["seed=0,1"], "a sweep with -m only"),
        (["-m", "seed=glob(*)"], "glob() is allowed only over a config group"),
        (["-m", "seed=0,1", "hydra/sweeper=basic", "hydra.sweep.subdir=${oc.env:HOME}"], "hydra.sweep.subdir="),
        (["-m", "seed=0,1", "hydra/sweeper=basic", "hydra.sweep.subdir=a/../../b"], "hydra.sweep.subdir="),
        (["-m", "seed=0,1", "hydra/sweeper=basic", "hydra.sweep.subdir=${hydra.job.name}", "hydra.job.name=.."], ".."),
    ],
)
def test_sweeps_and_job_folders(args: list[str], message: str) -> None:
    _refused(args, message)


ALLOWED = [
    [],
    ["scan=spiral", "seed=3"],
    ["-m", "seed=0,1", "scan=basic,spiral"],
    ["-m", "seed=interval(0,1)"],  # Optuna's syntax: checked by its bounds, no traceback
    ["-m", "seed=tag(a,choice(0,1))", "scan=glob(b*)"],
    ["-m", "+experiment=paper"],
    ["--help"],
    ["--hydra-help"],
    ["--cfg", "job", "--resolve"],
    ["-i", "config", "seed=1"],
    ["-sc", "install=bash"],
    ["hydra.run.dir=/tmp/somewhere", "hydra.job.name=my_job", "hydra.verbose=true"],
    ["-m", "seed=0,1", "hydra.sweep.dir=out", "hydra/sweeper=basic", "hydra.sweep.subdir=job_${hydra.job.num}"],
    ["-m", "seed=0,1", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2"],
    ["-m", "seed=0,1", "hydra/launcher=basic"],
    ["-m", "seed=0,1", "hydra.launcher.timeout_s=60", "hydra.sweeper.allow_failures=true"],
    ["hydra/job_logging=disabled", "hydra/hydra_logging=none"],
    ["hydra.output_subdir=.hydra"],
    ["scene=cube", "hydra.mode=RUN"],
    ["-m", "seed=0,1", "hydra.mode=MULTIRUN"],
]


@pytest.mark.parametrize("args", ALLOWED)
def test_documented_invocations_pass(args: list[str]) -> None:
    check_invocation(args)


def test_the_sweeper_and_optuna_options_are_data() -> None:
    """Optuna's sampler targets only from optuna.samplers and only with its sweeper; storage by
    scheme or inside the sweep folder; the sampler's callables refused."""
    optuna = {"sweeper": {"_target_": allowlist.OPTUNA_SWEEPER}}
    nirspi = {"sweeper": {"_target_": "hydra_plugins.nirspi_pipe_sweeper.NirspiSweeper"}}
    key = "sweeper.sampler._target_"
    assert check_kind("optuna_target", key, "optuna.samplers.TPESampler", optuna) is None
    assert check_kind("optuna_target", key, "optuna.samplers.TPESampler", nirspi) is not None
    assert check_kind("optuna_target", key, "os.system", optuna) is not None
    assert check_kind("optuna_target", key, "optuna.samplers.x.y", optuna) is not None
    # storage: a database server by scheme, or SQLite inside the sweep folder (nirspi_pipe.app.study)
    assert check_kind("storage", "sweeper.storage", "redis://127.0.0.1/0", optuna) is not None
    assert check_kind("storage", "sweeper.storage", "sqlite:////tmp/x.db", {**optuna, "sweep": {"dir": "/srv/s"}})
    assert (
        check_kind("storage", "sweeper.storage", "sqlite:////srv/s/x.db", {**optuna, "sweep": {"dir": "/srv/s"}})
        is None
    )
    assert check_kind("storage", "sweeper.storage", "postgresql://db.lab/studies", optuna) is None
    assert check_kind("scalar", "sweeper.sampler.constraints_func", "os.system", optuna) is not None
    assert check_kind("scalar", "sweeper.sampler.seed", 3, optuna) is None
    assert check_kind("direction", "sweeper.direction", ["minimize", "maximize"], optuna) is None
    assert check_kind("direction", "sweeper.direction", "sideways", optuna) is not None


def test_targets_logging_classes_only_at_logging_handler_keys() -> None:
    from nirspi_pipe.app.hydratargets import check_target
    from nirspi_pipe.errors import ConfigError

    check_target("logging.StreamHandler", "hydra.job_logging.handlers.console.class")
    for key in ("hydra.callbacks.logging._target_", "solver.logging._target_", "hydra.job_logging._target_"):
        with pytest.raises(ConfigError):
            check_target("logging.FileHandler", key)


# ------------------------------------------------------------------ config folders (-cd)


def _evil_folder(root: Path) -> Path:
    """A -cd folder whose files try each way: inline logging, callbacks, env_set, a shadowed
    Hydra preset, a primary config."""
    conf = root / "conf"
    (conf / "experiment").mkdir(parents=True)
    for group in ("job_logging", "help", "launcher"):
        (conf / "hydra" / group).mkdir(parents=True)
    victim = root / "VICTIM"
    handler = f"{{class: logging.FileHandler, filename: {victim}, mode: w}}"
    files = {
        "experiment/ok.yaml": "# @package _global_\nseed: 5\n",
        "experiment/logging.yaml": f"# @package _global_\nhydra:\n  job_logging:\n    handlers:\n      file: {handler}\n",
        "experiment/hlogging.yaml": (
            "# @package _global_\nhydra:\n  hydra_logging:\n    handlers:\n"
            f"      x: {{'()': site.addsitedir, sitedir: {root}}}\n"
        ),
        "experiment/callback.yaml": (
            "# @package _global_\nhydra:\n  callbacks:\n    evil: {_target_: os.system, command: touch MARK}\n"
        ),
        "experiment/env.yaml": "# @package _global_\nhydra:\n  job:\n    env_set:\n      LD_PRELOAD: lib.so\n",
        "hydra/job_logging/evil.yaml": f"version: 1\nhandlers:\n  file: {handler}\nroot:\n  handlers: [file]\n",
        "hydra/job_logging/default.yaml": f"version: 1\nhandlers:\n  file: {handler}\nroot:\n  handlers: [file]\n",
        "experiment/meta_evil.yaml": "# @package _global_\nhydra:\n  sweeper:\n    experiments: [ok, logging]\n",
        "experiment/meta_nope.yaml": "# @package _global_\nhydra:\n  sweeper:\n    experiments: [ok, nope]\n",
        "experiment/meta_up.yaml": "# @package _global_\nhydra:\n  sweeper:\n    experiments: [ok, ../x]\n",
        "experiment/meta_ok.yaml": "# @package _global_\nhydra:\n  sweeper:\n    experiments: [ok, table2_ci]\n",
        "hydra/help/evil.yaml": "app_name: x\ntemplate: ${oc.env:HOME}\n",
        "hydra/launcher/evil.yaml": "_target_: os.system\ncommand: touch MARK\n",
        "evil.yaml": f"defaults:\n  - config\n  - _self_\nhydra:\n  job_logging:\n    handlers:\n      file: {handler}\n",
    }
    for name, text in files.items():
        (conf / name).write_text(text)
    victim.write_text(VICTIM_TEXT)
    return conf


_FOLDER_ARGS = [
    ["+experiment=logging"],
    ["+experiment=hlogging"],
    ["+experiment=callback"],
    ["+experiment=env"],
    ["hydra/job_logging=evil"],
    ["hydra/help=evil"],
    ["hydra/launcher=evil"],
    ["-cn", "evil"],
    ["-m", "+experiment=ok,logging"],
    ["-m", "seed=0,1", "+experiment=callback", "hydra/launcher=basic"],
]
_FOLDER_FLAGS = [[], ["--help"], ["--info", "config"], ["--cfg", "job"]]


def _folder_cases() -> list[tuple[list[str], list[str]]]:
    """Each folder attack with each flag; with a flag, a sweep's attack (which needs -m, and -m
    does not combine with --info/--cfg) is tried as its single-run form, without the sweep."""
    cases = []
    for args in _FOLDER_ARGS:
        for flag in _FOLDER_FLAGS:
            if flag and "-m" in args:
                single = [
                    "+experiment=" + a.split(",")[-1] if a.startswith("+experiment=") else a for a in args if a != "-m"
                ]
                single = [a for a in single if not a.startswith("seed=")]
                if (single, flag) in cases:
                    continue
                cases.append((single, flag))
            else:
                cases.append((args, flag))
    return cases


@pytest.mark.parametrize(("args", "flag"), _folder_cases())
def test_config_folder_files_are_checked(args: list[str], flag: list[str], tmp_path: Path) -> None:
    conf = _evil_folder(tmp_path)
    _refused([*flag, "-cd", str(conf), *args])
    assert (tmp_path / "VICTIM").read_text() == VICTIM_TEXT


@pytest.mark.parametrize("args", [["+experiment=logging"], ["+experiment=env"], ["hydra/launcher=evil"]])
def test_a_searchpath_folder_is_checked_like_a_config_folder(args: list[str], tmp_path: Path) -> None:
    """The same files through ``hydra.searchpath=[file://DIR]`` instead of ``-cd DIR``."""
    conf = _evil_folder(tmp_path)
    _refused([f"hydra.searchpath=[pkg://nirspi_pipe.experiments,{conf.as_uri()}]", *args])
    assert (tmp_path / "VICTIM").read_text() == VICTIM_TEXT


@pytest.mark.parametrize("meta", ["meta_evil", "meta_nope", "meta_up"])
def test_a_meta_experiment_in_a_config_folder_is_checked_experiment_by_experiment(meta: str, tmp_path: Path) -> None:
    """``hydra.sweeper.experiments`` naming experiments of a user's folder: each is composed and
    checked as the sweeper will run it; one that sets a logging handler, does not exist or is a
    path is refused. The same list from the package's experiments only is fine."""
    conf = _evil_folder(tmp_path)
    _refused(["-m", "-cd", str(conf), f"+experiment={meta}"])
    check_invocation(["-m", "-cd", str(conf), "+experiment=meta_ok"])


def test_a_config_folder_is_fine_when_its_files_are(tmp_path: Path) -> None:
    conf = _evil_folder(tmp_path)
    inv = check_invocation(["-cd", str(conf), "+experiment=ok"])
    assert "-cd" not in inv.hydra_argv and any(a.startswith("hydra.searchpath=") for a in inv.hydra_argv)
    assert inv.config.seed == 5
    _refused(["-cd", str(tmp_path / "nope")], "a folder that exists")


# ------------------------------------------------------------------ through the installed CLI


def _env(tmp_path: Path) -> dict[str, str]:
    env = {**os.environ, "MPLBACKEND": "Agg", "OPENBLAS_NUM_THREADS": "1"}
    env.pop("NIRSPI_TRACEBACK", None)
    return env


def _snapshot(root: Path) -> set[Path]:
    return {p for p in root.rglob("*")}


def _cli(args: list[str], cwd: Path, timeout: float = 240) -> subprocess.CompletedProcess[str]:
    from conftest import script

    return subprocess.run(
        [script("nirspi-run"), *args], cwd=cwd, capture_output=True, text=True, timeout=timeout, env=_env(cwd)
    )


PICKLE_PAYLOAD = b"cos\nsystem\n(S'touch MARK'\ntR."


@pytest.mark.slow
def test_cli_refuses_every_way_in_one_line(tmp_path: Path) -> None:
    """Each way of the issue, through nirspi-run: exit 2, one line, no MARK, the victim intact,
    nothing written anywhere (the working directory holds exactly what it held)."""
    conf = _evil_folder(tmp_path)
    victim = tmp_path / "VICTIM"
    (tmp_path / "task.pickle").write_bytes(PICKLE_PAYLOAD)
    ways = [
        ["--help", "-cd", str(conf), "hydra/hydra_logging=evil"],
        ["--help", f"+hydra.hydra_logging.handlers.x={{class:io.FileIO,file:{victim},mode:w}}"],
        ["-cd", str(conf), "-cn", "evil"],
        ["--experimental-r", "task.pickle"],
        ["--experimental-rerun", "task.pickle"],
        [f"+hydra.callbacks.logging={{_target_:logging.FileHandler,filename:{victim},mode:w}}"],
        [f"hydra.job_logging.handlers.file.filename={victim}"],
        ["+hydra.job.env_set.LD_PRELOAD=lib.so"],
        ["hydra.output_subdir=../../X"],
        ["-m", "seed=0,1", "hydra/sweeper=basic", "hydra.sweep.subdir=../../X"],
        ["-sc", "query=bash", f"+hydra.callbacks.logging={{_target_:logging.FileHandler,filename:{victim}}}"],
    ]
    before = _snapshot(tmp_path)
    for args in ways:
        res = _cli([*args, "hydra.run.dir=out", "hydra.sweep.dir=sweep"], tmp_path)
        lines = res.stderr.strip().splitlines()
        assert res.returncode == 2 and len(lines) == 1 and lines[0].startswith("nirspi-run: error:"), (args, res.stderr)
        assert not (tmp_path / "MARK").exists(), args
        assert victim.read_text() == VICTIM_TEXT, args
        assert _snapshot(tmp_path) == before, (args, _snapshot(tmp_path) - before)


@pytest.mark.slow
@pytest.mark.parametrize("launcher", ["nirspi", "basic", "joblib"])
def test_sweeps_with_every_launcher_refuse_job_logging_and_write_only_below_the_sweep(
    launcher: str, tmp_path: Path
) -> None:
    """A -m sweep whose experiment (in a -cd folder) sets a job's logging handler: refused
    before any job, with the nirspi launcher and Hydra's basic and joblib launchers. The same
    sweep with a clean experiment runs and writes only below its sweep folder."""
    conf = _evil_folder(tmp_path)
    victim = tmp_path / "VICTIM"
    work = tmp_path / "work"
    work.mkdir()
    common = ["-m", "-cd", str(conf), f"hydra/launcher={launcher}", "hydra.sweep.dir=sweep", "camera.resolution=8"]
    for evil in ("+experiment=logging", "+experiment=ok,logging", "+experiment=env"):
        res = _cli([*common, evil, "seed=0,1"], work)
        assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1, (evil, res.stderr)
        assert victim.read_text() == VICTIM_TEXT and not list(work.iterdir()), evil
    res = _cli([*common, "+experiment=ok", "seed=0,1", "output.quiet=true"], work)
    assert res.returncode == 0, res.stderr[-2000:]
    assert {p.name for p in work.iterdir()} == {"sweep"}
    assert len(list((work / "sweep").rglob("record.json"))) == 2
    assert victim.read_text() == VICTIM_TEXT


# ------------------------------------------------------------------ the Python API elsewhere

_API_SCRIPT = textwrap.dedent(
    """
    import sys
    import nirspi_pipe
    from nirspi_pipe.targets import plugin_targets
    assert "os.system" not in plugin_targets(), "a dist-info in the working directory registered os:system"
    for overrides in (["solver._target_=os.system", "+solver.command=touch MARK"],
                      ["+hydra.job.env_set.LD_PRELOAD=lib.so"],
                      ["+hydra.callbacks.x={_target_:logging.FileHandler,filename:VICTIM,mode:w}"],
                      ["--experimental-rerun", "x"]):
        try:
            nirspi_pipe.run(overrides)
        except ValueError as exc:
            print("REFUSED", str(exc).splitlines()[0])
        else:
            print("RAN", overrides)
    res = nirspi_pipe.run(["camera.resolution=8", "preset=null", "upscale=null", "metrics=default"])
    print("OK", res.reconstruction.shape)
    """
)


@pytest.mark.slow
def test_the_api_in_another_working_directory_ignores_its_plugins(tmp_path: Path) -> None:
    """``python -c`` (the working directory first on sys.path, as in a notebook) in a folder that
    holds a ``*.dist-info`` registering ``os:system`` as a target and plugin, and a
    ``hydra_plugins`` module that creates MARK on import: every attack is refused, a normal run
    works, MARK never appears."""
    dist = tmp_path / "evil_plugin-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: evil-plugin\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text(
        "[nirspi_pipe.targets]\nsystem = os:system\n\n[nirspi_pipe.plugins]\nevil = evil_plugin_mod\n"
    )
    (tmp_path / "evil_plugin_mod.py").write_text("open('MARK', 'w').close()\n")
    (tmp_path / "hydra_plugins").mkdir()
    (tmp_path / "hydra_plugins" / "evil_scan.py").write_text("open('MARK', 'w').close()\n")
    (tmp_path / "VICTIM").write_text(VICTIM_TEXT)
    res = subprocess.run(
        [sys.executable, "-c", _API_SCRIPT],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=240,
        env=_env(tmp_path),
    )
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.count("REFUSED") == 4 and "RAN" not in res.stdout, res.stdout
    assert "OK (8, 8)" in res.stdout
    assert not (tmp_path / "MARK").exists()
    assert (tmp_path / "VICTIM").read_text() == VICTIM_TEXT


# ------------------------------------------------------------------ shell completion


@pytest.mark.parametrize(
    "args",
    [["-sc"], ["-sc", "query=pwsh"], ["-sc", "query=bash", "seed=1"], ["-sc", "install=bash", "query=bash"]],
)
def test_shell_completion_takes_one_shell_word(args: list[str]) -> None:
    _refused(args, "-sc needs exactly one of")


def test_a_completion_query_without_the_shell_is_one_line(monkeypatch: pytest.MonkeyPatch) -> None:
    """``-sc query=bash`` typed by hand (no COMP_LINE): Hydra's completer would raise KeyError."""
    monkeypatch.delenv("COMP_LINE", raising=False)
    _refused(["-sc", "query=bash"], "COMP_LINE", "-sc install=SHELL")
    monkeypatch.setenv("COMP_LINE", "nirspi-run sol")
    check_invocation(["-sc", "query=bash"])  # what the shell calls goes on


@pytest.mark.slow
def test_shell_completion_runs_nothing(tmp_path: Path) -> None:
    """``-sc query=bash`` composes what ``COMP_LINE`` holds to complete it: Hydra's handlers,
    callbacks and logging given there are never applied (Hydra's completion builds nothing)."""
    victim = tmp_path / "VICTIM"
    victim.write_text(VICTIM_TEXT)
    line = (
        f"nirspi-run +hydra.callbacks.x={{_target_:logging.FileHandler,filename:{victim},mode:w}} "
        f"+hydra.hydra_logging.handlers.x={{class:logging.FileHandler,filename:{victim},mode:w}} "
        f"hydra.job_logging.handlers.file.filename={victim} +hydra.job.env_set.LD_PRELOAD=lib.so sc"
    )
    from conftest import script

    before = _snapshot(tmp_path)
    res = subprocess.run(
        [script("nirspi-run"), "-sc", "query=bash"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=240,
        env={**_env(tmp_path), "COMP_LINE": line},
    )
    assert res.returncode == 0 and "scene" in res.stdout, res.stderr[-2000:]
    assert victim.read_text() == VICTIM_TEXT and _snapshot(tmp_path) == before


# ------------------------------------------------------------------ one composition


def test_the_check_composes_once_for_plain_overrides(monkeypatch: pytest.MonkeyPatch) -> None:
    """The default invocation, job group choices and plain value overrides (no ``+``/``~``,
    allow-listed ``hydra.`` leaves) cost one composition, and the shortcut is sound: with plain
    value overrides Hydra's node differs from the reference only at the ``hydra.`` keys they set."""
    import hydra
    from omegaconf import OmegaConf

    from nirspi_pipe.app import composition, hydranode

    calls: list[list[str]] = []
    real = hydra.compose

    def counting(config_name=None, overrides=(), **kw):  # type: ignore[no-untyped-def]
        calls.append(list(overrides))
        return real(config_name, overrides, **kw)

    monkeypatch.setattr(composition, "compose", counting)  # composition binds compose at import
    composition.baseline.cache_clear()
    plain = [
        [],
        ["scene.distance_mm=300", "seed=2", "output.quiet=true"],
        ["hydra.run.dir=/tmp/x", "hydra.job.name=n", "hydra.verbose=true", "camera.resolution=16"],
        ["-m", "seed=0,1", "hydra.launcher.n_jobs=2", "hydra.sweep.dir=out"],
    ]
    for args in plain:
        calls.clear()
        inv = check_invocation(args)
        assert len(calls) == 1, (args, calls)
        assert composition.baseline.cache_info().currsize == 0  # no reference composed
        node = OmegaConf.to_container(inv.config.hydra, resolve=False)
        user, ref = hydranode.flat_leaves(node), hydranode.flat_leaves(composition.baseline(()))
        composition.baseline.cache_clear()
        changed = {k for k in set(user) | set(ref) if user.get(k) != ref.get(k)}
        changed = {k for k in changed if not any(hydranode.key_matches(p, k) for p in allowlist.IGNORED_KEYS)}
        set_keys = {a.split("=", 1)[0][len("hydra.") :] for a in args if a.startswith("hydra.")}
        assert changed <= set_keys, (args, changed)
    for args in (["scene=cube", "hydra.run.dir=/tmp/x"], ["-m", "+experiment=paper_ci", "hydra.launcher.n_jobs=2"]):
        calls.clear()
        check_invocation(args)  # job group choices: shipped option files (trusted), no reference
        assert len(calls) == 1 and composition.baseline.cache_info().currsize == 0, (args, calls)
    calls.clear()
    check_invocation(["hydra/launcher=joblib", "hydra.run.dir=/tmp/x"])  # a hydra/ choice: the reference
    assert len(calls) == 3 and composition.baseline.cache_info().currsize == 2  # the default's choices, then joblib's
    calls.clear()
    check_invocation(["hydra/launcher=joblib", "scene=torus"])
    assert len(calls) == 1  # the reference is cached per process and choices
    for attack in ("hydra.job.chdir=true", "hydra.run.dir=", "hydra.job.name=../x"):
        _refused([attack])  # a plain override of a key off the allow-list or a bad value


@pytest.mark.slow
def test_the_cli_in_another_working_directory_ignores_its_plugins(tmp_path: Path) -> None:
    """``nirspi-run`` in a folder with a ``*.dist-info`` registering ``os:system`` (target and
    plugin) and a ``hydra_plugins`` module, with ``PYTHONPATH=.`` (Python makes it the folder's
    absolute path): the target is refused, the plugin is not listed, MARK never appears."""
    dist = tmp_path / "evil_plugin-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: evil-plugin\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text(
        "[nirspi_pipe.targets]\nsystem = os:system\n\n[nirspi_pipe.plugins]\nevil = evil_plugin_mod\n"
    )
    (tmp_path / "evil_plugin_mod.py").write_text("open('MARK', 'w').close()\n")
    (tmp_path / "hydra_plugins").mkdir()
    (tmp_path / "hydra_plugins" / "evil_scan.py").write_text("open('MARK', 'w').close()\n")
    from conftest import script

    env = _env(tmp_path)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (".", env.get("PYTHONPATH", "")) if p)
    run = [script("nirspi-run")]
    attack = subprocess.run(
        [*run, "solver._target_=os.system", "+solver.command=touch MARK", "hydra.run.dir=out"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=240,
        env=env,
    )
    assert attack.returncode == 2 and "os.system" in attack.stderr, attack.stderr[-2000:]
    listing = subprocess.run([*run, "--plugins"], cwd=tmp_path, capture_output=True, text=True, timeout=240, env=env)
    assert listing.returncode == 0, listing.stdout + listing.stderr[-2000:]
    # named only as ignored, never loaded
    evil = [line for line in listing.stdout.splitlines() if "evil" in line]
    assert all("IGNORED: not from an installed distribution" in line for line in evil), listing.stdout
    assert not (tmp_path / "MARK").exists() and not (tmp_path / "out").exists()
