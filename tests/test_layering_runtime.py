"""Issue 42, item 4: the two layers hold at run time, not only in the import statements.

* Jobs run through the runner (:func:`nirspi_pipe.execute.execute_job` on a plain-data config)
  in a Python process where Hydra, OmegaConf, the app and the config groups cannot be imported:
  a ``sys.meta_path`` finder, installed before ``nirspi_pipe`` is imported, makes loading them
  raise ``ImportError`` and notes every attempt (so an import swallowed by a
  ``try``/``except ImportError`` shows too). Finding them is allowed: the records' source hash
  reads where ``nirspi_pipe.conf``'s files lie (``importlib.util.find_spec``) without importing
  it. A 2D job, a 3D job (iToF, fusion, surface, 3D metrics), a device replay
  (``source=recorded``) and a live device job (``source=stream`` from the device emulator on
  loopback, served in the same process) finish with status ok, and none of those modules is
  loaded or was asked for. The configs are composed here, with the app, as the command line
  composes them, and handed over as JSON.
* The runner's target check refuses every class of a layer above it (``hydra.*``,
  ``omegaconf.*``, ``nirspi_pipe.app.*``, …), with one line naming the key and why, even when an
  allow-list holds the name; the app allows the classes Hydra builds from its own node, at
  their keys only (:mod:`nirspi_pipe.app.hydratargets`).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from nirspi_pipe import targets
from nirspi_pipe.errors import ConfigError

#: What the child process may not import: the config system and every layer above the runner.
BLOCKED = ("hydra", "hydra_plugins", "omegaconf", "nirspi_pipe.app", "nirspi_pipe.conf")

_CHILD = textwrap.dedent(
    """
    import importlib.abc, importlib.machinery, json, sys
    BLOCKED = {blocked!r}
    attempts = []

    def _blocked(name):
        return any(name == b or name.startswith(b + ".") for b in BLOCKED)

    class _Refuse(importlib.abc.Loader):
        def create_module(self, spec):
            attempts.append(spec.name)
            raise ImportError(f"{{spec.name}} is blocked: the runner runs without Hydra, OmegaConf and the app")

        def exec_module(self, module):
            raise ImportError(f"{{module.__name__}} is blocked")

    class _Blocker:
        # A blocked module is still found (importlib.util.find_spec: where its files lie, which the
        # records' source hash reads), but loading it raises ImportError.
        def find_spec(self, name, path=None, target=None):
            if not _blocked(name):
                return None
            spec = None
            for finder in sys.meta_path:
                if finder is not self and hasattr(finder, "find_spec"):
                    spec = finder.find_spec(name, path, target)
                    if spec is not None:
                        break
            spec = spec or importlib.machinery.ModuleSpec(name, None)
            spec.loader = _Refuse()
            return spec

    sys.meta_path.insert(0, _Blocker())
    from pathlib import Path
    from nirspi_pipe.execute import execute_job

    plans = json.loads(Path(sys.argv[1]).read_text())
    out = {{}}
    for name, cfg in plans.items():
        if name == "stream":  # the device emulator on loopback, in this process: nothing of the app
            from nirspi_pipe.device.emulator import Emulator
            from nirspi_pipe.scene.objects import Sphere
            from nirspi_pipe.types import Camera

            emulator = Emulator(Sphere().render(Camera(16)).radiance, device="layering-test")
            cfg["source"]["port"], thread = emulator.serve_in_thread(connections=1, lifetime_s=60)
        rec = execute_job(cfg, Path(sys.argv[2]) / name, {{}}, [])
        out[name] = {{"status": rec["meta"].get("status"), "error": rec["meta"].get("error"),
                      "metrics": sorted(rec.get("metrics") or {{}}), "stages": sorted(rec.get("timings_ms") or {{}})}}
    # the facade's lazy names are served by the app: reading one is refused too
    import nirspi_pipe
    try:
        nirspi_pipe.run
    except ImportError:
        out["facade"] = "refused"
    out["loaded"] = sorted(m for m in sys.modules if _blocked(m))
    out["attempts"] = attempts
    print(json.dumps(out))
    """
)


def _recording(path: Path, n: int) -> Path:
    """A 16² device recording of the default sphere: explicit interleaved ± Hadamard patterns
    (the format's ``patterns`` form, which needs no scan option resolved by the config layer)."""
    from nirspi_pipe.device.recording import save_recording
    from nirspi_pipe.patterns.hadamard import sylvester
    from nirspi_pipe.scene.objects import Sphere
    from nirspi_pipe.types import Camera

    img = Sphere().render(Camera(n)).radiance
    h = sylvester(n)
    k = np.arange(n * n)
    pm = (h[k // n][:, :, None] * h[k % n][:, None, :]).reshape(n * n, n * n)
    patterns = np.empty((2 * n * n, n * n), dtype=np.float32)
    patterns[0::2], patterns[1::2] = (1 + pm) / 2, (1 - pm) / 2
    y = patterns.astype(np.float64) @ img.ravel()
    return save_recording(path, measurements=y, patterns=patterns, image=img, device="layering-test")


def _plans(tmp_path: Path) -> dict[str, object]:
    """The three jobs' configs, composed by Hydra from the shipped config groups as a job of
    ``nirspi-run`` sees them, as plain data. Pictures only for the replay (summary.png is most of
    a tiny job's time)."""
    from hydra import compose, initialize_config_module

    from nirspi_pipe.app.configs import CONFIG_MODULE, CONFIG_NAME
    from nirspi_pipe.instantiate import plain_config

    small = ["camera.resolution=16", "upscale=off", "output.images=false"]
    jobs = {
        "2d": [*small, "scan.ratio=0.5"],
        "3d": [*small, "sfs=lax_friedrichs", "itof=cw4", "fusion=itof", "surface=power_crust", "metrics=full"],
        "replay": [
            "camera.resolution=16",
            "upscale=off",
            "source=recorded",
            f"source.path={_recording(tmp_path / 'rec.npz', 16)}",
        ],
        "stream": [*small, "source=stream", "source.port=1"],  # the child serves the emulator, sets the port
    }
    with initialize_config_module(CONFIG_MODULE, version_base="1.3"):
        return {name: plain_config(compose(CONFIG_NAME, overrides=ov)) for name, ov in jobs.items()}


def test_jobs_run_with_hydra_omegaconf_and_the_app_blocked(tmp_path: Path) -> None:
    plans = tmp_path / "plans.json"
    plans.write_text(json.dumps(_plans(tmp_path)))
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    proc = subprocess.run(
        [sys.executable, "-c", _CHILD.format(blocked=BLOCKED), str(plans), str(tmp_path / "out")],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=tmp_path,
        env=env,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    for name in ("2d", "3d", "replay", "stream"):
        assert out[name]["status"] == "ok", (name, out[name]["error"])
    assert {"sfs", "itof", "fusion", "surface", "metrics"} <= set(out["3d"]["stages"])
    assert "chamfer_mm" in out["3d"]["metrics"] and "ssim" in out["replay"]["metrics"]
    assert out["facade"] == "refused"
    assert out["loaded"] == [], out["loaded"]
    # the only import asked for is the facade's lazy name, read on purpose above
    assert out["attempts"] == ["nirspi_pipe.app"], out["attempts"]
    assert (tmp_path / "out" / "replay" / "summary.png").is_file()  # the figure's code ran too


# ---- the runner's target check: nothing of a layer above it ---------------------------------

UPPER = [
    "hydra.utils.instantiate",
    "hydra._internal.core_plugins.basic_launcher.BasicLauncher",
    "hydra_plugins.nirspi_pipe_sweeper.NirspiLauncher",
    "omegaconf.OmegaConf.create",
    "nirspi_pipe.app.results.CollectResults",
    "nirspi_pipe.app.api.run",
    "nirspi_pipe.conf.Anything",
    "nirspi_pipe.run",
]


@pytest.mark.parametrize("key", ["solver._target_", "hydra.launcher._target_", "hydra.callbacks.collect._target_"])
@pytest.mark.parametrize("target", UPPER)
def test_the_runner_refuses_targets_above_it_even_when_listed(
    target: str, key: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Listed by the project and registered by a plugin, at the keys where Hydra's node once
    allowed them: still refused, one line naming the key and why, nothing imported."""
    monkeypatch.setattr(targets, "PROJECT_TARGETS", targets.PROJECT_TARGETS | {target})
    monkeypatch.setattr(targets, "plugin_targets", lambda: frozenset({target}))
    imported: list[str] = []
    monkeypatch.setattr(targets.importlib, "import_module", lambda name: imported.append(name))
    with pytest.raises(ConfigError) as err:
        targets.check_target(target, key)
    text = str(err.value)
    assert text.startswith(f"{key}={target!r} is not allowed; allowed: a stage class of the runner")
    assert "the runner builds stages without Hydra, OmegaConf or the app" in text and "\n" not in text
    assert target not in targets.allowed_targets() and not imported


@pytest.mark.parametrize("target", ["nirspi_pipe.app.results.CollectResults", "hydra.utils.instantiate"])
def test_building_an_app_class_from_the_runner_is_refused(target: str) -> None:
    from nirspi_pipe.instantiate import build

    with pytest.raises(ConfigError, match=r"^metrics\._target_=.*the runner builds stages without Hydra"):
        build({"_target_": target}, "metrics")


def test_the_app_allows_what_hydra_builds_at_its_keys_only() -> None:
    from nirspi_pipe.app import hydratargets

    hydratargets.check_target("nirspi_pipe.app.results.CollectResults", "hydra.callbacks.collect._target_")
    hydratargets.check_target("hydra._internal.core_plugins.basic_launcher.BasicLauncher", "hydra.launcher._target_")
    hydratargets.check_target("optuna.samplers.TPESampler", "hydra.sweeper.sampler._target_")
    hydratargets.check_targets({"scene": {"_target_": "nirspi_pipe.scene.objects.Sphere"}})
    for target, key in [
        ("nirspi_pipe.app.results.CollectResults", "metrics._target_"),
        ("nirspi_pipe.app.results.CollectResults", "hydra.launcher._target_"),
        ("hydra._internal.core_plugins.basic_launcher.BasicLauncher", "solver._target_"),
        ("optuna.samplers.TPESampler", "solver._target_"),
        ("hydra.utils.instantiate", "hydra.callbacks.collect._target_"),
    ]:
        with pytest.raises(ConfigError, match=f"^{key}="):
            hydratargets.check_target(target, key)


def test_the_upper_layers_cover_the_architecture_tests_split() -> None:
    """:data:`nirspi_pipe.targets.UPPER_LAYERS` names every layer tests/test_architecture.py puts
    above the runner (the app side, the config system and the command-line tools)."""
    import test_architecture as arch  # tests/ is on sys.path, as for tests/test_deferred_imports.py

    assert set(arch.APP_SIDE) | set(arch.CONFIG_SYSTEM) | set(arch.TOOLS) <= set(targets.UPPER_LAYERS)
    assert set(BLOCKED) <= set(targets.UPPER_LAYERS)
