"""``summary.png``: one labelled picture per run.

Top row: the true radiance, the reconstruction and their difference (reconstruction − truth),
on the scene plane in millimetres, with colour bars in units of a white target's radiance, and
the upscaled image when the run has one (the device preset's 32² product). For 3D runs a second
row shows, on the grid the record scores depth on (:func:`nirspi_pipe.mesh.metrics3d.depth_truth`:
the upscaled grid on the device preset, else the camera's) and on the pixels it compares
(:func:`nirspi_pipe.mesh.metrics3d.compared_depths`): the true depth, the depth error of shape
from shading alone (Alg. A2) and of the fused depth (Alg. A3) on one colour scale, and their
histogram; a third row the mesh render (``mesh.png``, pyvista off screen, with a ruler) when
there is one. The SFS error is the headline's: the geometric baseline with its best constant
offset (``depth_rmse_sfs_offsetfree_mm``, Table 3's primary baseline; the module docstring of
:mod:`nirspi_pipe.mesh.metrics3d`); the header names the record's two other baselines as text.

:func:`draw_summary` returns the figure and the numbers it drew, each computed from the arrays
drawn (``tests/test_figure.py`` compares them with ``record.json``).

Layout: matplotlib's constrained layout, saved "tight" at :data:`SUMMARY_DPI` so that nothing
drawn is cut (the image panels keep their aspect, which the layout cannot always fit); legends
sit outside the data (below their axes).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from nirspi_pipe.stages import Products
from nirspi_pipe.summary import effects_lines

__all__ = ["SUMMARY_DPI", "SUMMARY_PAD_IN", "SUMMARY_NAME", "draw_summary", "summary_figure", "write_summary_figure"]

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
    """One image panel with its colour bar; the bar's ends are arrows where values lie beyond
    ``vmin``/``vmax`` (drawn in the end colours), so a clipped panel says so."""
    data = np.ma.masked_invalid(np.asarray(img, dtype=np.float64))
    # images are stored row 0 = top of the view; origin="upper" keeps that on screen
    handle = ax.imshow(data, cmap=cmap, vmin=vmin, vmax=vmax, extent=extent, origin="upper", interpolation="nearest")
    ax.set_title(title, fontsize=9)
    ax.set_xlabel(xlabel, fontsize=8)
    ax.set_ylabel("y (pixel)" if xlabel == "pixel" else "y (mm)", fontsize=8)
    ax.tick_params(labelsize=7)
    finite = data.compressed()
    low = vmin is not None and finite.size > 0 and float(finite.min()) < vmin
    high = vmax is not None and finite.size > 0 and float(finite.max()) > vmax
    extend = {(True, True): "both", (True, False): "min", (False, True): "max"}.get((low, high), "neither")
    bar = fig.colorbar(handle, ax=ax, fraction=0.046, pad=0.04, extend=extend)
    bar.set_label(unit, fontsize=8)
    bar.ax.tick_params(labelsize=7)


def _symmetric(a: np.ndarray) -> float:
    finite = np.abs(a[np.isfinite(a)])
    return float(np.percentile(finite, 99)) if finite.size and np.percentile(finite, 99) > 0 else 1.0


def _metrics(record: Mapping[str, Any]) -> dict[str, float]:
    out = {}
    for k, v in (record.get("metrics", {}) or {}).items():
        try:
            f = float(v)
        except (TypeError, ValueError):
            continue
        if math.isfinite(f):
            out[k] = f
    return out


def _other_baselines(record: Mapping[str, Any], m: Mapping[str, float], free: bool) -> str | None:
    """The header's line of the SFS baselines not drawn (median placed, the fusion's global fit)."""
    others = []
    if free and "depth_rmse_sfs_mm" in m:
        dist = ((record.get("config", {}) or {}).get("scene") or {}).get("distance_mm")
        at = f" at {float(dist):g} mm" if isinstance(dist, (int, float)) else " at the working distance"
        pct = f" ({m['improvement_pct']:+.1f} %)" if "improvement_pct" in m else ""
        others.append(f"median placed{at} {m['depth_rmse_sfs_mm']:.3g} mm{pct}")
    if "depth_rmse_sfs_fit_mm" in m:
        pct = f" ({m['improvement_fit_pct']:+.1f} %)" if "improvement_fit_pct" in m else ""
        others.append(f"the fusion's iToF global fit {m['depth_rmse_sfs_fit_mm']:.3g} mm{pct}")
    return "other SFS baselines (record.json, not drawn): " + "; ".join(others) if others else None


def _depth_lines(record: Mapping[str, Any], m: Mapping[str, float], depth_grid: int | None) -> list[str]:
    """The header's 3D lines: SFS and fused depth RMSE with Eq. 17's improvement, and the
    other baselines; none without a fused depth."""
    if "depth_rmse_fused_mm" not in m:
        return []
    free = "depth_rmse_sfs_offsetfree_mm" in m
    base, imp = (
        ("depth_rmse_sfs_offsetfree_mm", "improvement_offsetfree_pct")
        if free
        else ("depth_rmse_sfs_mm", "improvement_pct")
    )
    grid = f" on the {depth_grid}×{depth_grid} grid" if depth_grid else ""
    pixels = f" ({m['depth_pixels']:.0f} object pixels)" if "depth_pixels" in m else ""
    depth = f"depth RMSE{grid}{pixels}: "
    if base in m:
        what = "best constant offset" if free else "camera geometry only"
        depth += f"SFS {m[base]:.3g} mm (Alg. A2, {what}) → "
    depth += f"fused {m['depth_rmse_fused_mm']:.3g} mm (Alg. A3)"
    if imp in m:
        depth += f": Eq. 17 improvement {m[imp]:+.1f} %"
    others = _other_baselines(record, m, free)
    return [depth] if others is None else [depth, others]


def _title(record: Mapping[str, Any], depth_grid: int | None = None) -> str:
    """The header: the run, its 2D scores, its 3D scores (on ``depth_grid``², the grid the
    record's depth RMSEs were computed on) and the active effects, numbers as in the record."""
    ch = record.get("choices", {}) or {}
    res = ((record.get("config", {}) or {}).get("camera") or {}).get("resolution")
    m = _metrics(record)
    head = f"scene={ch.get('scene')}  scan={ch.get('scan')}  solver={ch.get('solver')}  {res}×{res}"
    scores = [fmt.format(m[key]) for key, fmt in (("ssim", "SSIM {:.3f}"), ("psnr", "PSNR {:.2f} dB")) if key in m]
    if scores and "psnr_raw" in m:
        raw = f"raw PSNR {m['psnr_raw']:.2f} dB" + (f", RMSE {m['rmse']:.3g}" if "rmse" in m else "")
        scores.append(f"(after a least-squares gain and offset; {raw})")
    lines = [head + ("   " + "  ".join(scores) if scores else ""), *_depth_lines(record, m, depth_grid)]
    effects = [" ".join(line.split()) for line in effects_lines(record)]
    return "\n".join([*lines, *effects])


def write_summary_figure(
    folder: Path, products: Products, record: Mapping[str, Any], mesh_png: Path | None = None
) -> Path:
    """Write ``summary.png`` into ``folder`` (see the module docstring); returns its path.

    ``mesh_png``: an already rendered mesh view to place in the 3D row (``mesh.png``)."""
    import matplotlib.pyplot as plt  # start-up: loads matplotlib, PIL, cycler (376 ms here)

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
    return draw_summary(products, record, mesh_png)[0]


def draw_summary(
    products: Products, record: Mapping[str, Any], mesh_png: Path | None = None
) -> tuple[Any, dict[str, float]]:
    """The ``summary.png`` figure and the numbers it draws, keyed as in the record's metrics and
    each computed from the very arrays drawn: ``rmse`` (the radiance error panel),
    ``depth_rmse_sfs_offsetfree_mm``, ``depth_rmse_fused_mm``, ``improvement_offsetfree_pct`` and
    ``depth_pixels`` (the depth-error panels and histogram), and ``depth_grid`` (their side)."""
    import matplotlib  # start-up: loads matplotlib, PIL, cycler (96 ms here)

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt  # start-up: loads matplotlib, PIL, cycler (376 ms here)

    # start-up: loads PIL, charset_normalizer, cycler (463 ms here)
    from nirspi_pipe.mesh.metrics3d import (
        compared_depths,
        run_depth_truth,
    )

    n = np.asarray(products.image.data).shape[0]
    extent, xlabel = _extent_mm(products, n)
    truth = products.truth
    m = _metrics(record)
    three_d = products.depth is not None and truth is not None
    up = products.upscaled
    dtruth = run_depth_truth(products, record.get("config")) if three_d else None
    compared = compared_depths(dtruth, products.depth, products.cloud) if dtruth is not None else None
    grid_side = dtruth.camera.resolution if dtruth is not None else None
    mesh_view = three_d and mesh_png is not None and Path(mesh_png).exists()
    title = _title(record, grid_side if compared is not None else None)
    title_in = 0.05 + 9 * 1.2 / 72 * (title.count("\n") + 1)  # inches: the header's lines of 9 pt
    ncols = 4 if (three_d or up is not None) else 3
    heights = [3.5] * (2 if three_d else 1) + ([4.4] if mesh_view else [])
    # constrained layout packs the header, panels, labels and colour bars (saved "tight", above)
    fig = plt.figure(figsize=(4.2 * ncols, sum(heights) + title_in), dpi=SUMMARY_DPI, layout="constrained")
    grid = fig.add_gridspec(len(heights), ncols, height_ratios=heights)
    r0 = [fig.add_subplot(grid[0, c]) for c in range(ncols)]
    drawn = _radiance_row(fig, r0, products, m, (extent, xlabel))
    if three_d:
        assert dtruth is not None
        row = [fig.add_subplot(grid[1, c]) for c in range(ncols)]
        drawn.update(_depth_row(fig, row, dtruth, compared, extent, xlabel))
        if mesh_view:
            _mesh_panel(fig, grid[2, :], mesh_png, dtruth.camera.resolution)
    fig.suptitle(title, fontsize=9, x=0.01, ha="left")
    fig.canvas.draw()  # lay out now: the caller may read the artists' extents
    return fig, drawn


def _radiance_row(
    fig: Any, r0: list[Any], products: Products, m: Mapping[str, float], axes: tuple[list[float], str]
) -> dict[str, float]:
    """The first row: ground truth, reconstruction, their error and (with four columns) the
    upscaled image; returns the numbers drawn (the raw ``rmse``, :func:`draw_summary`)."""
    extent, xlabel = axes
    drawn: dict[str, float] = {}
    recon = np.asarray(products.image.data, dtype=np.float64)
    n = recon.shape[0]
    truth = products.truth
    up = products.upscaled
    unit = "radiance (white target = 1)"
    if truth is not None:
        _show(fig, r0[0], truth.radiance, f"ground truth, {n}×{n}", unit, extent, xlabel, vmin=0.0, vmax=1.0)
    else:
        r0[0].axis("off")
        r0[0].text(0.5, 0.5, "no ground truth\n(measured data)", ha="center", va="center")
    _show(fig, r0[1], recon, f"reconstruction, {n}×{n}", unit, extent, xlabel, vmin=0.0, vmax=1.0)
    if truth is not None and truth.radiance.shape == recon.shape:
        err = recon - truth.radiance
        lim = _symmetric(err)
        drawn["rmse"] = float(np.sqrt(np.mean(err[np.isfinite(err)] ** 2)))
        _show(
            fig,
            r0[2],
            err,
            f"error: reconstruction − truth (raw RMSE {drawn['rmse']:.3g})",
            "radiance difference",
            extent,
            xlabel,
            cmap="RdBu_r",
            vmin=-lim,
            vmax=lim,
        )
    else:
        r0[2].axis("off")
    if len(r0) == 4:
        if up is not None:
            k = up.data.shape[0]
            score = f", PSNR {m['upscale_psnr']:.2f} dB" if "upscale_psnr" in m else ""
            _show(
                fig, r0[3], up.data, f"upscaled ×{k // n} to {k}×{k}{score}", unit, extent, xlabel, vmin=0.0, vmax=1.0
            )
        else:
            r0[3].axis("off")
            r0[3].text(0.5, 0.5, "no upscaling\n(upscale=null)", ha="center", va="center", fontsize=9)
    return drawn


def _mesh_panel(fig: Any, cell: Any, mesh_png: Any, g: int) -> None:
    """The third row: the rendered mesh view (``mesh.png``) across the figure's width."""
    import matplotlib.image as mpimg  # start-up: loads matplotlib, PIL, cycler (215 ms here)

    ax = fig.add_subplot(cell)
    ax.imshow(mpimg.imread(str(mesh_png)))
    ax.axis("off")
    ax.set_title(
        f"final mesh (left) and true surface on the {g}×{g} grid (right), seen from beside the camera; "
        "ruler in mm at the object",
        fontsize=9,
    )


def _depth_row(fig: Any, row: Any, truth: Any, compared: Any, extent: list[float], xlabel: str) -> dict[str, float]:
    """True depth, SFS and fused depth errors (one colour scale) and their histogram, on
    ``truth``'s grid and the compared pixels; returns the numbers drawn (:func:`draw_summary`)."""
    # start-up: loads PIL, charset_normalizer, cycler (463 ms here)
    from nirspi_pipe.mesh.metrics3d import (
        improvement_rate,
    )

    g = truth.camera.resolution
    zt = np.where(truth.mask, truth.depth_m, np.nan) * 1e3
    finite = zt[np.isfinite(zt)]
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (None, None)
    _show(fig, row[0], zt, f"true depth, {g}×{g}", "depth (mm)", extent, xlabel, cmap="viridis", vmin=lo, vmax=hi)
    if compared is None or not compared[0].any():
        for ax in row[1:]:
            ax.axis("off")
        row[1].text(
            0.5, 0.5, "no depth error to show\n(needs SFS and a fused cloud)", ha="center", va="center", fontsize=9
        )
        return {}
    both, z_base, _, z_fused = compared
    t = truth.depth_m
    offset = float(np.mean(t[both] - z_base[both]))  # the offset-free baseline's constant (metrics3d)
    maps = {
        "sfs": np.where(both, z_base + offset - t, np.nan) * 1e3,
        "fused": np.where(both, z_fused - t, np.nan) * 1e3,
    }
    sfs, fused = maps["sfs"][both], maps["fused"][both]
    drawn = {
        "depth_grid": float(g),
        "depth_pixels": float(both.sum()),
        "depth_rmse_sfs_offsetfree_mm": _rmse(sfs),
        "depth_rmse_fused_mm": _rmse(fused),
    }
    if drawn["depth_rmse_sfs_offsetfree_mm"] > 0:
        drawn["improvement_offsetfree_pct"] = improvement_rate(
            drawn["depth_rmse_sfs_offsetfree_mm"], drawn["depth_rmse_fused_mm"]
        )
    lim = max(_symmetric(maps["sfs"]), _symmetric(maps["fused"]))
    titles = {
        "sfs": f"SFS − truth (Alg. A2, best offset): RMSE {drawn['depth_rmse_sfs_offsetfree_mm']:.3g} mm",
        "fused": f"fused − truth (Alg. A3): RMSE {drawn['depth_rmse_fused_mm']:.3g} mm",
    }
    for ax, key in zip(row[1:3], ("sfs", "fused"), strict=True):
        _show(fig, ax, maps[key], titles[key], "depth error (mm)", extent, xlabel, cmap="RdBu_r", vmin=-lim, vmax=lim)
    ax = row[3]
    top = max(float(np.max(np.abs(sfs))), float(np.max(np.abs(fused)))) or 1.0  # every pixel inside the bins
    for label, e in (("SFS, best offset (Alg. A2)", sfs), ("fused (Alg. A3)", fused)):
        ax.hist(e, bins=40, range=(-top, top), histtype="step", linewidth=1.5, label=f"{label}: RMSE {_rmse(e):.3g} mm")
    ax.set_title(f"depth error, {both.sum()} compared pixels, {g}×{g} grid", fontsize=9)
    ax.set_xlabel("depth − true depth (mm)", fontsize=8)
    ax.set_ylabel("pixels", fontsize=8)
    ax.tick_params(labelsize=7)
    # below the axes, outside the data: a legend inside hid the bars (issue 34)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.2), frameon=False)
    return drawn


def _rmse(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(e))))
