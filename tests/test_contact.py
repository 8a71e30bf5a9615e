"""First contact (issue 27): --help describes the real default, --version is the project's,
nirspi-collect prints a summary, readme_numbers refuses outside a clone."""

from __future__ import annotations

from pathlib import Path

import pytest

from nirspi_pipe import __version__


def test_version_is_the_projects(cli) -> None:
    from importlib.metadata import version

    res = cli("nirspi-run", "--version")
    assert res.returncode == 0, res.stderr
    assert res.stdout.strip() == f"nirspi-pipe {__version__} (hydra-core {version('hydra-core')})"


@pytest.mark.parametrize("overrides", [[], ["preset=null"], ["upscale=bicubic", "upscale.scale=2"]])
def test_help_describes_the_composed_camera(cli, overrides: list[str]) -> None:
    from omegaconf import OmegaConf

    from nirspi_pipe.app.api import compose

    res = cli("nirspi-run", "--help", *overrides)
    assert res.returncode == 0, res.stderr
    head = res.stdout.split("== Examples ==")[0]
    cfg, choices = compose([o.replace("=null", "=off") for o in overrides])
    n = cfg.camera.resolution
    assert f"\n  {n}x{n} patterns" in head, head
    assert f"solver={choices['solver']}: Exact inverse" in head
    up = OmegaConf.select(cfg, "upscale")
    if up is None:
        assert "upscale=null: no upscale stage" in head
    else:
        assert f"upscale={choices['upscale']}:" in head and f"x{up.scale} to {n * up.scale}x{n * up.scale}" in head
    assert "64x64 patterns, exact inverse" not in head  # the old, wrong default
    if not overrides:  # the default camera is the device preset's (one CLI start for both checks)
        assert "8x8 patterns (preset=device)" in head and "x4 to 32x32" in head


@pytest.mark.slow  # a sweep through nirspi-run, then three nirspi-collect starts
def test_collect_prints_a_summary_and_the_table_on_request(cli) -> None:
    args = ["-m", "seed=0,1", "preset=null", "camera.resolution=16", "output.images=false", "hydra.sweep.dir=sweep"]
    assert cli("nirspi-run", *args).returncode == 0
    res = cli("nirspi-collect", "sweep")
    assert res.returncode == 0, res.stderr
    lines = res.stdout.strip().splitlines()
    assert lines[0] == "nirspi-collect: 2 records (2 ok) in sweep", lines
    assert "sweep/results.parquet" in lines[1] and "sweep/results.csv" in lines[1]
    assert len(lines) == 2 and "config_hash" not in res.stdout  # no table
    table = cli("nirspi-collect", "sweep", "--print-table").stdout
    assert "config_hash" in table and len(table.splitlines()) >= 2 + 1 + 2  # header, 2 rows, summary
    assert cli("nirspi-collect", "sweep", "--quiet").stdout == ""


