"""The oracle depth source ``sfs=truth`` (issue 44, item 1): the renderer's depth in the SFS
stages' contract, so a 3D error splits into SFS / anchoring / surface."""

from __future__ import annotations

import numpy as np
import pytest

import nirspi_pipe
from nirspi_pipe.errors import ConfigError, NirspiError
from nirspi_pipe.pipeline import _solve_from_scene
from nirspi_pipe.scene.objects import Sphere
from nirspi_pipe.sfs.oracle import TruthDepth
from nirspi_pipe.types import Camera, Image2D


@pytest.mark.parametrize("n", [16, 64])
def test_relative_truth_maps_back_to_the_rendered_depth(n):
    cam = Camera(n)
    scene = Sphere().render(cam)
    d = TruthDepth().solve(Image2D(scene.radiance), cam, scene)
    assert not d.metric and d.info["model"] == "truth"
    m = d.mask
    assert m.any() and np.array_equal(m, scene.mask & np.isfinite(scene.depth_m))
    z_ref = d.info["z_ref_m"]
    assert d.depth_m[m].min() == 0.0 and np.all(d.depth_m[~m] == 0.0)
    # the SFS stages' contract: z = z_ref + d * z_ref / focal_px
    np.testing.assert_allclose(z_ref + d.depth_m[m] * z_ref / cam.focal_px, scene.depth_m[m], rtol=1e-12)
    dm = TruthDepth(metric=True).solve(Image2D(scene.radiance), cam, scene)
    assert dm.metric and np.array_equal(dm.depth_m[m], scene.depth_m[m])


def test_without_a_scene_it_refuses_in_one_line():
    cam = Camera(8)
    with pytest.raises(NirspiError, match="needs the simulated scene"):
        TruthDepth().solve(Image2D(np.zeros((8, 8))), cam, None)
    with pytest.raises(ConfigError) as err:
        _solve_from_scene(TruthDepth(), None, None, Image2D(np.zeros((8, 8))), cam)
    assert "\n" not in str(err.value) and str(err.value).startswith("sfs")


def test_an_empty_scene_is_one_line():
    cam = Camera(8)
    scene = Sphere().render(cam)
    empty = type(scene)(**{**scene.__dict__, "mask": np.zeros_like(scene.mask)})
    with pytest.raises(NirspiError, match="empty mask"):
        TruthDepth().solve(Image2D(scene.radiance), cam, empty)


def test_the_oracle_splits_the_3d_error_sfs_from_anchoring():
    """With the true depth the only depth error left is the anchoring's: far below what SFS
    leaves on the same run (the split the 3D benchmarks report)."""
    base = ["preset=null", "camera.resolution=32", "itof=cw4", "fusion=itof", "metrics=full", "seed=0"]
    sfs = nirspi_pipe.run([*base, "sfs=second_order"])
    oracle = nirspi_pipe.run([*base, "sfs=truth"])
    assert oracle.info["sfs"]["model"] == "truth"
    assert np.isfinite(oracle.metrics["depth_rmse_fused_mm"])
    assert oracle.metrics["depth_rmse_fused_mm"] < sfs.metrics["depth_rmse_fused_mm"]
