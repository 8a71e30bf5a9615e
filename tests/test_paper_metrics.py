"""The two record metrics that issue 25 added, on single in-process jobs of the paper's grids:
the offset-free Eq. 17 baseline (metrics3d) and Figure 9's noise-only score (upscale metrics)."""

from __future__ import annotations

import numpy as np
import pytest

from nirspi_pipe.app.api import run


@pytest.mark.filterwarnings("ignore")
def test_offset_free_baseline_decomposes_the_centre_placed_one():
    """Least-squares offset: RMSE_centre² = offset² + RMSE_offsetfree², so the offset-free baseline
    is never worse and the improvement with it never larger."""
    m = run(["+experiment=table3", "scan=basic", "scene=sphere", "illumination.klux=5", "seed=0"]).metrics
    centre, free, off = m["depth_rmse_sfs_mm"], m["depth_rmse_sfs_offsetfree_mm"], m["sfs_offset_mm"]
    assert centre**2 == pytest.approx(off**2 + free**2, rel=1e-9)
    assert free <= centre and m["improvement_offsetfree_pct"] <= m["improvement_pct"]
    after = m["depth_rmse_fused_mm"]
    assert m["improvement_offsetfree_pct"] == pytest.approx((free - after) / free * 100)


@pytest.mark.filterwarnings("ignore")
def test_noise_only_score_is_exact_without_noise_and_finite_with_it():
    base = ["+experiment=figure9", "scan=spiral", "scene=sphere", "illumination.klux=50", "seed=0"]
    clean = run([*base, "detector=ideal", "fog.fluctuation_rel=0", "illumination.wander_rel=0"]).metrics
    assert clean["noise_psnr"] == 200.0  # the upscaled image is the upscaler's image of the clean one
    assert clean["upscale_psnr"] < 35.0  # while the score against the fine scene stays resolution-limited
    noisy = run(base).metrics
    assert np.isfinite(noisy["noise_psnr"]) and noisy["noise_psnr"] < 60.0
    # with the noise-only scores switched off, none
    none = run([*base, "metrics.noise_scores=false"]).metrics
    assert "noise_psnr" not in none and "upscale_psnr" in none
