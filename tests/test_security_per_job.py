"""Issue 41: the check sees what Hydra runs, for every job of a sweep (docs/hostile.md, "Configs").

Hydra re-applies ``hydra.overrides.hydra`` to every sweep job (``load_sweep_config``) and sweeps
``hydra.overrides.task``; it places a group where its parsed ``@package`` says. Two layers, each
tested on its own:

* layer 1, before Hydra (:func:`nirspi_pipe.app.entry.check_invocation`): what Hydra fills itself
  (``hydra.overrides``, ``hydra.runtime``) must be exactly what it fills from the checked command
  line; no override sets it; no group is placed under ``hydra``;
* layer 2, in the job (:func:`nirspi_pipe.app.hydranode.check_job`, called by the task function, the
  nirspi launcher and the nirspi sweeper): the Hydra node the job received, against the
  allow-list, with layer 1 switched off in a child process.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
from hydra import compose, initialize_config_module
from omegaconf import OmegaConf, open_dict

from nirspi_pipe.app.composition import check_filled_by_hydra
from nirspi_pipe.app.configs import CONFIG_MODULE, CONFIG_NAME
from nirspi_pipe.app.entry import check_invocation
from nirspi_pipe.app.flags import Refused
from nirspi_pipe.app.hydranode import check_job

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


def _planting_folder(root: Path, victim: Path) -> Path:
    """A ``-cd`` folder whose experiments plant what Hydra fills itself."""
    conf = root / "conf"
    (conf / "experiment").mkdir(parents=True)
    files = {
        "ok": "# @package _global_\nseed: 3\n",
        "plant": (
            "# @package _global_\nhydra:\n  overrides:\n    hydra:\n"
            f"      - hydra.job_logging.handlers.file.filename={victim}\n"
        ),
        "plant_task": "# @package _global_\nhydra:\n  overrides:\n    task:\n      - scene._target_=os.system\n",
        "subdir": "# @package _global_\nhydra:\n  overrides:\n    hydra:\n      - hydra.sweep.subdir=../..\n",
        "env": "# @package _global_\nhydra:\n  overrides:\n    hydra:\n      - +hydra.job.env_set.LD_PRELOAD=x.so\n",
        "choice": "# @package _global_\nhydra:\n  runtime:\n    choices:\n      tables: paper\n",
        "outdir": "# @package _global_\nhydra:\n  runtime:\n    output_dir: /etc\n",
        # a logging config at experiment's package: harmless there, a factory at hydra.job_logging
        "x": "version: 1\nhandlers:\n  f:\n    (): os.system\n",
    }
    for name, text in files.items():
        (conf / "experiment" / f"{name}.yaml").write_text(text)
    # two harmless choices that together pick a logging config of this folder (the defaults list
    # interpolates another group's choice): +experiment=comb metrics=comb. Hydra's own logging
    # (hydra_logging): conf/config.yaml chooses hydra/job_logging itself, and the primary config's
    # choice wins over an option file's (tests/test_logging_presets.py)
    (conf / "experiment" / "comb.yaml").write_text(
        "# @package _global_\ndefaults:\n  - override /metrics: default\n  - override /hydra/hydra_logging: ${metrics}\n"
    )
    (conf / "metrics").mkdir()
    (conf / "metrics" / "comb.yaml").write_text(
        (Path(__file__).resolve().parents[1] / "conf/metrics/default.yaml").read_text()
    )
    (conf / "hydra" / "hydra_logging").mkdir(parents=True)
    (conf / "hydra" / "hydra_logging" / "comb.yaml").write_text(
        f"version: 1\nhandlers:\n  f:\n    class: logging.FileHandler\n    filename: {victim}\n    mode: w\n"
        "root:\n  handlers: [f]\n"
    )
    return conf


# ------------------------------------------------------------------ layer 1: before Hydra


@pytest.mark.parametrize(
    "override",
    [
        'hydra.overrides.hydra=["hydra.job_logging.handlers.file.filename=VICTIM"]',
        "hydra.overrides.task=['scene._target_=os.system']",
        "+hydra.overrides.hydra=['hydra.sweep.subdir=../..']",
        "++hydra.overrides.task=['a=1']",
        "~hydra.overrides",
        "+hydra.runtime.choices.experiment=paper",
        "hydra.runtime.output_dir=/etc",
        "~hydra.runtime.choices.scene",
        "hydra={}",
    ],
)
@pytest.mark.parametrize("flags", [[], ["-m"]])
def test_no_override_sets_what_hydra_fills(override: str, flags: list[str]) -> None:
    _refused([*flags, override, "camera.resolution=8"], "is not allowed")


def test_layer_one_compares_the_lists_hydra_fills() -> None:
    """The comparison itself, on nodes Hydra composed (no command-line refusal involved)."""
    overrides = ["hydra.verbose=true", "scene=cube"]
    with initialize_config_module(CONFIG_MODULE, version_base="1.3"):
        clean = compose(CONFIG_NAME, overrides, return_hydra_config=True)
        planted = compose(
            CONFIG_NAME, [*overrides, "hydra.overrides.hydra=['hydra.sweep.subdir=x']"], return_hydra_config=True
        )
        choice = compose(CONFIG_NAME, [*overrides, "+hydra.runtime.choices.experiment=paper"], return_hydra_config=True)
    check_filled_by_hydra(OmegaConf.to_container(clean.hydra), overrides)  # type: ignore[arg-type]
    with pytest.raises(Refused, match="hydra.overrides differs from the command line"):
        check_filled_by_hydra(OmegaConf.to_container(planted.hydra), overrides)  # type: ignore[arg-type]
    with pytest.raises(Refused, match="hydra.runtime.choices.experiment"):
        node = OmegaConf.to_container(choice.hydra)
        known = dict(clean.hydra.runtime.choices)  # what Hydra chose for these overrides
        check_filled_by_hydra(node, [*overrides, "+hydra.runtime.choices.experiment=paper"], known)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["+experiment=plant"], "hydra.overrides differs from the command line"),
        (["+experiment=plant_task"], "hydra.overrides differs from the command line"),
        (["+experiment=subdir"], "hydra.overrides differs from the command line"),
        (["+experiment=env"], "hydra.overrides differs from the command line"),
        (["+experiment=ok,plant"], "hydra.overrides differs from the command line"),
        (["+experiment=choice(ok,subdir)"], "hydra.overrides differs from the command line"),
        (["+experiment=choice"], "hydra.runtime.choices.tables"),
        (["+experiment=outdir"], "hydra.runtime.output_dir"),
        (["+experiment@hydra.job_logging=choice(x)"], "a package under hydra is not allowed"),
        (["+experiment@hydra.job_logging=x"], "a package under hydra is not allowed"),
        (["+scene@hydra.callbacks.evil=sphere"], "a package under hydra is not allowed"),
        (["+scene@hydra=sphere"], "a package under hydra is not allowed"),
    ],
)
def test_config_files_cannot_plant_what_hydra_fills(args: list[str], message: str, tmp_path: Path) -> None:
    conf = _planting_folder(tmp_path, tmp_path / "VICTIM")
    _refused(["-m", "-cd", str(conf), "hydra/launcher=basic", *args], message)


def test_a_clean_config_folder_still_passes(tmp_path: Path) -> None:
    conf = _planting_folder(tmp_path, tmp_path / "VICTIM")
    inv = check_invocation(["-m", "-cd", str(conf), "+experiment=ok", "seed=0,1"])
    assert inv.config.seed == 3


# ------------------------------------------------------------------ layer 2: in the job


def _job_node(master_overrides: list[str], job_overrides: list[str], num: int = 0) -> object:
    """A job's config as Hydra's launchers compose it (``load_sweep_config``): the master's
    ``hydra.overrides.hydra`` re-applied, then the job's own overrides; no check involved."""
    with initialize_config_module(CONFIG_MODULE, version_base="1.3"):
        master = compose(CONFIG_NAME, master_overrides, return_hydra_config=True)
        again = list(OmegaConf.to_container(master.hydra.overrides.hydra, resolve=False))  # type: ignore[arg-type]
        job = compose(CONFIG_NAME, [*again, *job_overrides], return_hydra_config=True)
    with open_dict(job):
        job.hydra.job.num = num
        job.hydra.job.id = f"app_{num}"
        job.hydra.mode = "MULTIRUN"
    return job


