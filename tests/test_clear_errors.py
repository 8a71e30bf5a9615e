"""Issue 24, item 9: one-line errors naming the argument for the Python API's overrides and
results files, for config files that are not plain YAML (a ``!!python/...`` tag), and for the
device emulator's command line."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest

import nirspi_pipe
from conftest import run_cli
from nirspi_pipe.app.devicecli import main as emulator_main

# ---- nirspi_pipe.run: the overrides argument ---------------------------------------------------


@pytest.mark.parametrize(
    ("overrides", "names"),
    [
        ("camera.resolution=16", ["overrides='camera.resolution=16'", "single string", "['camera.resolution=16']"]),
        ({"seed": 1}, ["overrides={'seed': 1}", "mapping", "['seed=1']"]),
        ([1, 2], ["overrides[0]=1", "not a string"]),
        (["seed=1", None], ["overrides[1]=None", "not a string"]),
        (None, ["overrides=None", "not a list"]),
    ],
)
def test_run_names_the_overrides_argument_in_one_line(overrides: object, names: list[str]) -> None:
    with pytest.raises(nirspi_pipe.BadOverrides) as info:
        nirspi_pipe.run(overrides)  # type: ignore[arg-type]
    text = str(info.value)
    assert "\n" not in text and "allowed: a list of 'key=value' strings" in text
    for part in names:
        assert part in text, (part, text)


def test_compose_takes_any_iterable_of_strings_once() -> None:
    """A generator of strings is read once and composes like the list it yields."""
    cfg, _ = nirspi_pipe.compose(o for o in ["camera.resolution=8", "seed=3"])
    assert cfg.camera.resolution == 8 and cfg.seed == 3


# ---- nirspi_pipe.load_results: a file that is not a table ---------------------------------------


@pytest.mark.parametrize(
    ("name", "content"),
    [
        ("results.csv", b'a,b\n1,2,3,4\n"\x00\xff\n'),  # unbalanced quote: pandas' ParserError
        ("results.csv", bytes(range(128, 256)) * 8),  # not UTF-8
        ("results.parquet", b"PAR1 this is not parquet"),
    ],
)
def test_load_results_names_a_garbage_file(tmp_path: Path, name: str, content: bytes) -> None:
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(nirspi_pipe.BadResults) as info:  # a ValueError
        nirspi_pipe.load_results(path)
    text = str(info.value)
    assert "\n" not in text and text.startswith(f"{path}: not a readable results table")
    assert isinstance(info.value, ValueError)


def test_load_results_garbage_parquet_in_a_sweep_folder_is_named(tmp_path: Path) -> None:
    (tmp_path / "results.parquet").write_bytes(b"\x00" * 64)
    with pytest.raises(nirspi_pipe.BadResults, match=r"results\.parquet: not a readable results table"):
        nirspi_pipe.load_results(tmp_path)
    # refresh rebuilds from the (absent) records instead of reading the broken file
    assert len(nirspi_pipe.load_results(tmp_path, refresh=True)) == 0


def test_load_results_empty_csv_is_an_empty_table(tmp_path: Path) -> None:
    """What collect() writes for a sweep without records (a frame without columns)."""
    path = tmp_path / "results.csv"
    path.write_text(pd.DataFrame().to_csv(index=False))
    assert len(nirspi_pipe.load_results(path)) == 0


# ---- a config file with a !!python tag, or not YAML at all --------------------------------------

EVIL = "# @package _global_\nseed: !!python/object/apply:os.system ['touch {mark}']\n"


def _search_path(tmp_path: Path, text: str) -> Path:
    folder = tmp_path / "configs"
    (folder / "experiment").mkdir(parents=True)
    (folder / "experiment" / "evil.yaml").write_text(text)
    return folder


@pytest.mark.parametrize("multirun", [False, True])
def test_a_python_tag_in_a_config_file_is_one_line_and_runs_nothing(tmp_path: Path, multirun: bool) -> None:
    mark = tmp_path / "MARK"
    folder = _search_path(tmp_path, EVIL.format(mark=mark))
    args = ["nirspi-run", f"hydra.searchpath=[file://{folder}]", "+experiment=evil", "camera.resolution=8"]
    args += ["-m", "seed=1,2", "hydra.sweep.dir=sweep"] if multirun else ["hydra.run.dir=run"]
    res = run_cli(args, tmp_path, timeout=120)
    assert res.returncode == 2, res.stderr[-2000:]
    assert "Traceback" not in res.stderr
    errors = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert errors == [
        f"nirspi-run: error: config file {folder / 'experiment' / 'evil.yaml'}, line 2: the YAML tag "
        "'!!python/object/apply:os.system' is not allowed; allowed: plain YAML values (a config never builds "
        "Python objects)"
    ], res.stderr
    assert not mark.exists()
    assert not (tmp_path / "run").exists() and not (tmp_path / "sweep").exists()


def test_a_yaml_syntax_error_names_the_file_and_line(tmp_path: Path) -> None:
    folder = _search_path(tmp_path, "# @package _global_\nseed: [1, 2\n")
    res = run_cli(
        ["nirspi-run", f"hydra.searchpath=[file://{folder}]", "+experiment=evil", "hydra.run.dir=run"], tmp_path, 120
    )
    assert res.returncode == 2 and "Traceback" not in res.stderr
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and f"config file {folder / 'experiment' / 'evil.yaml'}, line 3: not valid YAML" in lines[0]


def test_a_python_tag_through_the_python_api_is_bad_overrides(tmp_path: Path) -> None:
    mark = tmp_path / "MARK"
    folder = _search_path(tmp_path, EVIL.format(mark=mark))
    with pytest.raises(nirspi_pipe.BadOverrides) as info:
        nirspi_pipe.run([f"hydra.searchpath=[file://{folder}]", "+experiment=evil"])
    text = str(info.value)
    assert "\n" not in text and "evil.yaml, line 2" in text and "'!!python/object/apply:os.system'" in text
    assert not mark.exists()


# ---- nirspi-device-emulator's arguments ----------------------------------------------------------


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--port", "70000"], "--port=70000 is not allowed; allowed: a TCP port from 0 (a free one) to 65535"),
        (["--port", "-1"], "--port=-1 is not allowed"),
        (["--gain", "nan"], "--gain=nan is not allowed; allowed: a finite number > 0"),
        (["--gain", "0"], "--gain=0.0 is not allowed"),
        (["--gain=-inf"], "--gain=-inf is not allowed"),
        (["--noise-rel", "-1"], "--noise-rel=-1.0 is not allowed; allowed: a finite number >= 0"),
        (["--noise-rel", "inf"], "--noise-rel=inf is not allowed"),
        (["--background", "nan"], "--background=nan is not allowed; allowed: a finite number"),
        (["--resolution", "3"], "--resolution=3 is not allowed; allowed: a power of two from 2 to 4096"),
        (["--resolution", "8192"], "--resolution=8192 is not allowed; allowed: a power of two from 2 to 4096"),
        (["--seed", "-2"], "--seed=-2 is not allowed; allowed: an integer >= 0"),
        (["--connections", "0"], "--connections=0 is not allowed; allowed: an integer from 1 to 1000"),
        (["--lifetime-s", "nan"], "--lifetime-s=nan is not allowed; allowed: seconds in (0, 3600]"),
        (
            ["--scene-override", "scene.distance_mm=-5"],
            "scene.distance_mm=-5 is not allowed; allowed: a distance in mm > 0",
        ),
    ],
)
def test_emulator_refuses_bad_arguments_in_one_line(
    args: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as info:
        emulator_main([*args, "--lifetime-s", "0.1"] if "--lifetime-s" not in args else args)
    assert info.value.code == 2
    err = capsys.readouterr()
    assert err.out == ""  # no port printed: nothing listened
    lines = err.err.splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"nirspi-device-emulator: error: {message}"), lines


def test_emulator_with_good_arguments_listens_on_loopback(capsys: pytest.CaptureFixture[str]) -> None:
    """The checks let the boundary values through: port 0, gain > 0, noise 0, resolution 2."""
    import json

    emulator_main(["--port", "0", "--resolution", "2", "--gain", "1e-3", "--noise-rel", "0", "--lifetime-s", "0.05"])
    out = json.loads(capsys.readouterr().out.splitlines()[0])
    assert out["host"] == "127.0.0.1" and 0 < out["port"] <= 65535 and out["n"] == 2
