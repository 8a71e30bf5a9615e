"""The generated shape set (issue 14) through the whole 3D path: a Markdown table for docs/mesh.md.

    python experiments/shapes/shape_table.py [--resolution 64] [--sfs second_order] [hydra overrides…]

For each shape (conf/scene/{plate_edge,ring,bowl,multi,partial,off_centre,vase}.yaml, plus the
paper's sphere) runs ``sfs=<sfs> itof=cw4 fusion=itof surface=power_crust metrics=full``,
noise-free by default (ideal detector, no fog), and prints depth RMSE before (SFS made metric)
and after fusion, Eq. (17), chamfer, Hausdorff and the mean equiangle skewness of the final mesh.
Extra arguments are Hydra overrides applied to every run (e.g. ``fog=chamber`` for noise).
"""

from __future__ import annotations

import argparse
import time
import warnings

SHAPES = ("sphere", "plate_edge", "ring", "bowl", "multi", "partial", "off_centre", "vase")
COLUMNS = (
    # the SFS depth made metric with the fusion's global scale and offset, and Eq. 17 against it
    # (docs/mesh.md's table; the no-iToF baseline of Table 3 is depth_rmse_sfs_mm/improvement_pct)
    ("depth_rmse_sfs_fit_mm", "RMSE SFS (mm)", "{:.2f}"),
    ("depth_rmse_fused_mm", "RMSE fused (mm)", "{:.2f}"),
    ("improvement_fit_pct", "Eq. 17 (%)", "{:+.1f}"),
    ("chamfer_mm", "chamfer (mm)", "{:.2f}"),
    ("hausdorff_mm", "Hausdorff (mm)", "{:.1f}"),
    ("skewness_mean", "skewness", "{:.2f}"),
)


def run_shape(shape: str, resolution: int, sfs: str, extra: list[str]) -> tuple[dict, list[str], dict]:
    """Metrics, warnings and fusion info of one shape (an error becomes ``{"error": …}``)."""
    from hydra import compose, initialize_config_module

    from nirspi_pipe.pipeline import run_pipeline

    # noise-free 64² by default, as documented (the default run became the noisy device model in
    # issue 11; these keep the table's setting); ``extra`` may override any of them
    noise_free = ["preset=off", "fog=none", "illumination=none", "detector=ideal"]
    overrides = [
        *noise_free,
        f"scene={shape}",
        f"sfs={sfs}",
        "itof=cw4",
        "fusion=itof",
        "surface=power_crust",
        "metrics=full",
        f"camera.resolution={resolution}",
        *extra,
    ]
    with initialize_config_module("nirspi_pipe.conf", version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            out = run_pipeline(cfg)
    except Exception as exc:  # noqa: BLE001 - a failing shape is a table row
        return {"error": f"{type(exc).__name__}: {exc}"}, list(getattr(exc, "nirspi_warnings", [])), {}
    return out.metrics, out.warnings, {**out.info.get("fusion", {}), "total_ms": out.timings_ms.get("total")}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--resolution", type=int, default=64)
    p.add_argument("--sfs", default="second_order")
    p.add_argument("--shapes", default=",".join(SHAPES))
    ns, extra = p.parse_known_args(argv)
    head = "| shape | " + " | ".join(c[1] for c in COLUMNS) + " | anchors |"
    print(head)
    print("|" + "---|" * (len(COLUMNS) + 2))
    for shape in ns.shapes.split(","):
        t0 = time.perf_counter()
        m, _warns, fus = run_shape(shape, ns.resolution, ns.sfs, extra)
        if "error" in m:
            print(f"| {shape} | failed: {m['error']} |")
            continue
        cells = [fmt.format(m[k]) if k in m else "—" for k, _, fmt in COLUMNS]
        print(f"| {shape} | " + " | ".join(cells) + f" | {fus.get('anchors_used', '—')} |", flush=True)
        _ = t0
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