@pytest.mark.parametrize(
    "planted",
    [
        "hydra.job_logging.handlers.file.filename=VICTIM",
        "+hydra.job.env_set.LD_PRELOAD=x.so",
        "hydra.sweep.subdir=../..",
        "+hydra.callbacks.x={_target_:os.system}",
    ],
)
def test_the_job_gate_refuses_a_node_hydra_re_applied(planted: str) -> None:
    job = _job_node([f"hydra.overrides.hydra=[{planted!r}]".replace("'", '"')], ["scene=cube"])
    with pytest.raises(Refused) as err:
        check_job(job.hydra, job)  # type: ignore[attr-defined]
    assert "\n" not in str(err.value)


@pytest.mark.parametrize(
    "job_overrides",
    [
        ["hydra.job_logging.handlers.file.filename=VICTIM"],  # what a swept hydra.overrides.task brings
        ["+hydra.job.env_set.LD_PRELOAD=x.so"],
        ["hydra.sweep.subdir=${hydra.job.num}/../../.."],  # resolves to a path with '..'
        ["hydra.job.chdir=true"],
        ["scene._target_=os.system"],
    ],
)
def test_the_job_gate_refuses_what_a_job_brings(job_overrides: list[str]) -> None:
    job = _job_node([], job_overrides)
    with pytest.raises(Refused):
        check_job(job.hydra, job)  # type: ignore[attr-defined]


