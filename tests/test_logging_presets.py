"""Every job-logging preset runs (helper k3 found ``hydra/job_logging=stdout`` and ``=disabled`` ending
in a Hydra traceback: conf/config.yaml patched ``hydra.job_logging.handlers.file.delay`` into every
preset, giving those without a file handler a handler 'file' with no class). The delayed log file
is now a preset of its own (conf/hydra/job_logging/nirspi.yaml, Hydra's default plus
``delay: true``), chosen by conf/config.yaml; Hydra's presets run as Hydra ships them.

The project's preset keeps issue 34's promise: a run that logs nothing leaves no empty cli.log.
Because the primary config chooses ``hydra/job_logging`` itself, an option file's ``override
/hydra/job_logging`` no longer reaches the group (the primary config's choice wins); the
combination attacks of tests/test_security_launchers.py therefore go through
``hydra/hydra_logging``, and the last test here pins that an option file cannot pick a job
logging config."""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

from omegaconf import OmegaConf

from nirspi_pipe.app.composition import hydra_group_options

FAST = ["preset=null", "camera.resolution=16", "output.quiet=true", "output.images=false", "output.arrays=false"]

#: Runs ``nirspi-run hydra/job_logging=<preset> …`` for each preset in one process (one start-up
#: for all: each run is a whole Hydra run, logging configured again) and prints what each left.
_EACH_PRESET = textwrap.dedent(
    """
    import json, sys
    from pathlib import Path
    from nirspi_pipe.app import cli
    root, fast, presets = Path(sys.argv[1]), json.loads(sys.argv[2]), sys.argv[3:]
    out = {}
    for preset in presets:
        folder = root / preset
        try:
            cli.run([f"hydra/job_logging={preset}", f"hydra.run.dir={folder}", *fast])
            status = 0
        except SystemExit as exc:
            status = exc.code
        out[preset] = [status, (folder / "record.json").is_file(), (folder / "cli.log").exists()]
    print(json.dumps(out))
    """
)


def test_every_job_logging_preset_runs(tmp_path: Path) -> None:
    presets = hydra_group_options("hydra/job_logging")
    assert {"default", "disabled", "none", "stdout", "nirspi"} <= set(presets)
    script = tmp_path / "each_preset.py"
    script.write_text(_EACH_PRESET)
    done = subprocess.run(
        [sys.executable, str(script), str(tmp_path / "runs"), json.dumps(FAST), *presets],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=tmp_path,
    )
    assert done.returncode == 0 and "Traceback" not in done.stderr, done.stderr[-3000:]
    left = json.loads(done.stdout.strip().splitlines()[-1])
    for preset in presets:
        status, record, log = left[preset]
        assert status in (0, None) and record, (preset, left[preset], done.stderr[-3000:])
        # a log file only from Hydra's default preset, which opens it eagerly; the project's opens it
        # on the first message (this run logs none), the others have no file handler
        assert log == (preset == "default"), (preset, left[preset])


def test_an_option_file_cannot_choose_the_job_logging(tmp_path: Path) -> None:
    """An experiment file's ``override /hydra/job_logging: x`` (a logging config that truncates a
    file) does not reach the group: the primary config's choice, the project's preset, stays, and
    the file is untouched."""
    from nirspi_pipe.app.entry import check_invocation

    victim = tmp_path / "VICTIM"
    victim.write_text("precious\n")
    conf = tmp_path / "conf"
    (conf / "experiment").mkdir(parents=True)
    (conf / "hydra" / "job_logging").mkdir(parents=True)
    (conf / "experiment" / "a.yaml").write_text(
        "# @package _global_\ndefaults:\n  - override /hydra/job_logging: x\nseed: 3\n"
    )
    (conf / "hydra" / "job_logging" / "x.yaml").write_text(
        f"version: 1\nhandlers:\n  f:\n    class: logging.FileHandler\n    filename: {victim}\n    mode: w\n"
        "root:\n  handlers: [f]\n"
    )
    invocation = check_invocation(["-cd", str(conf), "+experiment=a", "camera.resolution=8"])
    assert invocation.config.hydra.runtime.choices["hydra/job_logging"] == "nirspi"
    handlers = OmegaConf.to_container(invocation.config.hydra.job_logging.handlers, resolve=False)
    assert str(victim) not in json.dumps(handlers)
    assert victim.read_text() == "precious\n"
