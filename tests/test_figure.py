"""summary.png (nirspi_pipe.figure): every text inside the picture, and the numbers it prints are
the record's (issue 27: the picture was cut at the bottom; its histogram disagreed with its header;
issue 34: two grids and two definitions of depth error under one headline, a legend over the bars)."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import matplotlib.pyplot as plt
import pytest

import nirspi_pipe
from nirspi_pipe.figure import SUMMARY_DPI, SUMMARY_PAD_IN, draw_summary, summary_figure, write_summary_figure

_3D = ["sfs=godunov", "itof=cw4", "fusion=itof", "metrics=full"]


@pytest.fixture(scope="module")
def runs() -> dict[str, Any]:
    return {
        "2d": nirspi_pipe.run([]),  # the default: the device preset, 8² upscaled to 32²
        "3d_up": nirspi_pipe.run(_3D),  # the same with the 3D path: depth scored on 32²
        "3d": nirspi_pipe.run(["preset=off", "camera.resolution=16", *_3D]),  # no upscaling
    }


def _texts(fig: Any) -> list[Any]:
    """The texts drawn: visible, not empty, not a tick or axis label of a hidden axes, not a tick
    label outside its axis' limits (matplotlib keeps those but does not draw them)."""
    out = []
    for ax in fig.axes:
        if ax.axison:
            out += [t for t in (ax.xaxis.label, ax.yaxis.label) if t.get_text()]
        out += [t for t in (ax.title, *ax.texts) if t.get_text()]
        if ax.get_legend():
            out += [t for t in ax.get_legend().get_texts() if t.get_text()]
    return out + [fig._suptitle]


@pytest.mark.parametrize("name", ["2d", "3d_up", "3d"])
def test_summary_png_holds_every_text_and_no_empty_band(runs: dict[str, Any], name: str, tmp_path: Path) -> None:
    from matplotlib.image import imread

    r = runs[name]
    fig = summary_figure(r.products, r.record())
    try:
        renderer = fig.canvas.get_renderer()
        texts = _texts(fig)
        assert len(texts) >= 10  # titles, axis labels, colour-bar labels, the header
        # what summary.png holds: the drawn content plus the pad, at the fixed DPI
        held = fig.get_tightbbox(renderer).padded(SUMMARY_PAD_IN).transformed(fig.dpi_scale_trans)
        # each panel as drawn (its tick labels, axis labels, title, legend, texts) and the header
        boxes = [(ax.get_title() or ax.get_ylabel(), ax.get_tightbbox(renderer)) for ax in fig.axes]
        boxes.append(("header", fig._suptitle.get_window_extent(renderer)))
        assert any(ax.get_xlabel().startswith("x (mm") for ax in fig.axes)
        for what, box in boxes:
            assert box.x0 >= held.x0 and box.y0 >= held.y0 and box.x1 <= held.x1 and box.y1 <= held.y1, (
                f"{what!r} at {box.bounds} outside {held.bounds}"
            )
        # no empty band under the header: the panels' titles start within two of its lines
        header = fig._suptitle.get_window_extent(renderer)
        top_title = max(ax.title.get_window_extent(renderer).y1 for ax in fig.axes if ax.title.get_text())
        assert 0 < header.y0 - top_title < 2 * 9 * SUMMARY_DPI / 72, (header.y0, top_title)
        # nor under the panels: the lowest text is within the pad of the bottom
        assert min(t.get_window_extent(renderer).y0 for t in texts) - held.y0 < 2 * SUMMARY_PAD_IN * SUMMARY_DPI
    finally:
        plt.close(fig)
    h, w = imread(str(write_summary_figure(tmp_path, r.products, r.record()))).shape[:2]
    # (savefig lays the figure out again: a few pixels may differ)
    assert abs(w - held.width) < 0.01 * w and abs(h - held.height) < 0.03 * h, ((w, h), held.bounds)


def _numbers(text: str, key: str) -> float:
    m = re.search(re.escape(key) + r"\s*([-+]?[0-9.]+)", text)
    assert m, f"{key!r} not in {text!r}"
    return float(m.group(1))


def _header(r: Any) -> tuple[str, dict[str, float], list[str]]:
    fig = summary_figure(r.products, r.record())
    try:
        legend = [t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().get_texts()]
        titles = [ax.get_title() for ax in fig.axes]
        return fig._suptitle.get_text(), r.metrics, legend + titles
    finally:
        plt.close(fig)


def _same(printed: float, value: float) -> bool:
    return f"{printed:.3g}" == f"{value:.3g}"