@pytest.mark.parametrize(
    "master",
    [
        [],
        ["hydra.sweep.dir=x", "hydra/launcher=basic"],
        ["hydra.sweep.subdir=a_${hydra.job.num}", "hydra.verbose=true"],
    ],
)
def test_the_job_gate_passes_a_clean_job(master: list[str]) -> None:
    job = _job_node(master, ["scene=cube", "seed=4"], num=3)
    check_job(job.hydra, job)  # type: ignore[attr-defined]


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


@pytest.mark.slow
@pytest.mark.parametrize("launcher", ["nirspi", "basic", "joblib"])
def test_planted_overrides_are_refused_before_any_job(launcher: str, tmp_path: Path) -> None:
    """Layer 1 through nirspi-run with each launcher: one line, exit 2, the victim intact,
    nothing written (no sweep folder, nothing outside it)."""
    victim = tmp_path / "VICTIM"
    victim.write_text(VICTIM_TEXT)
    conf = _planting_folder(tmp_path, victim)
    work = tmp_path / "work"
    work.mkdir()
    common = ["-m", f"hydra/launcher={launcher}", "hydra/sweeper=basic", "hydra.sweep.dir=sweep", "camera.resolution=8"]
    ways = [
        [f'hydra.overrides.hydra=["hydra.job_logging.handlers.file.filename={victim}","hydra.sweep.subdir=../.."]'],
        ["-cd", str(conf), "+experiment=plant"],
        ["-cd", str(conf), "+experiment=ok,subdir"],
        ["-cd", str(conf), "+experiment=env"],
        ["-cd", str(conf), "+experiment@hydra.job_logging=choice(x)"],
        ["+scene@hydra.callbacks.evil=sphere"],
    ]
    for way in ways if launcher == "basic" else ways[:2]:  # basic: Hydra's own way of re-applying lists
        res = _cli([*common, *way, "seed=0,1"], work)
        lines = res.stderr.strip().splitlines()
        assert res.returncode == 2 and len(lines) == 1 and lines[0].startswith("nirspi-run: error:"), (way, res.stderr)
        assert victim.read_text() == VICTIM_TEXT and not list(work.iterdir()), way
        assert sorted(p.name for p in tmp_path.iterdir()) == ["VICTIM", "conf", "work"], way


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
@pytest.mark.parametrize("launcher", ["nirspi", "basic", "joblib"])
def test_the_job_gate_alone_stops_every_launcher(launcher: str, tmp_path: Path) -> None:
    """Layer 2 on its own (layer 1 switched off in the child): the planted list reaches the
    jobs, and each launcher's jobs are refused in one line, exit 2, before the job's code runs
    (no record, no folder outside the sweep). With the nirspi launcher the gate runs before
    Hydra touches the job; Hydra's own launchers configure the job's logging first (docs)."""
    (tmp_path / "probe.py").write_text(_LAYER_TWO_ONLY)
    args = [
        "-m",
        f"hydra/launcher={launcher}",
        "hydra/sweeper=basic",
        "hydra.sweep.dir=sweep/deep",
        "camera.resolution=8",
        'hydra.overrides.hydra=["hydra.sweep.subdir=../../../escaped"]',
        "seed=0,1",
    ]
    res = subprocess.run(
        [sys.executable, "probe.py", *args], cwd=tmp_path, capture_output=True, text=True, timeout=240, env=_env()
    )
    assert res.returncode == 2, res.stderr[-2000:]
    assert "nirspi-run: error: job refused:" in res.stderr and "Traceback" not in res.stderr, res.stderr[-2000:]
    assert not list(tmp_path.rglob("record.json"))
    if launcher == "nirspi":
        assert not (tmp_path / "escaped").exists()


