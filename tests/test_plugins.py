"""Plugin discovery: entry points, config search path, failure isolation, and a real pip-installed
throwaway plugin run through ``nirspi-run``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import uuid
from importlib import metadata
from pathlib import Path

import pytest

from nirspi_pipe.app import plugins
from nirspi_pipe.errors import ConfigError


def _pip_flags() -> list[str]:
    """Offline and fast (no build isolation) when this venv can build a wheel itself; otherwise
    let pip fetch setuptools into an isolated build environment."""
    import importlib.util

    offline = importlib.util.find_spec("setuptools") is not None and importlib.util.find_spec("wheel") is not None
    return ["--no-deps", "-q", *(["--no-build-isolation", "--no-index"] if offline else [])]


PIP_FLAGS = _pip_flags()


def _write_module(root: Path, name: str, body: str) -> None:
    (root / f"{name}.py").write_text(textwrap.dedent(body))


@pytest.fixture
def fake_entry_points(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """Install entry points without pip: modules and a ``*.dist-info`` folder in tmp_path (an
    absolute ``sys.path`` entry, as a site folder is). Tests append :func:`_ep` entry points;
    ``entry_points()`` then reads them from that real distribution (written on each call) and
    from nothing else, so that installed plugins cannot change what a test sees."""
    monkeypatch.syspath_prepend(str(tmp_path))
    tag = uuid.uuid4().hex[:8]
    distinfo = tmp_path / f"nirspi_fake_{tag}-0.0.1.dist-info"
    distinfo.mkdir()
    (distinfo / "METADATA").write_text(f"Metadata-Version: 2.1\nName: nirspi-fake-{tag}\nVersion: 0.0.1\n")
    eps: list[metadata.EntryPoint] = []

    def entry_points(group: str | None = None, **_: object):
        groups: dict[str, list[str]] = {}
        for e in eps:
            groups.setdefault(e.group, []).append(f"{e.name} = {e.value}")
        (distinfo / "entry_points.txt").write_text("".join(f"[{g}]\n" + "\n".join(v) + "\n" for g, v in groups.items()))
        found = metadata.Distribution.at(distinfo).entry_points
        assert all(e.dist is not None for e in found)
        return [e for e in found if group in (None, e.group)]

    monkeypatch.setattr(plugins.metadata, "entry_points", entry_points)
    yield tmp_path, eps
    monkeypatch.setattr(plugins, "_REPORT", None)  # forget the fakes


def _ep(name: str, value: str) -> metadata.EntryPoint:
    return metadata.EntryPoint(name=name, value=value, group=plugins.ENTRY_POINT_GROUP)


def test_entry_points_without_an_installed_distribution_are_ignored(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    """Plugins come only from installed distributions: an entry point made in code (no
    distribution behind it) and one whose ``*.dist-info`` lies in the working directory or on a
    relative ``sys.path`` entry register nothing, neither a plugin nor a target."""
    from nirspi_pipe import targets

    tag = uuid.uuid4().hex[:8]
    (tmp_path / f"mod_{tag}.py").write_text("def register():\n    return None\n")
    distinfo = tmp_path / f"nirspi_cwd_{tag}-0.0.1.dist-info"
    distinfo.mkdir()
    (distinfo / "METADATA").write_text(f"Metadata-Version: 2.1\nName: nirspi-cwd-{tag}\nVersion: 0.0.1\n")
    (distinfo / "entry_points.txt").write_text(
        f"[nirspi_pipe.plugins]\ncwd = mod_{tag}:register\n[nirspi_pipe.targets]\nsystem = os:system\n"
    )
    monkeypatch.chdir(tmp_path)
    for entry in ("", ".", str(tmp_path)):  # the working directory, as python -c / a notebook put it there
        monkeypatch.setattr(sys, "path", [entry, *[p for p in sys.path if p not in ("", ".")]])
        real = [e for e in metadata.entry_points(group=plugins.ENTRY_POINT_GROUP) if e.name == "cwd"]
        assert real and real[0].dist is not None  # importlib.metadata does find it there
        assert not targets.installed(real[0])
        assert "os.system" not in targets.plugin_targets.__wrapped__()  # uncached: read now
        caplog.clear()
        report = plugins.discover(refresh=True)
        assert "cwd" not in [p.name for p in report.plugins]
        assert any("plugin 'cwd' was ignored" in r.getMessage() for r in caplog.records), caplog.text
        # ... and not without a word: the report and the refusal say why
        assert ("cwd", os.path.realpath(tmp_path)) in report.ignored
        assert "IGNORED: not from an installed distribution" in plugins.format_report(report)
        with pytest.raises(ConfigError, match="outside the installed distributions") as refused:
            targets.check_target("os.system", "solver._target_")
        assert len(str(refused.value).splitlines()) == 1
    made_in_code = _ep("code", f"mod_{tag}:register")
    assert made_in_code.dist is None and not targets.installed(made_in_code)
    monkeypatch.setattr(plugins.metadata, "entry_points", lambda group=None, **_: [made_in_code])
    report = plugins.discover(refresh=True)
    assert not report.plugins and not report.failures
    assert report.ignored == (("code", "no distribution (made in code)"),)
    monkeypatch.setattr(plugins, "_REPORT", None)


def test_failing_plugins_are_named_and_skipped(fake_entry_points, caplog: pytest.LogCaptureFixture) -> None:
    root, eps = fake_entry_points
    tag = uuid.uuid4().hex[:8]
    conf = root / f"good_{tag}_conf" / "solver"
    conf.mkdir(parents=True)
    (conf.parent / "__init__.py").write_text("")
    (conf / f"good_{tag}.yaml").write_text("_target_: nirspi_pipe.solvers.fwht.FWHTSolver\n")
    _write_module(root, f"good_{tag}", f"SEARCHPATH = 'pkg://good_{tag}_conf'\n")
    _write_module(root, f"raises_{tag}", "raise ImportError('missing dependency foo')\n")
    _write_module(root, f"badret_{tag}", "def register():\n    return 42\n")
    _write_module(root, f"nofolder_{tag}", "def register():\n    return 'pkg://does_not_exist_xyz'\n")
    _write_module(root, f"exits_{tag}", "import sys\nsys.exit(3)\n")
    eps += [
        _ep("good", f"good_{tag}"),
        _ep("raises", f"raises_{tag}"),
        _ep("missing", f"no_such_module_{tag}"),
        _ep("badret", f"badret_{tag}:register"),
        _ep("nofolder", f"nofolder_{tag}:register"),
        _ep("exits", f"exits_{tag}"),
    ]
    report = plugins.discover(refresh=True)
    assert [p.name for p in report.plugins] == ["good"]
    assert report.plugins[0].options == {"solver": [f"good_{tag}"]}
    failed = {f.name: f.error for f in report.failures}
    assert set(failed) == {"raises", "missing", "badret", "nofolder", "exits"}
    assert "missing dependency foo" in failed["raises"]
    assert "ModuleNotFoundError" in failed["missing"]
    assert "int" in failed["badret"]
    assert all("\n" not in e for e in failed.values())
    # one warning line per failure, naming the plugin
    warned = [r.getMessage() for r in caplog.records if r.name == "nirspi_pipe.plugins"]
    assert len(warned) == 5 and all(any(f"'{n}'" in w for w in warned) for n in failed)
    listing = plugins.format_report(report)
    assert f"solver: good_{tag}" in listing and "raises  FAILED" in listing


def test_config_store_entries_are_listed(fake_entry_points) -> None:
    root, eps = fake_entry_points
    tag = uuid.uuid4().hex[:8]
    _write_module(
        root,
        f"store_{tag}",
        f"""
        from dataclasses import dataclass
        from hydra.core.config_store import ConfigStore

        @dataclass
        class Conf:
            _target_: str = "nirspi_pipe.solvers.fwht.FWHTSolver"

        def register():
            ConfigStore.instance().store(name="stored_{tag}", node=Conf, group="solver")
        """,
    )
    eps.append(_ep("store", f"store_{tag}:register"))
    report = plugins.discover(refresh=True)
    assert report.plugins[0].options == {"solver": [f"stored_{tag}"]}
    assert report.plugins[0].searchpath == ()


def test_builtin_option_clash_is_refused_naming_the_plugin(fake_entry_points) -> None:
    root, eps = fake_entry_points
    tag = uuid.uuid4().hex[:8]
    conf = root / f"shadow_{tag}_conf" / "solver"
    conf.mkdir(parents=True)
    (conf.parent / "__init__.py").write_text("")
    (conf / "fwht.yaml").write_text("_target_: nirspi_pipe.solvers.fwht.FWHTSolver\n")
    _write_module(root, f"shadow_{tag}", f"SEARCHPATH = ['pkg://shadow_{tag}_conf']\n")
    eps.append(_ep("shadow", f"shadow_{tag}"))
    report = plugins.discover(refresh=True)
    assert not report.plugins
    assert report.failures[0].name == "shadow" and "solver/fwht" in report.failures[0].error


def test_configstore_clash_is_refused_and_unregistered(fake_entry_points) -> None:
    from hydra.core.config_store import ConfigStore

    root, eps = fake_entry_points
    tag = uuid.uuid4().hex[:8]
    before = ConfigStore.instance().repo.get("scan", {}).get("basic.yaml")
    _write_module(
        root,
        f"clash_{tag}",
        """
        from hydra.core.config_store import ConfigStore
        ConfigStore.instance().store(group="scan", name="basic", node={"ratio": 0.5, "evil": 1})
        ConfigStore.instance().store(group="scan", name="clash_extra", node={"ratio": 0.5})
        """,
    )
    eps.append(_ep("clash", f"clash_{tag}"))
    report = plugins.discover(refresh=True)
    assert [f.name for f in report.failures] == ["clash"] and "scan/basic" in report.failures[0].error
    scan = ConfigStore.instance().repo.get("scan", {})
    assert scan.get("basic.yaml") is before and "clash_extra.yaml" not in scan


@pytest.mark.parametrize(
    "body, expected",
    [
        ("raise SystemExit(3)", "SystemExit"),
        ("raise KeyboardInterrupt", "KeyboardInterrupt"),
        ("import os\nos._exit(0)", "ended the process on import"),
    ],
)
def test_plugin_that_exits_on_import_is_named_and_skipped(fake_entry_points, body: str, expected: str) -> None:
    root, eps = fake_entry_points
    tag = uuid.uuid4().hex[:8]
    _write_module(root, f"exits_{tag}", body + "\n")
    eps.append(_ep("exits", f"exits_{tag}"))
    report = plugins.discover(refresh=True)
    assert not report.plugins
    assert report.failures[0].name == "exits" and expected in report.failures[0].error


_PLUGIN_SOLVER = '''
"""Throwaway nirspi-pipe plugin used by tests/test_plugins.py."""
from dataclasses import dataclass

import numpy as np
from hydra.core.config_store import ConfigStore

from nirspi_pipe.solvers.fwht import zero_filled_inverse
from nirspi_pipe.types import Acquisition, Image2D


@dataclass(frozen=True)
class DoubledSolver:
    """Zero-filled inverse times ``factor`` (a recognisable, wrong-on-purpose solver)."""

    factor: float = 2.0

    def solve(self, acquisition: Acquisition) -> Image2D:
        img = zero_filled_inverse(acquisition.n, acquisition.indices, acquisition.coefficients())
        return Image2D(self.factor * img, info={{"plugin": "throwaway", "factor": self.factor}})


@dataclass(frozen=True)
class Unregistered:
    """A class of the plugin that it does not register: no config may build it."""

    path: str = ""

    def __post_init__(self) -> None:
        open(self.path, "w").close()


@dataclass
class StoredConf:
    _target_: str = "{mod}.DoubledSolver"
    factor: float = 3.0


def register():
    ConfigStore.instance().store(name="{name}_stored", node=StoredConf, group="solver")
    return "pkg://{mod}.conf"
'''


@pytest.mark.slow
def test_throwaway_plugin_pip_installed_runs_through_nirspi_run(tmp_path: Path) -> None:
    tag = uuid.uuid4().hex[:8]
    name, mod = f"tw{tag}", f"nirspi_tw{tag}"
    dist = f"nirspi-tw{tag}"
    pkg = tmp_path / "src" / "pkg"
    (pkg / mod / "conf" / "solver").mkdir(parents=True)
    (pkg / mod / "__init__.py").write_text(_PLUGIN_SOLVER.format(mod=mod, name=name))
    (pkg / mod / "conf" / "__init__.py").write_text("")
    (pkg / mod / "conf" / "solver" / f"{name}.yaml").write_text(f"_target_: {mod}.DoubledSolver\nfactor: 2.0\n")
    (pkg / f"{mod}_broken.py").write_text("raise RuntimeError('this plugin is broken on purpose')\n")
    (tmp_path / "src" / "pyproject.toml").write_text(
        textwrap.dedent(
            f"""
            [build-system]
            requires = ["setuptools>=61"]
            build-backend = "setuptools.build_meta"

            [project]
            name = "{dist}"
            version = "0.0.1"

            [project.entry-points."nirspi_pipe.plugins"]
            {name} = "{mod}:register"
            {name}_broken = "{mod}_broken"

            [project.entry-points."nirspi_pipe.targets"]
            DoubledSolver = "{mod}:DoubledSolver"

            [tool.setuptools]
            package-dir = {{"" = "pkg"}}
            packages = ["{mod}", "{mod}.conf"]
            py-modules = ["{mod}_broken"]

            [tool.setuptools.package-data]
            "{mod}.conf" = ["**/*.yaml"]
            """
        )
    )
    pip = [sys.executable, "-m", "pip"]
    exe = str(Path(sys.executable).with_name("nirspi-run"))
    env = {**os.environ, "MPLBACKEND": "Agg"}
    install = subprocess.run([*pip, "install", *PIP_FLAGS, str(tmp_path / "src")], capture_output=True, text=True)
    assert install.returncode == 0, install.stderr
    try:
        listing = subprocess.run([exe, "--plugins"], capture_output=True, text=True, env=env, timeout=120)
        assert listing.returncode == 0, listing.stderr
        assert f"solver: {name}, {name}_stored" in listing.stdout
        assert f"{name}_broken  FAILED" in listing.stdout and "broken on purpose" in listing.stdout

        out = tmp_path / "run"
        run = subprocess.run(
            [exe, f"solver={name}", "camera.resolution=16", f"hydra.run.dir={out}"],
            capture_output=True,
            text=True,
            env=env,
            timeout=300,
        )
        assert run.returncode == 0, run.stderr
        # the broken plugin is named in one warning line and the run goes on
        warn = [ln for ln in run.stderr.splitlines() if f"{name}_broken" in ln]
        assert len(warn) == 1 and "skipped" in warn[0]
        rec = json.loads((out / "record.json").read_text())
        assert rec["meta"]["status"] == "ok" and rec["info"]["solver"]["plugin"] == "throwaway"
        # the factor-2 solver doubles the (exact) reconstruction: RMSE = mean radiance
        assert rec["metrics"]["rmse"] > 0.0

        sweep = tmp_path / "sweep"
        multi = subprocess.run(
            [
                exe,
                "-m",
                f"solver={name},{name}_stored",
                "camera.resolution=16",
                "hydra/launcher=joblib",
                "hydra.launcher.n_jobs=2",
                f"hydra.sweep.dir={sweep}",
            ],
            capture_output=True,
            text=True,
            env=env,
            timeout=300,
        )
        assert multi.returncode == 0, multi.stderr
        recs = [json.loads(p.read_text()) for p in sorted(sweep.glob("*/record.json"))]
        assert [r["meta"]["status"] for r in recs] == ["ok", "ok"]
        assert sorted(r["info"]["solver"]["factor"] for r in recs) == [2.0, 3.0]

        bad = subprocess.run([exe, f"solver={name}_nope"], capture_output=True, text=True, env=env, timeout=120)
        assert bad.returncode == 2 and f"{name}, {name}_stored" in bad.stderr

        # a class of the plugin that it did not register is refused by name, and never built
        marker = tmp_path / "MARK"
        evil = subprocess.run(
            [
                exe,
                f"solver._target_={mod}.Unregistered",
                f"+solver.path={marker}",
                f"hydra.run.dir={tmp_path / 'evil'}",
            ],
            capture_output=True,
            text=True,
            env=env,
            timeout=120,
        )
        assert evil.returncode == 2 and not marker.exists(), evil.stderr
        assert f"solver._target_='{mod}.Unregistered' is not allowed" in evil.stderr
        assert f"{mod}.DoubledSolver" in evil.stderr  # the registered one is named as allowed
    finally:
        subprocess.run([*pip, "uninstall", "-y", "-q", dist], capture_output=True, text=True)
    gone = subprocess.run([exe, "--plugins"], capture_output=True, text=True, env=env, timeout=120)
    assert name not in gone.stdout