def _fake_install(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """This module as ``pip install .`` places it: in a venv's site-packages, outside any clone."""
    import nirspi_pipe.readme_numbers as rn

    site = tmp_path / "venv" / "lib" / "python3" / "site-packages" / "nirspi_pipe" / "readme_numbers.py"
    monkeypatch.setattr(rn, "_HERE", site)


def test_readme_numbers_refuses_outside_a_clone(tmp_path: Path, monkeypatch, capsys) -> None:
    from nirspi_pipe.readme_numbers import main

    _fake_install(tmp_path, monkeypatch)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    with pytest.raises(SystemExit) as exc:
        main(["--install"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "not run from a clone" in err and str(elsewhere) in err
    assert not list(tmp_path.rglob("readme_numbers.md"))  # nothing written into the "venv"


def test_readme_numbers_finds_the_clone(tmp_path: Path, monkeypatch) -> None:
    from nirspi_pipe.readme_numbers import find_clone, machine_stamp

    repo = Path(__file__).resolve().parents[1]
    assert find_clone() == repo  # an editable install: the clone holding the module
    _fake_install(tmp_path, monkeypatch)
    assert find_clone(tmp_path) is None
    assert find_clone(repo / "docs") == repo  # from inside a clone, installed elsewhere
    assert machine_stamp(repo)["commit"] != "unknown"


def test_table2_noise_model_stays_physical() -> None:
    """The LSM's noise variance c0 + c1·s/2 (tables/table2.py) must stay positive at every
    signal, also when the measured variances happen to slope down (the cause of table2's sqrt
    warning: c1 < 0 made the modelled variance negative at near distances)."""
    import numpy as np

    from nirspi_pipe.tables.table2 import lsm_max_distance

    z = np.linspace(0.2, 0.5, 7)
    s = np.exp(np.log(3e4) - 2 * 0.5 * z) / z**2
    sigma = 420.0 - 20.0 * (s - s.min()) / (s.max() - s.min())  # noise falling with the signal
    assert np.polyfit(0.5 * s, sigma**2, 1)[0] < 0  # an unconstrained fit would slope down
    z_max, fit = lsm_max_distance(z, s, sigma, 64)
    assert fit["c1"] >= 0 and fit["c0"] == pytest.approx(np.mean(sigma**2))
    near = np.exp(fit["a"] - fit["b"] * 0.05) / 0.05**2  # the plot's nearest distance, 5 cm
    assert fit["c0"] + fit["c1"] * 0.5 * near > 0
    assert 0.2 < z_max < 10.0


@pytest.mark.parametrize("quiet", [True, False])
def test_deliberate_segfault_leaves_no_dump(tmp_path: Path, quiet: bool) -> None:
    """crash_as("segv") dies of SIGSEGV without faulthandler's dump, which pytest's faulthandler
    (inherited by forked children) would write into the test log; a crash that is not staged
    (the control: the same fault without crash_as) still dumps."""
    import signal
    import subprocess
    import sys

    tests = Path(__file__).resolve().parent
    crash = "from conftest import crash_as; crash_as('segv')" if quiet else "import ctypes; ctypes.string_at(0)"
    code = f"import sys; sys.path.insert(0, {str(tests)!r}); {crash}"
    res = subprocess.run(
        [sys.executable, "-X", "faulthandler", "-c", code], capture_output=True, text=True, timeout=60, cwd=tmp_path
    )
    assert res.returncode == -signal.SIGSEGV
    assert ("Fatal Python error" in res.stderr) is not quiet, res.stderr


def test_sfs_region_warning_says_what_the_regions_are() -> None:
    """A bright disc (its centre a singular point) and two dim specks just above min_intensity,
    as background noise in the upscaled default image gives: the warning counts the specks'
    pixels and brightness, and the advice it gives (raise sfs.min_intensity) removes it."""
    import warnings

    import numpy as np

    from nirspi_pipe.sfs.models import prepare_image

    y, x = np.mgrid[-16:16, -16:16] + 0.5
    r2 = (x * x + y * y) / 10.0**2
    img = np.where(r2 < 1, np.sqrt(np.clip(1 - r2, 0, 1)), 0.0)  # Lambertian sphere, I = cos θ
    img[1, 1] = img[1, 2] = 0.07  # a 2-pixel speck
    img[30, 3] = 0.06  # a 1-pixel speck
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        prep = prepare_image(img, "auto", 0.05, 1e-3, 0)
    text = " ".join(str(w.message) for w in seen)
    assert prep.info["regions"] == 3 and prep.info["regions_without_singular_point"] == 2
    peak = 0.07 / img.max()  # the auto albedo is the brightest pixel
    assert f"2 of 3 object regions (3 of {int(prep.mask.sum())} object pixels, I/albedo at most {peak:.3g})" in text
    assert "sfs.min_intensity=0.05" in text
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        prep = prepare_image(img, "auto", 0.08, 1e-3, 0)  # above the specks: no warning
    assert prep.info["regions"] == 1