@pytest.mark.parametrize("name", ["2d", "3d_up", "3d"])
def test_header_prints_the_records_numbers(runs: dict[str, Any], name: str) -> None:
    head, m, _ = _header(runs[name])
    assert _numbers(head, "SSIM") == pytest.approx(m["ssim"], abs=5e-4)
    assert _numbers(head, "PSNR") == pytest.approx(m["psnr"], abs=5e-3)
    # the fitted PSNR is shown with the raw one that the raw RMSE gives (issue 34)
    assert _numbers(head, "raw PSNR") == pytest.approx(m["psnr_raw"], abs=5e-3)
    assert _same(_numbers(head, "RMSE"), m["rmse"])
    if name == "2d":
        assert "depth" not in head
        return
    # the headline baseline is Table 3's primary, the offset-free one; the others are named
    assert _same(_numbers(head, "SFS"), m["depth_rmse_sfs_offsetfree_mm"])
    assert _same(_numbers(head, "fused"), m["depth_rmse_fused_mm"])
    assert _numbers(head, "improvement") == pytest.approx(m["improvement_offsetfree_pct"], abs=0.05)
    assert _same(_numbers(head, "global fit"), m["depth_rmse_sfs_fit_mm"])
    assert _same(_numbers(head, "median placed at 200 mm"), m["depth_rmse_sfs_mm"])


@pytest.mark.parametrize(("name", "grid"), [("3d_up", 32), ("3d", 16)])
def test_numbers_drawn_are_the_records(runs: dict[str, Any], name: str, grid: int) -> None:
    """Every number the summary draws is computed from the arrays it draws; each equals the
    record's: one grid (the record's: 32² on the upscaled device run) and one definition."""
    r = runs[name]
    fig, drawn = draw_summary(r.products, r.record())
    try:
        texts = " ".join(t.get_text() for t in _texts(fig))
        legend = " ".join(t.get_text() for ax in fig.axes if ax.get_legend() for t in ax.get_legend().get_texts())
    finally:
        plt.close(fig)
    m = r.metrics
    assert drawn["depth_grid"] == grid
    for key in ("rmse", "depth_rmse_sfs_offsetfree_mm", "depth_rmse_fused_mm", "improvement_offsetfree_pct"):
        assert drawn[key] == pytest.approx(m[key], rel=1e-9, abs=1e-12), key
    assert drawn["depth_pixels"] == m["depth_pixels"]
    assert f"{grid}×{grid} grid" in texts and f"{drawn['depth_pixels']:.0f} compared pixels" in texts
    assert _same(_numbers(texts, "raw RMSE"), m["rmse"])
    assert _same(_numbers(texts, "best offset): RMSE"), m["depth_rmse_sfs_offsetfree_mm"])
    assert _same(_numbers(legend, "SFS, best offset (Alg. A2): RMSE"), m["depth_rmse_sfs_offsetfree_mm"])
    assert _same(_numbers(legend, "fused (Alg. A3): RMSE"), m["depth_rmse_fused_mm"])


def test_device_summary_shows_the_upscaled_image(runs: dict[str, Any]) -> None:
    r = runs["2d"]
    fig, drawn = draw_summary(r.products, r.record())
    try:
        titles = [ax.get_title() for ax in fig.axes]
        shapes = [im.get_array().shape for ax in fig.axes for im in ax.get_images()]
    finally:
        plt.close(fig)
    assert (32, 32) in shapes and (8, 8) in shapes
    up = next(t for t in titles if t.startswith("upscaled"))
    assert "32×32" in up and _numbers(up, "PSNR") == pytest.approx(r.metrics["upscale_psnr"], abs=5e-3)
    assert drawn["rmse"] == pytest.approx(r.metrics["rmse"], rel=1e-9)


@pytest.mark.parametrize("name", ["3d_up", "3d"])
def test_legends_cover_no_data(runs: dict[str, Any], name: str) -> None:
    r = runs[name]
    fig = summary_figure(r.products, r.record())
    try:
        renderer = fig.canvas.get_renderer()
        legends = [ax.get_legend() for ax in fig.axes if ax.get_legend()]
        assert legends
        for legend in legends:
            box = legend.get_window_extent(renderer)
            for ax in fig.axes:  # no axes' data area (a panel, a histogram) under a legend
                assert not box.overlaps(ax.get_window_extent(renderer)), (ax.get_title(), box.bounds)
    finally:
        plt.close(fig)


def test_mesh_view_draws_the_truth_on_the_scored_grid(tmp_path: Path) -> None:
    """mesh.png's ground truth is the surface on the grid depth is scored on (32² on the device
    preset), not the 8×8 camera's patch of at most 98 triangles (issue 34)."""
    from matplotlib.image import imread

    from nirspi_pipe.mesh.metrics3d import run_depth_truth
    from nirspi_pipe.mesh.outputs import truth_mesh, write_mesh_outputs

    r = nirspi_pipe.run([*_3D, "surface=power_crust"])
    truth = run_depth_truth(r.products, r.record()["config"])
    assert truth is not None and truth.camera.resolution == 32 == r.products.depth.depth_m.shape[0]
    assert len(truth_mesh(truth).faces) > 2 * 7 * 7
    written = write_mesh_outputs(tmp_path, r.products, render=True, truth=truth)
    assert [p.name for p in written] == ["mesh.ply", "mesh.png"]
    assert imread(str(written[1])).shape[:2] == (450, 900)
