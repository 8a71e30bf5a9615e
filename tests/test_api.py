"""The Python API (nirspi_pipe.run / load_results), its docs page, the run summary and summary.png."""

from __future__ import annotations

import dataclasses
import doctest
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import nirspi_pipe
from nirspi_pipe.summary import METRIC_HELP, effects_lines, format_summary, metric_lines

DOCS = Path(__file__).resolve().parents[1] / "docs"
NOISE_FREE = ["fog=none", "illumination=none", "detector=ideal"]


def test_docs_api_md_doctest(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Every example in docs/api.md runs and prints what the page says, and leaves nothing in
    the temporary directory (its folder of runs once stayed there)."""
    import tempfile

    scratch = tmp_path / "tmpdir"
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    res = doctest.testfile(
        str(DOCS / "api.md"),
        module_relative=False,
        optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE,
        verbose=False,
    )
    assert res.attempted >= 20 and res.failed == 0
    assert "tempfile" in (DOCS / "api.md").read_text()  # the page does use the temporary directory
    assert sorted(p.name for p in scratch.iterdir()) == []


def test_import_is_cheap_and_lazy() -> None:
    code = (
        "import sys, nirspi_pipe; heavy = [m for m in ('numpy', 'pandas', 'hydra', 'omegaconf', 'matplotlib') "
        "if m in sys.modules]; print(heavy); assert callable(nirspi_pipe.run); print('nirspi_pipe.app.api' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    lines = out.stdout.split()
    assert out.stdout.splitlines()[0] == "[]"  # nothing heavy on import
    assert lines[-1] == "True"  # loaded on first attribute use


def test_unknown_attribute_is_an_attribute_error() -> None:
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        nirspi_pipe.nope  # noqa: B018


def test_run_writes_nothing_and_matches_the_pipeline(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    r = nirspi_pipe.run([*NOISE_FREE, "camera.resolution=16", "scan=zigzag"])
    assert list(tmp_path.iterdir()) == []
    assert dataclasses.is_dataclass(r) and r.output_dir is None
    with pytest.raises(dataclasses.FrozenInstanceError):
        r.metrics = {}  # type: ignore[misc]
    with pytest.raises(TypeError):
        r.metrics["psnr"] = 0.0  # type: ignore[index]
    # noise-free, fully sampled: the inverse is exact whatever the order
    assert r.truth is not None and np.max(np.abs(r.error)) < 1e-9
    assert r.choices["scan"] == "zigzag" and r.config["camera"]["resolution"] == 16
    assert r.timings_ms["total"] >= r.timings_ms["solver"] >= 0
    assert r.seed == 0 and r.overrides[-1] == "scan=zigzag"


def test_run_same_config_same_numbers() -> None:
    a = nirspi_pipe.run(["camera.resolution=16", "seed=3"])
    b = nirspi_pipe.run(["camera.resolution=16", "seed=3"])
    c = nirspi_pipe.run(["camera.resolution=16", "seed=4"])
    np.testing.assert_array_equal(a.reconstruction, b.reconstruction)
    assert not np.array_equal(a.reconstruction, c.reconstruction)  # the default has detector noise


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["scan=spiralx"], "scan=spiralx is not an option; allowed: basic"),
        (["-m", "seed=0,1"], "-m is not an override"),
        (["camera.resolution=100"], "camera.resolution=100 is not allowed"),
    ],
)
def test_bad_overrides_are_one_line_value_errors(overrides: list[str], message: str) -> None:
    with pytest.raises(ValueError) as info:
        nirspi_pipe.run(overrides)
    text = str(info.value)
    assert message in text and "\n" not in text


def test_run_with_output_dir_writes_a_job_folder(tmp_path: Path) -> None:
    r = nirspi_pipe.run(["camera.resolution=16"], output_dir=tmp_path / "job")
    names = {p.name for p in (tmp_path / "job").iterdir()}
    assert {"record.json", "arrays.npz", "summary.png", "reconstruction.png", "truth.png"} <= names
    assert r.output_dir == tmp_path / "job"
    df = nirspi_pipe.load_results(tmp_path)
    assert len(df) == 1 and df["status"].iloc[0] == "ok"
    assert df["metrics.psnr"].iloc[0] == pytest.approx(r.metrics["psnr"])


def test_failed_run_with_output_dir_raises_run_failed(tmp_path: Path) -> None:
    # a mesh file that does not exist fails inside the pipeline, not at composition
    with pytest.raises(nirspi_pipe.RunFailed, match="error.txt"):
        nirspi_pipe.run(
            ["scene=mesh", "scene.path=/nonexistent/x.ply", "camera.resolution=8"], output_dir=tmp_path / "bad"
        )
    assert (tmp_path / "bad" / "error.txt").exists()


def test_load_results_reads_files_and_names_bad_paths(tmp_path: Path) -> None:
    frame = pd.DataFrame({"scan": ["basic", "spiral"], "metrics.psnr": [10.0, 12.0], "status": ["ok", "ok"]})
    frame.to_parquet(tmp_path / "results.parquet", index=False)
    frame.to_csv(tmp_path / "results.csv", index=False)
    pd.testing.assert_frame_equal(nirspi_pipe.load_results(tmp_path), frame)
    pd.testing.assert_frame_equal(nirspi_pipe.load_results(tmp_path / "results.csv"), frame)
    with pytest.raises(FileNotFoundError, match="no such sweep folder"):
        nirspi_pipe.load_results(tmp_path / "missing")
    (tmp_path / "x.txt").write_text("x")
    with pytest.raises(ValueError, match="not a results file"):
        nirspi_pipe.load_results(tmp_path / "x.txt")
    # an empty folder is an empty table, not an error
    (tmp_path / "empty").mkdir()
    assert len(nirspi_pipe.load_results(tmp_path / "empty")) == 0


# ---- the summary text -----------------------------------------------------------------------


def _record(choices: dict, derived: dict, metrics: dict, config: dict | None = None) -> dict:
    return {
        "choices": choices,
        "derived": derived,
        "metrics": metrics,
        "config": config or {},
        "timings_ms": {"solver": 1.0, "total": 2.0},
        "meta": {"seed": 0, "status": "ok", "warnings": []},
    }


def test_summary_names_every_active_effect_with_its_size() -> None:
    rec = _record(
        {"source": "simulator", "fog": "chamber", "illumination": "klux", "detector": "ingaas"},
        {
            "beta_per_m": 1.149,
            "visibility_m": 2.607,
            "transmittance_roundtrip": 0.63,
            "klux": 15.0,
            "background_irradiance_w_m2": 2.71,
            "snr_db": 30.2,
            "saturated_patterns": 3,
        },
        {"ssim": 0.5},
        {"illumination": {"band_nm": [1500.0, 1600.0], "flicker_rel": 0.05}, "fog": {"fluctuation_rel": 0.2}},
    )
    text = "\n".join(effects_lines(rec))
    for part in (
        "β = 1.15 /m",
        "visibility 2.61 m",
        "15 kLux",
        "2.71 W/m²",
        "1500–1600 nm",
        "ingaas",
        "SNR 30.2 dB",
        "3 saturated patterns",
        "flicker 5 %",
        "density fluctuation 20 %",
    ):
        assert part in text, part


def test_summary_says_when_effects_are_off_and_for_measured_data() -> None:
    off = effects_lines(
        _record(
            {"source": "simulator", "fog": "none", "illumination": "none", "detector": "ideal"},
            {"beta_per_m": 0.0, "snr_db": 200.0},
            {},
        )
    )
    assert [line.split()[0] for line in off] == ["fog", "background", "detector"]
    assert all("off" in line or "ideal" in line for line in off)
    measured = effects_lines(_record({"source": "recorded"}, {}, {}))
    assert len(measured) == 1 and "measured data" in measured[0]


def test_every_explained_metric_gets_one_line_and_the_rest_are_counted() -> None:
    metrics = {k: 1.0 for k in METRIC_HELP} | {"skewness_p95": 0.3, "depth_pixels": 100.0}
    lines = metric_lines(metrics)
    assert len(lines) == len(METRIC_HELP) + 1 and lines[-1] == "(+2 more metrics in record.json)"
    improvement = next(line for line in lines if line.startswith("improvement"))
    assert "Eq. (17)" in improvement and "negative" in improvement
    assert "inf" in metric_lines({"psnr": float("inf")})[0]


def test_format_summary_of_a_failed_record() -> None:
    rec = _record({"source": "simulator"}, {}, {})
    rec["meta"].update(status="failed", error="boom")
    assert "FAILED: boom" in format_summary(rec)


# ---- summary.png ----------------------------------------------------------------------------


def _png_size(path: Path) -> tuple[int, int]:
    from matplotlib.image import imread

    h, w = imread(str(path)).shape[:2]
    return w, h


def test_summary_png_2d_and_3d(tmp_path: Path) -> None:
    r2 = nirspi_pipe.run(["camera.resolution=16"])
    p2 = r2.save_figure(tmp_path / "2d")
    r3 = nirspi_pipe.run(["camera.resolution=32", "sfs=godunov", "itof=cw4", "fusion=itof", "metrics=full"])
    p3 = r3.save_figure(tmp_path / "3d")
    w2, h2 = _png_size(p2)
    _, h3 = _png_size(p3)
    assert w2 > 2.5 * h2 * 0.8  # one row of three panels
    assert h3 > 1.7 * h2  # a second row: the depth maps
    # the run keeps going when the picture is off
    r = nirspi_pipe.run(["camera.resolution=16", "output.images=false"], output_dir=tmp_path / "noimg")
    assert not (tmp_path / "noimg" / "summary.png").exists() and r.metrics


@pytest.mark.slow
def test_default_run_is_the_fog_chamber_and_says_so(tmp_path: Path) -> None:
    from conftest import run_cli

    res = run_cli(["nirspi-run", "camera.resolution=32", "hydra.run.dir=run"], tmp_path)
    assert res.returncode == 0, res.stderr
    out = res.stdout
    for part in (
        "fog        chamber: extinction β = 1.15 /m",
        "visibility 2.61 m",
        "background 15 kLux",
        "detector   ingaas",
        "structural similarity",
        "summary.png",
    ):
        assert part in out, part
    rec = json.loads((tmp_path / "run" / "record.json").read_text())
    assert rec["choices"].items() >= {"fog": "chamber", "illumination": "klux", "detector": "ingaas"}.items()
    assert rec["config"]["scene"]["distance_mm"] == 200.0 and rec["config"]["illumination"]["klux"] == 15.0
    assert 0.0 < rec["metrics"]["ssim"] < 0.99 and rec["derived"]["saturated_patterns"] == 0  # not trivial
    assert (tmp_path / "run" / "summary.png").stat().st_size > 10_000
    assert not (tmp_path / "run" / "cli.log").exists()  # Hydra's log file only when something is logged


@pytest.mark.slow
def test_help_teaches(tmp_path: Path) -> None:
    from conftest import run_cli
    from nirspi_pipe.app.validate import config_groups, group_options

    res = run_cli(["nirspi-run", "--help"], tmp_path)
    assert res.returncode == 0, res.stderr
    out = res.stdout
    examples = out.split("== Examples ==")[1].split("==")[0]
    assert sum(line.strip().startswith("nirspi-run") for line in examples.splitlines()) >= 5
    groups = out.split("== Configuration groups")[1].split("== Experiments")[0]
    for group in config_groups():
        if group == "experiment" or not group_options(group) or group == "reference":
            continue
        line = next(x for x in groups.splitlines() if x.startswith((f"{group}:", f"{group} (only with")))
        assert all(opt in line for opt in group_options(group) if opt != "astronaut"), line
    # the experiments package's data folders are not groups; mechanism is scan_order's (issue 34)
    assert "reference" not in groups and "heldout" not in groups
    assert "mechanism (only with +experiment=scan_order" in groups
    experiments = out.split("== Experiments")[1].split("== Installed plugins")[0]
    for name in group_options("experiment"):
        assert f"  {name} " in experiments or experiments.rstrip().endswith(name)
    assert "== Installed plugins" in out and "-sc install=bash" in out
    assert "$" not in out.replace("$(nirspi-run", "")  # no unfilled template variable


# ---- the README numbers script --------------------------------------------------------------


def test_readme_numbers_stamp_and_timer(tmp_path: Path) -> None:
    from nirspi_pipe.readme_numbers import machine_stamp, timed

    stamp = machine_stamp()
    assert set(stamp) == {"when", "platform", "cpu", "load", "commit"}
    assert "cores" in stamp["cpu"] and stamp["load"].count("/") == 2
    assert timed([sys.executable, "-c", "pass"], tmp_path) > 0
    with pytest.raises(RuntimeError, match="failed"):
        timed([sys.executable, "-c", "raise SystemExit(3)"], tmp_path)