# ------------------------------------------------------------------ the search path, before composing

_SEARCHPATH_PROBE = textwrap.dedent(
    """
    import sys
    import nirspi_pipe
    for entry in ("pkg://mod", "structured://mod", "pkg://pkgmod", "pkg://pkgmod.conf"):
        for call in (nirspi_pipe.compose, nirspi_pipe.run):
            try:
                call([f"hydra.searchpath=[{entry}]", "camera.resolution=8"])
            except ValueError as exc:
                print("REFUSED", str(exc).splitlines()[0])
            else:
                print("RAN", entry)
    """
)


def test_the_search_path_is_checked_before_anything_is_imported(tmp_path: Path) -> None:
    """``hydra.searchpath=[pkg://mod]`` next to a ``mod.py``: refused before Hydra composes
    (Hydra imports a pkg:// or structured:// entry's module while composing)."""
    (tmp_path / "mod.py").write_text(f"open({str(tmp_path / 'MARK')!r}, 'w').write('x')\n")
    (tmp_path / "pkgmod").mkdir()
    (tmp_path / "pkgmod" / "__init__.py").write_text(f"open({str(tmp_path / 'MARK2')!r}, 'w').write('x')\n")
    (tmp_path / "probe.py").write_text(_SEARCHPATH_PROBE)
    res = subprocess.run(
        [sys.executable, "probe.py"], cwd=tmp_path, capture_output=True, text=True, timeout=240, env=_env()
    )
    lines = res.stdout.strip().splitlines()
    assert res.returncode == 0 and len(lines) == 8, res.stderr[-2000:]
    assert all(line.startswith("REFUSED hydra.searchpath=") for line in lines), lines
    assert not (tmp_path / "MARK").exists() and not (tmp_path / "MARK2").exists()


# ------------------------------------------------------------------ Hydra's own files, never through a link


