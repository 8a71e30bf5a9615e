"""A new user's first hour (issue 43, item 7): the small stumbles, each checked as a user meets it."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
from matplotlib.image import imread

from nirspi_pipe.app.results import records_to_frame, tables_by_experiment
from nirspi_pipe.records import PNG_MIN_SIDE, pixel_blocks, write_arrays
from nirspi_pipe.summary import format_summary
from nirspi_pipe.tables import scan_order, table2
from nirspi_pipe.tables._common import bar_figure


def _record(tables: list[str], overrides: list[str], seed: int = 0) -> dict[str, Any]:
    return {
        "meta": {"status": "ok", "seed": seed, "overrides": overrides},
        "choices": {"experiment": "table2", "scene": "sphere"},
        "config": {"tables": tables, "seed": seed, "scene": {"distance_mm": 200.0}},
        "metrics": {"psnr": 20.0},
    }


def test_tables_override_to_none_builds_no_table() -> None:
    """``tables=[]`` on the command line: no table (it was the table named "[]", which failed)."""
    frame = records_to_frame([("a", _record([], ["+experiment=table2", "tables=[]"]))])
    assert frame.loc[0, "tables"] == ""
    assert tables_by_experiment(frame) == {}


def test_tables_override_names_the_tables() -> None:
    """``tables=[table2,table3]``: those tables, not one table named "['table2', 'table3']"."""
    rec = _record(["table2", "table3"], ["+experiment=table2", "tables=[table2,table3]", "scene.distance_mm=200"])
    frame = records_to_frame([("a", rec), ("b", _record(["table2", "table3"], ["tables=[table2,table3]"], seed=1))])
    assert tables_by_experiment(frame) == {"table2": ["table2", "table3"]}
    assert list(frame["seed"]) == [0, 1]
    assert list(frame["scene.distance_mm"].iloc[:1]) == [200.0]


def test_pngs_show_the_pixel_grid_at_a_readable_size(tmp_path: Path) -> None:
    """The PNGs a run writes (write_arrays: reconstruction, upscaled, truth): each pixel a k × k
    block (nearest neighbour, no smoothing), at least PNG_MIN_SIDE a side; the blocks hold the
    arrays' values. (That a default run writes upscaled.png: docs/api.md's doctest lists it.)"""
    rng = np.random.default_rng(0)
    images = {"reconstruction": rng.uniform(-0.1, 1.1, (8, 8)), "upscaled": rng.uniform(0, 1, (32, 32))}
    write_arrays(tmp_path, {}, {**images, "truth": None})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["reconstruction.png", "upscaled.png"]
    for name, raw in images.items():
        a = np.clip(raw, 0.0, 1.0)
        png = imread(tmp_path / f"{name}.png")[..., 0]
        k = png.shape[0] // a.shape[0]
        assert png.shape == (k * a.shape[0], k * a.shape[1]) and min(png.shape) >= PNG_MIN_SIDE, (name, png.shape)
        assert k == -(-PNG_MIN_SIDE // min(a.shape)), (name, k)
        blocks = png.reshape(a.shape[0], k, a.shape[1], k)
        assert np.ptp(blocks, axis=(1, 3)).max() == 0.0, name  # every block one value: no smoothing
        assert np.abs(blocks[:, 0, :, 0] - a).max() <= 2 / 255, name  # 8-bit grey levels, through the colormap


def test_pixel_blocks_leaves_large_images_alone() -> None:
    a = np.arange(512 * 300, dtype=float).reshape(512, 300)
    assert pixel_blocks(a) is a or np.array_equal(pixel_blocks(a), a)
    assert pixel_blocks(np.ones((8, 8))).shape == (256, 256)
    assert pixel_blocks(np.ones((3, 5))).shape == (258, 430)


def _scan_order_frame(gain_db: dict[str, float], seed: int = 0) -> pd.DataFrame:
    """A scan-order results frame: one mechanism at 100 %, 4 objects × 3 seeds per scan, each
    scan's PSNR = a per-sample level + ``gain_db[scan]`` + N(0, 1 dB) noise."""
    rng = np.random.default_rng(seed)
    rows = []
    for scene in ("sphere", "torus", "cube", "u_shape"):
        for s in range(3):
            level = 25.0 + rng.normal(0.0, 2.0)
            for scan in ("basic", "hilbert", "zigzag", "spiral"):
                psnr = level + gain_db.get(scan, 0.0) + rng.normal(0.0, 1.0)
                rows.append(
                    {
                        "status": "ok",
                        "mechanism": "fog_trend",
                        "scan.ratio": 1.0,
                        "scan": scan,
                        "scene": scene,
                        "seed": s,
                        "metrics.psnr": psnr,
                        "metrics.upscale_psnr": psnr - 3.0,
                    }
                )
    return pd.DataFrame(rows)


