"""No NaN or Inf in a record with status ok (docs/hostile.md): the guard, and the runs the issue
found (``camera.resolution=2``)."""

from __future__ import annotations

import copy
import json
import math
from pathlib import Path

from hydra import compose, initialize_config_module
from hypothesis import given, settings
from hypothesis import strategies as st

from nirspi_pipe.app.jobs import execute_job
from nirspi_pipe.finite import drop_nonfinite, is_finite_tree

leaf = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(),
    st.text(max_size=5),
    st.booleans(),
    st.none(),
    st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=3),
)
tree = st.recursive(
    leaf, lambda inner: st.dictionaries(st.text(min_size=1, max_size=6), inner, max_size=4), max_leaves=8
)


def count_bad(node: object) -> int:
    if isinstance(node, dict):
        return sum(count_bad(v) for v in node.values())
    return 0 if is_finite_tree(node) else 1


@settings(max_examples=40, deadline=None)
@given(
    sections=st.fixed_dictionaries(
        {
            k: st.dictionaries(st.text(min_size=1, max_size=6), tree, max_size=3)
            for k in ("metrics", "derived", "info", "timings_ms")
        }
    )
)
def test_guard_leaves_only_finite_values_and_says_what_it_removed(sections: dict) -> None:
    record = {"config": {"x": float("nan")}, **copy.deepcopy(sections)}
    expected = sum(count_bad(v) for v in sections.values())
    warnings = drop_nonfinite(record)
    assert len(warnings) == expected
    assert all(is_finite_tree(record[k]) for k in sections)
    assert math.isnan(record["config"]["x"])  # the user's input is not a result: untouched
    json.dumps({k: record[k] for k in sections}, allow_nan=False)  # strict JSON now
    for w in warnings:
        assert "left out of the record" in w and "\n" not in w


def test_resolution_2_records_no_nan_and_says_why(tmp_path: Path) -> None:
    with initialize_config_module("nirspi_pipe.conf", version_base="1.3"):
        cfg = compose("config", overrides=["camera.resolution=2"])
    rec = execute_job(cfg, tmp_path, {}, [])
    assert rec["meta"]["status"] == "ok"
    # 2x2 pixels of the centred sphere see the same radiance: a degenerate (uniform) reference, so
    # the normalised scores are left out too (issue 32), and the raw SSIM is undefined below 3x3
    assert "ssim" not in rec["metrics"] and "ssim_raw" not in rec["metrics"] and math.isfinite(rec["metrics"]["rmse"])
    assert rec["metrics"]["degenerate_reference"] == 1.0
    assert any(
        "metrics.ssim_raw=nan" in w and "SSIM is undefined for images smaller than 3x3" in w
        for w in rec["meta"]["warnings"]
    )
    stored = json.loads((tmp_path / "record.json").read_text())
    assert all(is_finite_tree(stored[k]) for k in ("metrics", "derived", "info", "timings_ms"))