@pytest.mark.slow
def test_hydra_files_are_never_written_through_links(tmp_path: Path) -> None:
    """A run folder holding ``.hydra/config.yaml`` and ``cli.log`` as links (``hydra.verbose``
    logs into the job log), a ``.hydra`` that is a folder link, a sweep folder holding a
    ``multirun.yaml`` link and a job's ``.hydra`` link (basic sweeper and launcher): the links
    are replaced, their targets keep their content; a run folder that is a link is refused."""
    victims = [tmp_path / f"V{i}" for i in range(4)]
    for v in victims:
        v.write_text(VICTIM_TEXT)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    out = tmp_path / "out"
    (out / ".hydra").mkdir(parents=True)
    (out / ".hydra" / "config.yaml").symlink_to(victims[0])
    (out / "cli.log").symlink_to(victims[1])
    out2 = tmp_path / "out2"
    out2.mkdir()
    (out2 / ".hydra").symlink_to(elsewhere, target_is_directory=True)
    sweep = tmp_path / "sweep"
    (sweep / "0").mkdir(parents=True)
    (sweep / "multirun.yaml").symlink_to(victims[2])
    (sweep / "0" / ".hydra").symlink_to(elsewhere, target_is_directory=True)
    (sweep / "0" / "cli.log").symlink_to(victims[3])
    common = ["hydra.output_subdir=.hydra", "camera.resolution=8", "output.quiet=true"]
    for args in (["hydra.run.dir=out", "hydra.verbose=true"], ["hydra.run.dir=out2"]):
        res = _cli([*args, *common], tmp_path)
        assert res.returncode == 0, res.stderr[-2000:]
    res = _cli(
        ["-m", "hydra/sweeper=basic", "hydra/launcher=basic", "hydra.sweep.dir=sweep", "seed=0,1", *common], tmp_path
    )
    assert res.returncode == 0, res.stderr[-2000:]
    assert all(v.read_text() == VICTIM_TEXT for v in victims)
    assert not list(elsewhere.iterdir())
    assert (out / ".hydra" / "config.yaml").is_file() and not (out / ".hydra" / "config.yaml").is_symlink()
    assert (out2 / ".hydra").is_dir() and not (out2 / ".hydra").is_symlink()
    linked = tmp_path / "linked"
    linked.symlink_to(elsewhere, target_is_directory=True)
    res = _cli(["hydra.run.dir=linked", *common], tmp_path)
    assert res.returncode == 1 and "symbolic link" in res.stderr and len(res.stderr.strip().splitlines()) == 1
    assert not list(elsewhere.iterdir())


# ------------------------------------------------------------------ skimage: names from a fixed list


def test_skimage_samples_are_files_shipped_with_skimage(monkeypatch: pytest.MonkeyPatch) -> None:
    """Each allowed ``skimage:<name>`` is a file in scikit-image's own data folder, and loads
    to a finite 2D image in [0, 1] with downloading made impossible (pooch's fetch fails)."""
    import numpy as np
    import skimage.data

    from nirspi_pipe.scene.objects import SKIMAGE_SAMPLES, load_gray_image

    folder = Path(str(skimage.data.__file__)).parent
    assert all((folder / file).is_file() for file in SKIMAGE_SAMPLES.values())
    try:
        import pooch

        monkeypatch.setattr(pooch.Pooch, "fetch", lambda *a, **k: pytest.fail("a download was attempted"))
    except ImportError:  # without pooch scikit-image cannot download at all
        pass
    for name in ("camera", "horse", "shepp_logan_phantom", "astronaut", "text"):
        img = load_gray_image(f"skimage:{name}")
        assert img.ndim == 2 and np.isfinite(img).all() and 0 <= img.min() <= img.max() <= 1, name


@pytest.mark.parametrize(
    "name", ["eagle", "download_all", "data_dir", "file_hash", "binary_blobs", "stereo_motorcycle", "", "../x"]
)
def test_other_skimage_names_are_refused_without_calling_skimage(name: str, monkeypatch: pytest.MonkeyPatch) -> None:
    import skimage.data

    from nirspi_pipe.errors import ConfigError
    from nirspi_pipe.scene.objects import load_gray_image

    def boom(*a: object, **k: object) -> None:
        raise AssertionError("a skimage.data function was called")

    for attr in ("eagle", "download_all", "file_hash", "binary_blobs", "stereo_motorcycle"):
        monkeypatch.setattr(skimage.data, attr, boom)
    with pytest.raises(ConfigError, match="skimage:<sample> with sample one of astronaut"):
        load_gray_image(f"skimage:{name}")


# ------------------------------------------------------------------ nirspi-bench gpu: a private folder