def _best_cell(tmp_path: Path, frame: pd.DataFrame) -> str:
    scan_order.build(frame, tmp_path)
    row = [line for line in (tmp_path / "scan_order.md").read_text().splitlines() if line.startswith("| fog_trend")]
    assert len(row) == 1
    return row[0].rstrip(" |").rsplit("|", 1)[1].strip()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_scan_order_names_a_winner_only_where_its_screen_supports_one(tmp_path: Path, seed: int) -> None:
    """The "best" column: no difference → none; two scans ahead of the rest but not of each
    other → none, naming both; one scan far ahead of every other → that scan."""
    assert _best_cell(tmp_path, _scan_order_frame({}, seed)) == "none (within noise)"
    both = _best_cell(tmp_path, _scan_order_frame({"zigzag": 6.0, "spiral": 6.0}, seed))
    assert both == "none (within noise: Zig-Zag, Spiral)"
    assert _best_cell(tmp_path, _scan_order_frame({"zigzag": 12.0, "spiral": 6.0}, seed)) == "Zig-Zag"
    assert scan_order.best_scan(_scan_order_frame({"hilbert": 20.0}, seed), "metrics.psnr") == "Hilbert"


_TINY = """
from nirspi_pipe.mesh import jitcache

@jitcache.jit
def tinykernel_add(x):
    return x + 1.0

print("RESULT", jitcache.rebuild_on_failure(lambda: tinykernel_add(1.0), modules=("tinykernel",), what="the tiny kernel"))
"""


def test_numba_compiling_is_announced_and_loading_is_silent(tmp_path: Path) -> None:
    """A cold numba cache (NUMBA_CACHE_DIR: an empty folder): the warm-up says on stderr that it
    compiles, and when it is done with the count and seconds; the second run loads the kernel from
    the cache and says nothing."""
    (tmp_path / "tinykernel.py").write_text(_TINY)
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "cache"), PYTHONPATH=str(tmp_path))

    def run() -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [sys.executable, "-c", "import tinykernel"],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            env=env,
            timeout=120,
        )

    cold = run()
    assert "RESULT 2.0" in cold.stdout, cold.stderr
    lines = [line for line in cold.stderr.splitlines() if line.startswith("numba:")]
    assert lines[0].startswith("numba: compiling the tiny kernel (not in its cache yet"), cold.stderr
    assert str(tmp_path / "cache") in lines[0]
    assert re.fullmatch(r"numba: the tiny kernel: 1 kernels compiled in \d+\.\d s", lines[-1]), cold.stderr
    warm = run()
    assert "RESULT 2.0" in warm.stdout and "numba:" not in warm.stderr, warm.stderr


def test_the_ms_line_shows_a_long_build() -> None:
    """The build (stages set up, kernels compiled) is not in the printed total; when it is long
    (a cold numba cache: 90 s) the ms: line says so, and a warm build is not shown."""
    record: dict[str, Any] = {"meta": {"seed": 0}, "config": {"camera": {"resolution": 8}}, "choices": {}}
    record["timings_ms"] = {"build": 90463.4, "scene": 1.3, "surface": 49.7, "total": 51.0}
    text = format_summary(record)
    assert "total 51.0 | build 90463.4 before the stages, not in total" in text
    record["timings_ms"] = {"build": 3426.6, "scene": 1.3, "surface": 49.7, "total": 51.0}
    ms = [line for line in format_summary(record).splitlines() if "ms:" in line]
    assert ms == ["  ms: scene 1.3 | surface 49.7 | total 51.0"]


