"""experiments/shapes/front.py (issue 44, item 5): the Pareto front of the 3D accuracy–time
sweep, its grid, and its table from a small hand-made results frame (no sweep runs here)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from conftest import load_script

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def front():
    yield from load_script(ROOT / "experiments" / "shapes" / "front.py", "front_3d")


def _dominates(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(np.all(a <= b) and np.any(a < b))


# few distinct values, so that ties and duplicates are common
values = st.sampled_from([0.0, 1.0, 2.0, 2.5, 7.0, math.inf, math.nan])


@settings(max_examples=150, deadline=None)
@given(arrays(np.float64, st.tuples(st.integers(0, 12), st.integers(1, 3)), elements=values))
def test_front_members_are_not_dominated_and_every_other_row_is(front, v):
    mask = front.front_mask(v)
    assert mask.shape == (len(v),)
    finite = np.isfinite(v).all(axis=1)
    assert not mask[~finite].any(), "a row with a non-finite value is on the front"
    members = v[mask]
    for i in np.flatnonzero(mask):
        assert not any(_dominates(w, v[i]) for w in v[finite]), f"front row {i} is dominated"
    for i in np.flatnonzero(finite & ~mask):
        assert any(_dominates(w, v[i]) for w in members), f"row {i} off the front, dominated by no member"
    if finite.any():
        assert mask.any(), "finite rows but an empty front"


def test_front_of_a_known_set(front):
    # (error, time): the slow accurate and the fast coarse are both on the front, the slow coarse not
    v = np.array([[1.0, 100.0], [3.0, 10.0], [3.0, 200.0], [2.0, 50.0]])
    assert front.front_mask(v).tolist() == [True, True, False, True]


def test_grid_builder(front):
    g = front.DEFAULT
    assert "truth" in g.sfs and g.resolution == (32, 64, 128)
    points = front.grid_points(g)
    assert len(points) == g.jobs() == len({tuple(sorted(p.items())) for p in points})
    assert {p["condition"] for p in points} == set(front.CONDITIONS)
    ov = front.sweep_overrides(g, "chamber")
    assert "fog=chamber" in ov and "preset=null" in ov and "detector=ingaas" in ov
    assert "camera.resolution=32,64,128" in ov and "sfs=second_order,perspective,truth" in ov
    # the view triangulation beside the power crust; screened Poisson (seconds a job) in --full only
    assert "surface=power_crust,view" in ov and "poisson" not in g.surface
    assert {"power_crust", "view", "poisson"} <= set(front.FULL.surface)
    assert front.sweep_overrides(g, "noise_free")[:4] == list(front.FIXED)
    # the job count of one condition's sweep is the product of its comma lists
    n = 1
    for o in ov:
        if "," in o:
            n *= len(o.split("=", 1)[1].split(","))
    assert n * len(g.conditions) == g.jobs()
    with pytest.raises(ValueError, match="sfs=truth"):
        front.Grid((64,), ("second_order",), (0.5,), ("power_crust",), ("vase",), (0,))
    with pytest.raises(ValueError, match="conditions"):
        front.Grid((64,), ("truth",), (0.5,), ("power_crust",), ("vase",), (0,), conditions=("fogg",))
    with pytest.raises(ValueError, match="allowed"):
        front.sweep_overrides(g, "fogg")
    assert front.FULL.jobs() > g.jobs()


def _frame() -> pd.DataFrame:
    """A results frame as load_results gives it, two shapes × three seeds per configuration."""
    rows = []
    for sfs, chamfer, depth, t in (("second_order", 3.0, 4.0, 200.0), ("truth", 1.0, 2.5, 150.0)):
        for shape, bump in (("vase", 0.0), ("bowl", 10.0)):
            for seed in (0, 1, 5):
                rows.append(
                    {
                        "condition": "noise_free",
                        "camera.resolution": 64,
                        "sfs": sfs,
                        "itof.averaging_s": 0.5,
                        "surface": "power_crust",
                        "scene": shape,
                        "seed": seed,
                        "status": "ok",
                        "metrics.chamfer_mm": chamfer + bump + seed,
                        "metrics.depth_rmse_fused_mm": depth + bump + seed,
                        "timings_ms.total": t + seed + 30.0,
                        "timings_ms.scene": 10.0,
                        "timings_ms.metrics": 20.0,
                    }
                )
    return pd.DataFrame(rows)


def test_summary_medians_split_and_front(front):
    table = front.summarise(_frame())
    so = table[table["sfs"] == "second_order"].iloc[0]
    tr = table[table["sfs"] == "truth"].iloc[0]
    # the mean of the shapes' medians over the seeds (vase 4, bowl 14), not the median of all six jobs (8.5)
    assert so["chamfer_mm"] == 9.0 and so["chamfer_mm_min"] == 3.0 and so["chamfer_mm_max"] == 18.0
    assert so["chamfer_mm_by_shape"] == "bowl 14.00, vase 4.00"
    # time: timings_ms.total less the scene's rendering and the metrics (no camera runs them)
    assert so["time_ms"] == 201.0 and so["total_ms"] == 231.0 and so["ok"] == so["jobs"] == 6
    assert so["sfs_share_chamfer_mm"] == pytest.approx(2.0) and so["sfs_share_depth_mm"] == pytest.approx(1.5)
    assert tr["anchoring_mm"] == 8.5 and tr["surface_mm"] == pytest.approx(7.0 - 8.5)
    # the oracle is faster and better, but a reference: never on a front; second_order alone is
    assert not tr["front_chamfer"] and not tr["front_depth"]
    assert bool(so["front_chamfer"]) and bool(so["front_depth"])
    md = front.markdown(table)
    assert "| 64 | truth |" in md and "C/D" in md and "| 64 | second_order |" in md


def test_the_front_of_real_configurations(front):
    f = _frame()
    slow = f[f["sfs"] == "second_order"].assign(sfs="perspective")
    slow["timings_ms.total"] += 1000.0  # slower, same error: dominated by second_order
    table = front.summarise(pd.concat([f, slow], ignore_index=True))
    flags = table.set_index("sfs")[["front_chamfer", "front_depth"]]
    assert flags.loc["second_order"].all() and not flags.loc["perspective"].any()
    assert flags.loc["perspective"].tolist() == [False, False]
    members = front.markdown(table, front_only=True).split("|---|")[-1]
    assert "second_order" in members and "truth" in members and "perspective" not in members


def test_a_failed_job_keeps_its_configuration_off_the_front(front):
    f = _frame()
    f.loc[(f["sfs"] == "second_order") & (f["seed"] == 1) & (f["scene"] == "vase"), "status"] = "failed"
    table = front.summarise(f)
    so = table[table["sfs"] == "second_order"].iloc[0]
    assert so["ok"] == 5 and so["jobs"] == 6
    assert math.isnan(so["chamfer_mm"]) and math.isnan(so["sfs_share_chamfer_mm"]) and not so["front_chamfer"]
    assert not table["front_chamfer"].any()


def test_bad_arguments_get_one_line_and_run_nothing(front, tmp_path, capsys):
    assert front.main(["--out", str(tmp_path / "o"), "--conditions", "fogg"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "grid.conditions" in err and "noise_free" in err
    assert not (tmp_path / "o").exists()
    with pytest.raises(SystemExit, match="no sweep folder"):
        front.main(["--out", str(tmp_path / "empty"), "--tables-only"])


def test_the_figure_draws_every_surface_and_variant(front, tmp_path):
    # two surfaces and the oracle: each (sfs, surface, averaging) group gets a marker and a colour
    f = _frame()
    view = f.assign(surface="view")
    view["timings_ms.total"] -= 50.0
    slow = f.assign(**{"itof.averaging_s": 8.0})
    table = front.summarise(pd.concat([f, view, slow], ignore_index=True))
    assert set(table["surface"]) == {"power_crust", "view"}
    front.figure(table, tmp_path / "front.png")
    assert (tmp_path / "front.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