def test_the_gpu_check_writes_its_icd_file_in_a_private_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``nirspi-bench gpu`` writes its OpenCL vendor file into a new 0700 folder
    (``tempfile.mkdtemp``), never through a link planted at a fixed name in the temp folder."""
    import stat
    import tempfile

    from nirspi_pipe.benchmarks import gpu

    victim = tmp_path / "VICTIM"
    victim.write_text(VICTIM_TEXT)
    shared = tmp_path / "shared"
    shared.mkdir()
    (shared / "nirspi-icd").symlink_to(tmp_path, target_is_directory=True)
    (tmp_path / "nvidia.icd").symlink_to(victim)
    monkeypatch.setenv("TMPDIR", str(shared))
    monkeypatch.setattr(tempfile, "tempdir", None)  # TMPDIR read again
    monkeypatch.setattr(gpu.glob, "glob", lambda pattern: ["/usr/lib64/libnvidia-opencl.so.1"])
    monkeypatch.setattr(gpu, "Path", lambda p: tmp_path / "no-vendors" if p == "/etc/OpenCL/vendors" else Path(p))
    env, line = gpu.nvidia_icd_env({})
    folder = Path(env["OCL_ICD_VENDORS"])
    assert folder.parent == shared and folder.name.startswith("nirspi-icd-") and not folder.is_symlink()
    assert stat.S_IMODE(folder.stat().st_mode) == 0o700
    assert (folder / "nvidia.icd").read_text() == "/usr/lib64/libnvidia-opencl.so.1\n"
    assert victim.read_text() == VICTIM_TEXT and str(folder) in line


# ------------------------------------------------------------------ tracebacks and silent acceptances (issue 41)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["seed=${seed}"], "seed: the interpolation does not resolve (Recursive interpolation"),
        (["seed=${nope}"], "seed: the interpolation does not resolve"),
        (["-m", "hydra/sweeper=optuna", "objective=metrics.psnr", "hydra.sweeper.max_failure_rate=5"], "[0, 1]"),
        (
            ["-m", "hydra/sweeper=optuna", "objective=metrics.psnr", "+hydra.sweeper.sampler._partial_=true"],
            "_partial_",
        ),
    ],
)
def test_values_that_crashed_later_are_refused_in_one_line(args: list[str], message: str) -> None:
    _refused(args, message)


@pytest.mark.slow
def test_cli_flags_and_folders_that_crashed_or_were_ignored(tmp_path: Path) -> None:
    """``--version``/``--plugins`` with anything else: refused (exit 2); a run folder Hydra
    cannot create (``/proc/nope``): one line naming it, exit 1, no traceback."""
    for args in (["--version", "seed=1"], ["--plugins", "-m"], ["--version", "--plugins"]):
        res = _cli(args, tmp_path)
        assert res.returncode == 2 and "takes nothing else" in res.stderr and not res.stdout, (args, res.stderr)
    res = _cli(["hydra.run.dir=/proc/nope/x", "camera.resolution=8"], tmp_path)
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 1 and len(lines) == 1 and "hydra.run.dir" in lines[0] and "/proc/nope" in lines[0], (
        res.stderr
    )


# ------------------------------------------------------------------ generative: what each job receives

_PIECES = [
    'hydra.overrides.hydra=["hydra.job_logging.handlers.file.filename=VICTIM"]',
    "hydra.overrides.task=['hydra.sweep.subdir=../..']",
    "+hydra.runtime.choices.experiment=paper",
    "+experiment@hydra.job_logging=x",
    "+scene@hydra.callbacks.evil=sphere",
    "+experiment=plant",
    "+experiment=ok,subdir",
    "+experiment=env",
    "+experiment=ok",
    "hydra.sweep.subdir=../..",
    "hydra.sweep.subdir=a_${hydra.job.num}",
    "hydra.job.name=n1",
    "hydra.verbose=true",
    "seed=${seed}",
    "seed=0,1",
    "scene=cube,sphere",
    "camera.resolution=8,16",
]
#: Hydra's settings a job may never receive changed (the oracle, independent of the allow-list code).
_FIXED = ("job_logging", "hydra_logging", "callbacks", "job.env_set", "job.env_copy", "job.chdir", "output_subdir")


def _select(node: dict, dotted: str) -> object:
    for part in dotted.split("."):
        node = node.get(part) if isinstance(node, dict) else None  # type: ignore[assignment]
    return node


_JOBS: list[tuple[dict, str]] = []


def _capture(cfg: object) -> None:  # the task function Hydra's basic launcher runs per job
    from hydra.core.hydra_config import HydraConfig

    hc = HydraConfig.get()
    _JOBS.append((OmegaConf.to_container(hc, resolve=False), str(hc.runtime.output_dir)))  # type: ignore[arg-type]


@pytest.mark.slow
def test_every_job_hydra_runs_receives_a_node_inside_the_allow_list(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Hypothesis draws override combinations (lists Hydra fills, packages, interpolations,
    sweeps, ``-cd`` experiments); each is checked, and what passes is run by Hydra itself
    (``hydra.main``, basic sweeper and launcher: Hydra's own per-job composition) with a task
    that records each job's Hydra node: no job's logging, callbacks, environment, chdir or
    output_subdir differs from the default, and every job folder lies inside the sweep folder."""
    import hydra
    from hypothesis import HealthCheck, example, given, settings
    from hypothesis import strategies as st

    with initialize_config_module(CONFIG_MODULE, version_base="1.3"):
        default = OmegaConf.to_container(compose(CONFIG_NAME, [], return_hydra_config=True).hydra, resolve=False)
    root = tmp_path_factory.mktemp("gen")
    conf = _planting_folder(root, root / "VICTIM")
    counter = iter(range(10**6))

    @settings(max_examples=8, deadline=None, suppress_health_check=list(HealthCheck), derandomize=True)
    @given(st.lists(st.sampled_from(_PIECES), min_size=1, max_size=3, unique=True))
    @example(["+experiment=ok,comb", "metrics=comb,default"])  # each value alone passes (issue 41)
    def one(pieces: list[str]) -> None:
        sweep = root / f"s{next(counter)}"
        pieces = [piece.replace("VICTIM", str(root / "VICTIM")) for piece in pieces]
        args = ["-m", "-cd", str(conf), "hydra/sweeper=basic", "hydra/launcher=basic", f"hydra.sweep.dir={sweep}"]
        try:
            inv = check_invocation([*args, *pieces])
        except Refused as exc:
            assert "\n" not in str(exc)
            return
        _JOBS.clear()
        old = sys.argv
        sys.argv = ["nirspi-run", *inv.hydra_argv]
        try:
            hydra.main(version_base="1.3", config_path=f"pkg://{CONFIG_MODULE}", config_name=inv.config_name)(
                _capture
            )()
        finally:
            sys.argv = old
        assert _JOBS, pieces
        for node, out_dir in _JOBS:
            for key in _FIXED:
                assert _select(node, key) == _select(default, key), (pieces, key)  # type: ignore[arg-type]
            assert Path(out_dir).resolve().is_relative_to(sweep.resolve()), (pieces, out_dir)
            listed = [str(t) for k in ("hydra", "task") for t in node["overrides"][k]]
            assert not any("hydra.overrides" in t or "hydra.runtime" in t or "@hydra" in t for t in listed), pieces

    one()