def test_figure6_visibility_labels_cross_no_curve() -> None:
    """Each "visibility … m" label's box holds no point of any drawn line (the curves densified to
    ~1 px steps, the threshold and the visibility lines): the chamber's label crossed the other
    curve when it stood along its line at mid height."""
    import matplotlib.pyplot as plt

    fig = table2.contrast_figure(None)
    try:
        fig.canvas.draw()
        ax = fig.axes[0]
        renderer = fig.canvas.get_renderer()  # type: ignore[attr-defined]
        labels = [t for t in ax.texts if t.get_text().startswith("visibility")]
        assert len(labels) == 2
        for text in labels:
            box = text.get_window_extent(renderer).expanded(1.0, 1.0)
            for line in ax.get_lines():
                xy = line.get_transform().transform(line.get_xydata())  # display pixels
                steps = np.linspace(0.0, 1.0, 50)[:, None]
                dense = np.concatenate([a + steps * (b - a) for a, b in zip(xy[:-1], xy[1:], strict=True)])
                x, y = dense[:, 0], dense[:, 1]
                inside = (x >= box.x0) & (x <= box.x1) & (y >= box.y0) & (y <= box.y1)
                assert not inside.any(), (text.get_text(), line.get_label())
    finally:
        plt.close(fig)


def test_bar_plot_tells_the_paper_series_apart() -> None:
    """Two paper series (Table 4's/6's two columns, Table 3's two kLux levels): each legend entry
    its own hatching, outlined in the colour of our series of that name."""
    import matplotlib.pyplot as plt

    series = {"SFS": ([1.0, 2.0], [0.1, 0.1]), "3D mesh": ([3.0, 4.0], [0.2, 0.2])}
    fig = bar_figure("t", ["Basic", "Hilbert"], series, {"SFS": [1.5, 2.5], "3D mesh": [3.5, 4.5]}, "ms", "e")
    try:
        legend = fig.axes[0].get_legend()
        handles = dict(zip([t.get_text() for t in legend.get_texts()], legend.legend_handles, strict=True))
        paper = [handles["paper: SFS"], handles["paper: 3D mesh"]]
        assert paper[0].get_hatch() != paper[1].get_hatch()
        for name in ("SFS", "3D mesh"):
            assert handles[f"paper: {name}"].get_edgecolor() == handles[f"ours: {name}"].get_facecolor()
    finally:
        plt.close(fig)


def test_readme_quotes_docs_readme_numbers() -> None:
    """README's figures are those of the file it cites (docs/readme_numbers.md, written by
    `python -m nirspi_pipe.readme_numbers --install --paper`): the default run's transcript, the
    install's seconds and megabytes, the sweep example's PSNR per kLux, the paper sweep's wall time."""
    root = Path(__file__).resolve().parents[1]
    readme = (root / "README.md").read_text()
    numbers = (root / "docs" / "readme_numbers.md").read_text()
    flat = " ".join(readme.split())
    block = re.search(r"```text\n(.*?)```", numbers, re.S)
    assert block is not None and block.group(1) in readme  # the transcript, ms: line included
    install = re.search(r"`pip install \.` into a fresh venv: (\d+) s, (\d+) MB", numbers)
    assert install is not None and f"took {install[1]} s and left {install[2]} MB" in flat
    rows = re.findall(r"^\| (\d+) \| (\d+\.\d\d ± \d+\.\d\d) \|", numbers, re.M)
    assert len(rows) == 3
    assert all(f"{psnr} dB at {klux}" in flat for klux, psnr in rows), rows
    paper = re.search(r"\| `nirspi-run -m \+experiment=paper` \((\d+) jobs\) \| (\d+\.\d) s \|", numbers)
    assert paper is not None and f"({paper[1]} distinct jobs" in flat and f"{paper[2]} s on this 2-core" in flat
