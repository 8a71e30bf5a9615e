"""Issue 24: no code from config values (the target allow-list), unknown keys refused, the numba
cache private and rebuilt when corrupt. docs/hostile.md says what a config may and may not do."""

from __future__ import annotations

import dataclasses
import os
import stat
import subprocess
import sys
import textwrap
from importlib import resources
from pathlib import Path

import pytest
import yaml

import nirspi_pipe
from nirspi_pipe import targets
from nirspi_pipe.app import hydratargets
from nirspi_pipe.app.entry import check_invocation
from nirspi_pipe.app.flags import Refused
from nirspi_pipe.errors import ConfigError
from nirspi_pipe.targets import PROJECT_TARGETS, check_target, check_targets, locate

#: ``{target: its arguments as a config node}``: each call would create the file MARK if it ran.
ATTACKS = {
    "os.system": {"command": "touch MARK"},
    "subprocess.run": {"args": ["touch", "MARK"]},
    "builtins.eval": {"_args_": ["open('MARK', 'w')"]},
    "importlib.import_module": {"name": "nirspi_evil_module"},
}
#: The same arguments as command-line overrides.
ATTACK_OVERRIDES = {
    "os.system": ["+solver.command=touch MARK"],
    "subprocess.run": ["+solver.args=[touch,MARK]"],
    "builtins.eval": ["+solver._args_=[\"open('MARK', 'w')\"]"],
    "importlib.import_module": ["+solver.name=nirspi_evil_module"],
}
#: A module that creates MARK when imported: on PYTHONPATH in the CLI tests, so an import of it
#: (by importlib.import_module or by locating ``nirspi_evil_module.Thing``) would show.
EVIL_MODULE = "open('MARK', 'w').close()\nclass Thing:\n    pass\n"


def _yaml_targets(node: object) -> set[str]:
    return {str(v) for _, v in targets.find_targets(node, "")}


def test_every_shipped_target_is_allowed_and_imports() -> None:
    """The allow-list is complete for what ships (every option and experiment file, and the nested
    dataclasses whose defaults the schemas expand) and names only importable classes."""
    named: set[str] = set()
    for package in ("nirspi_pipe.conf", "nirspi_pipe.experiments"):
        for path in Path(str(resources.files(package))).rglob("*.yaml"):
            named |= _yaml_targets(yaml.safe_load(path.read_text()) or {})
    named = {t for t in named if not t.startswith(hydratargets.HYDRA_PLUGIN_PREFIXES)} - hydratargets.APP_TARGETS
    assert named and named <= PROJECT_TARGETS, sorted(named - PROJECT_TARGETS)
    assert all(locate(t) is not None for t in hydratargets.APP_TARGETS)
    for target in sorted(PROJECT_TARGETS):
        cls = locate(target)
        assert cls is not None, target
        if dataclasses.is_dataclass(cls):  # nested defaults (Photodiode.budget) are expanded into configs
            for f in dataclasses.fields(cls):
                if dataclasses.is_dataclass(f.default):
                    kind = type(f.default)
                    assert f"{kind.__module__}.{kind.__qualname__}" in PROJECT_TARGETS, (target, f.name)


@pytest.mark.parametrize("target", [*ATTACKS, "nirspi_evil_module.Thing", "nirspi_pipe.outputfiles.atomic_write"])
def test_a_target_off_the_list_is_refused_before_import(target: str, monkeypatch: pytest.MonkeyPatch) -> None:
    imported = []
    monkeypatch.setattr(targets.importlib, "import_module", lambda name: imported.append(name))
    with pytest.raises(ConfigError) as err:
        check_targets({"solver": {"_target_": target, "x": 1}})
    assert str(err.value).startswith(f"solver._target_={target!r} is not allowed; allowed:")
    assert "\n" not in str(err.value) and not imported


def test_targets_are_found_everywhere_in_a_tree() -> None:
    tree = {"a": [{"b": {"_target_": "x.Y"}}], "hydra": {"job_logging": {"handlers": {"h": {"class": "os.system"}}}}}
    assert dict(targets.find_targets(tree, "")) == {
        "a.0.b._target_": "x.Y",
        "hydra.job_logging.handlers.h.class": "os.system",
    }
    # the app's check allows what Hydra builds from its own node, at those keys only
    hydratargets.check_target("hydra_plugins.nirspi_pipe_sweeper.NirspiLauncher", "hydra.launcher._target_")
    with pytest.raises(ConfigError):  # only where Hydra itself checks it is a registered plugin
        hydratargets.check_target("hydra_plugins.nirspi_pipe_sweeper.NirspiLauncher", "solver._target_")
    hydratargets.check_target("logging.StreamHandler", "hydra.job_logging.handlers.console.class")
    with pytest.raises(ConfigError):  # the runner's check allows none of them (issue 42)
        check_target("hydra_plugins.nirspi_pipe_sweeper.NirspiLauncher", "hydra.launcher._target_")