@pytest.mark.parametrize(
    "args",
    [
        ["compose", "--experiment", "../../etc/passwd"],
        ["compose", "--sample", "0"],
        ["readers", "--repeat", "-1"],
        ["readers", "--mb", "nan"],
    ],
)
def test_bench_arguments_are_checked_in_one_line(args: list[str], tmp_path: Path) -> None:
    from conftest import script

    res = subprocess.run(
        [script("nirspi-bench"), *args], cwd=tmp_path, capture_output=True, text=True, timeout=120, env=_env()
    )
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and "Traceback" not in res.stderr and "is not" in lines[-1], res.stderr[-2000:]
    assert not res.stdout.strip()


def test_the_summary_says_what_was_measured_and_written(tmp_path: Path) -> None:
    """``scan.ratio=1e-300`` measured one pattern: the head line says so (it printed
    '1e-298 % of the patterns'); a summary.png left from an earlier run is not announced after
    'summary.png not written'."""
    from nirspi_pipe.summary import format_summary

    record = {
        "choices": {"scene": "sphere", "scan": "basic", "solver": "fwht"},
        "config": {"camera": {"resolution": 8}, "scan": {"ratio": 1e-300}},
        "meta": {"status": "ok", "seed": 0, "warnings": ["summary.png not written: disk full"]},
        "info": {"source": {"patterns_measured": 1}},
    }
    (tmp_path / "summary.png").write_bytes(b"old")
    text = format_summary(record, tmp_path)
    assert "1 of 64 patterns (1.56 %)" in text.splitlines()[0] and "e-298" not in text
    assert "summary.png: truth" not in text and "summary.png not written" in text
