"""``summary.png``: one labelled picture per run.

Top row: the true radiance, the reconstruction and their difference (reconstruction − truth),
on the scene plane in millimetres, with colour bars in units of a white target's radiance. For
3D runs a second row shows the true depth, the SFS depth made metric by the fusion's scale
(Alg. A2), the fused depth's error against the truth (Alg. A3, mm) and the mesh render
(``mesh.png``, pyvista off screen) when there is one. The title names the scene, scan, solver,
the active effects and the headline metrics, as the record holds them (the depth RMSEs with the
grid they were scored on); the depth-error histogram makes the same comparison
(:func:`nirspi_pipe.mesh.metrics3d.compared_depths`) on the camera grid, and says so.

Layout: matplotlib's constrained layout, saved "tight" at :data:`SUMMARY_DPI` so that nothing
drawn is cut (the image panels keep their aspect, which the layout cannot always fit);
tests/test_figure.py reads the figure back.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from nirspi_pipe.stages import Products

__all__ = ["SUMMARY_DPI", "SUMMARY_PAD_IN", "SUMMARY_NAME", "summary_figure", "write_summary_figure"]

SUMMARY_NAME = "summary.png"
SUMMARY_DPI = 90  # dots per inch of summary.png: ~1100 px wide for the 2D figure
SUMMARY_PAD_IN = 0.1  # inches of margin around the drawn content in summary.png


def _extent_mm(products: Products, n: int) -> tuple[list[float], str]:
    """Image extent on the scene plane (mm) and the axis label; pixels when there is no scene."""
    truth = products.truth
    # a recording's ground truth has no distance (NaN): its plane is unknown, so pixels
    if truth is None or not (math.isfinite(truth.distance_m) and truth.distance_m > 0):
        return [0.0, float(n), float(n), 0.0], "pixel"
    half = truth.distance_m * math.tan(math.radians(truth.camera.fov_deg) / 2) * 1e3
    return [-half, half, -half, half], f"x (mm, on the plane at {truth.distance_m * 1e3:.0f} mm)"


def _show(
    fig: Any,
    ax: Any,
    img: np.ndarray,
    title: str,
    unit: str,
    extent: list[float],
    xlabel: str,
    cmap: str = "gray",
    vmin: float | None = None,
    vmax: float | None = None,
) -> None:
    data = np.ma.masked_invalid(np.asarray(img, dtype=np.float64))
    # images are stored row 0 = top of the view; origin="upper" keeps that on screen
    handle = ax.imshow(data, cmap=cmap, vmin=vmin, vmax=vmax, extent=extent, origin="upper", interpolation="nearest")
    ax.set_title(title, fontsize=9)
    ax.set_xlabel(xlabel, fontsize=8)
    ax.set_ylabel("y (pixel)" if xlabel == "pixel" else "y (mm)", fontsize=8)
    ax.tick_params(labelsize=7)
    bar = fig.colorbar(handle, ax=ax, fraction=0.046, pad=0.04)
    bar.set_label(unit, fontsize=8)
    bar.ax.tick_params(labelsize=7)


def _symmetric(a: np.ndarray) -> float:
    finite = np.abs(a[np.isfinite(a)])
    return float(np.percentile(finite, 99)) if finite.size and np.percentile(finite, 99) > 0 else 1.0


def _title(record: Mapping[str, Any], depth_grid: int | None = None) -> str:
    """The header: the run, its 2D scores, its 3D scores (on ``depth_grid``², the grid the
    record's depth RMSEs were computed on) and the active effects, numbers as in the record."""
    from nirspi_pipe.summary import effects_lines

    ch = record.get("choices", {}) or {}
    res = ((record.get("config", {}) or {}).get("camera") or {}).get("resolution")
    m = {k: float(v) for k, v in (record.get("metrics", {}) or {}).items() if math.isfinite(float(v))}
    head = f"scene={ch.get('scene')}  scan={ch.get('scan')}  solver={ch.get('solver')}  {res}×{res}"
    scores = [fmt.format(m[key]) for key, fmt in (("ssim", "SSIM {:.3f}"), ("psnr", "PSNR {:.2f} dB")) if key in m]
    lines = [head + ("   " + "  ".join(scores) if scores else "")]
    if "depth_rmse_fused_mm" in m:
        grid = f", on the {depth_grid}×{depth_grid} grid" if depth_grid else ""
        depth = f"depth RMSE{grid}: "
        if "depth_rmse_sfs_mm" in m:
            depth += f"SFS {m['depth_rmse_sfs_mm']:.3g} mm (camera geometry only) → "
        depth += f"fused {m['depth_rmse_fused_mm']:.3g} mm"
        if "improvement_pct" in m:
            depth += f" (Eq. 17 improvement {m['improvement_pct']:+.1f} %)"
        if "depth_rmse_sfs_fit_mm" in m:
            depth += f";  SFS with the fusion's global fit {m['depth_rmse_sfs_fit_mm']:.3g} mm"
        lines.append(depth)
    effects = [" ".join(line.split()) for line in effects_lines(record)]
    return "\n".join([*lines, *effects])


def _scored_grid(products: Products) -> int | None:
    """Side of the grid the 3D metrics score depth on: the upscaled SFS grid on an upscaled run
    (:class:`nirspi_pipe.mesh.metrics3d.Metrics3D`), else the camera's."""
    if products.depth is None or products.truth is None:
        return None
    side = int(products.depth.depth_m.shape[0])
    return side if products.upscaled is not None else products.truth.camera.resolution


def _metric_depth(products: Products) -> np.ndarray | None:
    """The SFS depth in metres on its grid: as solved when metric, else scaled by the fusion."""
    depth, cloud = products.depth, products.cloud
    if depth is None:
        return None
    z = np.asarray(depth.depth_m, dtype=np.float64)
    if not depth.metric:
        if cloud is None or "scale" not in cloud.info:
            return None
        z = float(cloud.info["scale"]) * z + float(cloud.info["offset_m"])
    return np.where(np.asarray(depth.mask, dtype=bool) & np.isfinite(z), z, np.nan)


def write_summary_figure(
    folder: Path, products: Products, record: Mapping[str, Any], mesh_png: Path | None = None
) -> Path:
    """Write ``summary.png`` into ``folder`` (see the module docstring); returns its path.

    ``mesh_png``: an already rendered mesh view to place in the 3D row (``mesh.png``)."""
    import matplotlib.pyplot as plt

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    fig = summary_figure(products, record, mesh_png)
    path = folder / SUMMARY_NAME
    try:
        # the panels keep their aspect, so the constrained layout may leave a label past the
        # canvas's edge: save what is drawn, all of it ("tight"), at the fixed DPI
        fig.savefig(path, dpi=SUMMARY_DPI, bbox_inches="tight", pad_inches=SUMMARY_PAD_IN)
    finally:
        plt.close(fig)
    return path


def summary_figure(products: Products, record: Mapping[str, Any], mesh_png: Path | None = None) -> Any:
    """The ``summary.png`` figure (a matplotlib ``Figure``, laid out; the caller closes it)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    recon = np.asarray(products.image.data, dtype=np.float64)
    n = recon.shape[0]
    extent, xlabel = _extent_mm(products, n)
    truth = products.truth
    three_d = products.depth is not None and truth is not None
    mesh_view = three_d and mesh_png is not None and Path(mesh_png).exists()
    title = _title(record, _scored_grid(products))
    title_in = 0.05 + 9 * 1.2 / 72 * (title.count("\n") + 1)  # inches: the header's lines of 9 pt
    ncols = 4 if three_d else 3
    heights = [3.5] * (2 if three_d else 1) + ([4.4] if mesh_view else [])
    # constrained layout packs the header, panels, labels and colour bars (saved "tight", above)
    fig = plt.figure(figsize=(4.2 * ncols, sum(heights) + title_in), dpi=SUMMARY_DPI, layout="constrained")
    grid = fig.add_gridspec(len(heights), ncols, height_ratios=heights)
    r0 = [fig.add_subplot(grid[0, c]) for c in range(ncols)]
    unit = "radiance (white target = 1)"
    if truth is not None:
        _show(fig, r0[0], truth.radiance, "ground truth", unit, extent, xlabel, vmin=0.0, vmax=1.0)
    else:
        r0[0].axis("off")
        r0[0].text(0.5, 0.5, "no ground truth\n(measured data)", ha="center", va="center")
    _show(fig, r0[1], recon, "reconstruction", unit, extent, xlabel, vmin=0.0, vmax=1.0)
    if truth is not None and truth.radiance.shape == recon.shape:
        err = recon - truth.radiance
        lim = _symmetric(err)
        rms = float(np.sqrt(np.mean(err[np.isfinite(err)] ** 2)))
        _show(
            fig,
            r0[2],
            err,
            f"error: reconstruction − truth (RMSE {rms:.3g})",
            "radiance difference",
            extent,
            xlabel,
            cmap="RdBu_r",
            vmin=-lim,
            vmax=lim,
        )
    else:
        r0[2].axis("off")
    if three_d:
        up = products.upscaled
        if up is not None:
            _show(
                fig,
                r0[3],
                up.data,
                f"upscaled {up.data.shape[0]}×{up.data.shape[1]}",
                unit,
                extent,
                xlabel,
                vmin=0.0,
                vmax=1.0,
            )
        else:
            r0[3].axis("off")
            r0[3].text(0.5, 0.5, "no upscaling\n(upscale=null)", ha="center", va="center", fontsize=9)
        _depth_row(fig, [fig.add_subplot(grid[1, c]) for c in range(ncols)], products, extent, xlabel)
        if mesh_view:
            import matplotlib.image as mpimg

            ax = fig.add_subplot(grid[2, :])
            ax.imshow(mpimg.imread(str(mesh_png)))
            ax.axis("off")
            ax.set_title("final mesh (left) and true surface (right), mm, seen from beside the camera", fontsize=9)
    fig.suptitle(title, fontsize=9, x=0.01, ha="left")
    fig.canvas.draw()  # lay out now: the caller may read the artists' extents
    return fig


def _depth_row(fig: Any, row: Any, products: Products, extent: list[float], xlabel: str) -> None:
    from nirspi_pipe.mesh.metrics3d import _interpolate_depth, _to_grid

    truth = products.truth
    assert truth is not None
    zt = np.where(truth.mask, truth.depth_m, np.nan) * 1e3
    finite = zt[np.isfinite(zt)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (None, None)
    _show(fig, row[0], zt, "true depth", "depth (mm)", extent, xlabel, cmap="viridis", vmin=lo, vmax=hi)
    zs = _metric_depth(products)
    if zs is not None:
        _show(
            fig,
            row[1],
            zs * 1e3,
            "SFS depth, fusion's global fit (Alg. A2)",
            "depth (mm)",
            extent,
            xlabel,
            cmap="viridis",
            vmin=lo,
            vmax=hi,
        )
    else:
        row[1].axis("off")
        row[1].text(0.5, 0.5, "SFS depth is relative\n(no fusion to scale it)", ha="center", va="center")
    if products.cloud is not None:
        zf = _interpolate_depth(np.asarray(products.cloud.points_m), truth.camera)
        err = (zf - truth.depth_m) * 1e3
        err = np.where(truth.mask, err, np.nan)
        lim = _symmetric(err)
        _show(
            fig,
            row[2],
            err,
            "fused depth − true depth (Alg. A3)",
            "depth error (mm)",
            extent,
            xlabel,
            cmap="RdBu_r",
            vmin=-lim,
            vmax=lim,
        )
    elif zs is not None:
        err = (_to_grid(zs, truth.camera.resolution) - truth.depth_m) * 1e3
        lim = _symmetric(err)
        _show(
            fig,
            row[2],
            np.where(truth.mask, err, np.nan),
            "SFS depth − true depth",
            "depth error (mm)",
            extent,
            xlabel,
            cmap="RdBu_r",
            vmin=-lim,
            vmax=lim,
        )
    else:
        row[2].axis("off")
    _depth_histogram(row[3], products)


def _depth_histogram(ax: Any, products: Products) -> None:
    """Histogram of the per-pixel depth errors (mm) on the camera grid, object pixels: the same
    comparison as the record's ``depth_rmse_*`` (:func:`nirspi_pipe.mesh.metrics3d.compared_depths`),
    which on an upscaled run is made on the upscaled grid instead (the title says which)."""
    from nirspi_pipe.mesh.metrics3d import compared_depths

    truth = products.truth
    assert truth is not None
    compared = compared_depths(truth, products.depth, products.cloud)
    if compared is None or not compared[0].any():
        ax.axis("off")
        ax.text(0.5, 0.5, "no depth error to show\n(needs SFS and a fused cloud)", ha="center", va="center", fontsize=9)
        return
    both, z_geom, z_fit, z_fused = compared
    geom, fit, fused = ((z[both] - truth.depth_m[both]) * 1e3 for z in (z_geom, z_fit, z_fused))
    n = truth.camera.resolution
    lim = max(float(np.percentile(np.abs(e), 99)) for e in (fit, fused)) or 1.0
    for label, e in (("SFS, global fit", fit), ("fused (Alg. A3)", fused)):
        ax.hist(
            np.clip(e, -lim, lim),
            bins=40,
            range=(-lim, lim),
            histtype="step",
            linewidth=1.5,
            label=f"{label}: {_rmse(e):.3g} mm",
        )
    if not np.array_equal(z_geom, z_fit, equal_nan=True):
        ax.plot([], [], " ", label=f"SFS, geometry only: {_rmse(geom):.3g} mm (not drawn)")
    ax.set_title(f"depth error, object pixels, {n}×{n} grid", fontsize=9)
    ax.set_xlabel("depth − true depth (mm)", fontsize=8)
    ax.set_ylabel("pixels", fontsize=8)
    ax.tick_params(labelsize=7)
    ax.legend(fontsize=7, title="RMSE", title_fontsize=7)


def _rmse(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(e))))