def test_plugins_register_targets_through_entry_point_metadata(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """A plugin's registered class is allowed; another class of the same plugin is not. Read from
    the metadata of an installed distribution (a ``*.dist-info`` on an absolute ``sys.path``
    entry): the plugin is not imported."""
    from importlib.metadata import Distribution

    dist = tmp_path / "nirspi_fake_plugin-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: nirspi-fake-plugin\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text(
        f"[{targets.TARGET_ENTRY_POINTS}]\nGood = nirspi_fake_plugin.solver:GoodSolver\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    eps = list(Distribution.at(dist).entry_points)
    monkeypatch.setattr(targets.metadata, "entry_points", lambda group=None: eps if group else [])
    targets.plugin_targets.cache_clear()
    try:
        check_target("nirspi_fake_plugin.solver.GoodSolver", "solver._target_")
        with pytest.raises(ConfigError, match="nirspi_fake_plugin.solver.GoodSolver"):
            check_target("nirspi_fake_plugin.solver.OtherClass", "solver._target_")
        assert "nirspi_fake_plugin.solver" not in sys.modules
    finally:
        targets.plugin_targets.cache_clear()


def _override(target: str) -> list[str]:
    return [f"solver._target_={target}", *ATTACK_OVERRIDES.get(target, [])]


@pytest.mark.parametrize("target", [*ATTACKS, "nirspi_evil_module.Thing"])
def test_python_api_refuses_targets(target: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    (tmp_path / "nirspi_evil_module.py").write_text(EVIL_MODULE)
    for overrides in (
        _override(target),
        [f"+metrics.evil={{_target_: {target}}}"],
        [f"source.effects.extra=[{{_target_: {target}}}]"],
        [f"+hydra.callbacks.evil={{_target_: {target}}}"],
    ):
        with pytest.raises(ValueError, match="is not allowed") as err:
            nirspi_pipe.run(overrides)
        assert "\n" not in str(err.value)
    assert not (tmp_path / "MARK").exists()
    assert "nirspi_evil_module" not in sys.modules


@pytest.mark.parametrize(
    "override, message",
    [
        ("+bogus_top=1", "bogus_top is not a key or group"),
        ("+output.bogus=1", "output.bogus is not a key of output; allowed keys: arrays, images, quiet"),
        ("output.arrays=maybe", "output.arrays='maybe' is not allowed; allowed: true or false"),
        ("tables=foo", "tables='foo' is not allowed; allowed: a list of"),
        ("tables=[table2,nope]", "tables: 'nope' is not a table; allowed: figure9"),
        ("tables=[_common]", "tables: '_common' is not a table"),
        ("+scene.bogus=1", "scene.bogus is not a key; allowed keys: distance_mm, diameter_mm"),
        ("+fog.bogus=1", "fog.bogus is not a key; allowed keys: piezo_frequency_hz"),
        ("+solver.lam=3", "solver.lam is not a key; allowed keys: (none)"),
        ("++scene.reflectance=abc", "scene.reflectance='abc' is not allowed"),
    ],
)
def test_unknown_keys_and_wrong_types_are_refused(override: str, message: str) -> None:
    with pytest.raises(ValueError, match="is not") as err:
        nirspi_pipe.run([override])
    assert message in str(err.value) and "\n" not in str(err.value)


def _refusal(args: list[str]) -> str | None:
    """The one line ``nirspi-run ARGS`` is refused with (its entry check), or None."""
    try:
        check_invocation(args)
    except Refused as exc:
        return str(exc)
    return None


def test_a_sweep_is_checked_value_by_value() -> None:
    assert "os.system" in (_refusal(["-m", "solver._target_=nirspi_pipe.solvers.fwht.FWHTSolver,os.system"]) or "")
    assert "bogus is not a key" in (_refusal(["-m", "+bogus=1,2"]) or "")
    assert "output.images=" in (_refusal(["-m", "output.images=true,maybe"]) or "")
    assert _refusal(["-m", "seed=0,1", "scan=basic,spiral"]) is None


@pytest.mark.parametrize(
    "override, message",
    [
        (
            "hydra.launcher.timeout_s=abc",
            "hydra.launcher.timeout_s='abc' is not allowed; allowed: a number > 0 or null",
        ),
        ("hydra.launcher.timeout_s=-1", "hydra.launcher.timeout_s=-1 is not allowed"),
        ("hydra.launcher.n_jobs=0", "hydra.launcher.n_jobs=0 is not allowed; allowed: -1 (one per core)"),
        (
            "hydra.sweeper.allow_failures=maybe",
            "hydra.sweeper.allow_failures='maybe' is not allowed; allowed: true or false",
        ),
    ],
)
def test_a_sweeps_own_settings_are_one_line(override: str, message: str) -> None:
    assert message in (_refusal(["-m", "seed=0,1", override]) or "")
    assert message in (_refusal(["seed=0", override]) or "")  # Hydra's node is checked in a single run too


def test_hydra_flags_that_load_code_are_refused() -> None:
    assert "unpickles" in (_refusal(["--experimental-rerun", "x.pickle"]) or "")
    assert "--config-dir" in (_refusal(["-cp", "/tmp"]) or "")


@pytest.mark.slow
@pytest.mark.parametrize("target", [*ATTACKS, "nirspi_evil_module.Thing"])
def test_cli_refuses_targets_from_overrides_and_config_files(target: str, tmp_path: Path) -> None:
    """Through ``nirspi-run``: an override, an experiment file on ``hydra.searchpath`` and a Hydra
    callback in a file given by ``--config-dir``. Exit 2, one line, no MARK, nothing imported."""
    from conftest import script

    (tmp_path / "lib").mkdir()
    (tmp_path / "lib" / "nirspi_evil_module.py").write_text(EVIL_MODULE)
    extra = ATTACKS.get(target, {})
    node = {"_target_": target, **extra}
    (tmp_path / "conf" / "experiment").mkdir(parents=True)
    (tmp_path / "conf" / "experiment" / "evil.yaml").write_text(
        "# @package _global_\n" + yaml.safe_dump({"solver": node})
    )
    (tmp_path / "conf" / "experiment" / "evil_callback.yaml").write_text(
        "# @package _global_\n" + yaml.safe_dump({"hydra": {"callbacks": {"evil": node}}})
    )
    searchpath = "hydra.searchpath=[pkg://nirspi_pipe.experiments,nirspi-schema://nirspi_pipe.conf,file://{}]".format(
        tmp_path / "conf"
    )
    env = {**os.environ, "PYTHONPATH": str(tmp_path / "lib"), "MPLBACKEND": "Agg"}
    env.pop("NIRSPI_TRACEBACK", None)
    for args in (
        _override(target),
        [searchpath, "+experiment=evil"],
        ["-cd", str(tmp_path / "conf"), "+experiment=evil_callback"],
    ):
        res = subprocess.run(
            [script("nirspi-run"), *args, "hydra.run.dir=out"],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=180,
            env=env,
        )
        assert res.returncode == 2, (args, res.stderr)
        lines = res.stderr.strip().splitlines()
        assert len(lines) == 1 and "is not allowed" in lines[0] and target in lines[0], res.stderr
        assert not (tmp_path / "MARK").exists(), args


def test_numba_cache_folder_is_private(tmp_path: Path) -> None:
    """The cache folder is made 0700; one open to others is closed and its cache files dropped;
    a link is not used."""
    from nirspi_pipe.mesh import jitcache

    folder = tmp_path / "cache" / "nirspi-pipe" / "numba"
    assert jitcache._private(folder) and stat.S_IMODE(folder.stat().st_mode) == 0o700
    (folder / "sub").mkdir()
    planted = folder / "sub" / "isotropic.f-1.py311.nbi"
    planted.write_bytes(b"planted")
    folder.chmod(0o777)
    assert jitcache._private(folder) and stat.S_IMODE(folder.stat().st_mode) == 0o700
    assert not planted.exists()
    link = tmp_path / "link"
    link.symlink_to(folder)
    assert not jitcache._private(link)


_TINY = """
import warnings
warnings.simplefilter("always")
from nirspi_pipe.mesh import jitcache

@jitcache.jit
def tinykernel_add(x):
    return x + 1.0

print("RESULT", jitcache.rebuild_on_failure(lambda: tinykernel_add(1.0), modules=("tinykernel",)))
"""


def test_a_corrupt_numba_cache_is_rebuilt_with_a_warning_naming_it(tmp_path: Path) -> None:
    (tmp_path / "tinykernel.py").write_text(textwrap.dedent(_TINY))
    cache = tmp_path / "xdg" / "nirspi-pipe" / "numba"
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env.update(XDG_CACHE_HOME=str(tmp_path / "xdg"), PYTHONPATH=str(tmp_path))

    def run() -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-c", "import tinykernel"],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            env=env,
            timeout=120,
        )

    first = run()
    assert "RESULT 2.0" in first.stdout, first.stderr
    index = [p for p in cache.rglob("*.nbi") if p.name.startswith("tinykernel.")]
    assert index and stat.S_IMODE(cache.stat().st_mode) == 0o700
    for p in index:
        p.write_bytes(p.read_bytes()[:12] + b"\x80garbage")  # the version pickle, then a broken one
    second = run()
    assert "RESULT 2.0" in second.stdout, second.stderr
    assert f"numba cache {cache} did not load" in second.stderr
    third = run()  # rebuilt: loads silently
    assert "RESULT 2.0" in third.stdout and "did not load" not in third.stderr
