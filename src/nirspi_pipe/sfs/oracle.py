"""The oracle depth source ``sfs=truth``: the renderer's own depth on the camera's pixels, in
place of shape from shading (issue 44, item 1).

It is a benchmark instrument, not a reconstruction: with it, a 3D error splits into what SFS
loses (``sfs=<model>`` against ``sfs=truth``), what anchoring and fusion lose (``sfs=truth``'s
fused cloud against the truth) and what the surface loses (its mesh against its cloud). It needs
a simulated scene (the renderer's depth): a recorded or streamed source has none, and the runner
refuses the pair in one line.

The output has the SFS stages' contract (:mod:`nirspi_pipe.sfs.models`): by default relative
depth in pixel pitches at the object behind the nearest pixel, ``z = z_ref + d·z_ref/focal_px``
with ``z_ref`` the nearest depth, so the fusion anchors it exactly as it anchors an SFS map and
its scale fit is part of the anchoring error. ``metric: true`` hands the fusion metres
(``DepthMap.metric``), whose scale is then 1 up to the anchors' noise.

Pixels: the scene's ``mask`` (at least half covered by the object, :class:`~nirspi_pipe.types.Scene`),
the rule the renderer and the 3D metrics share (docs/mesh.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from nirspi_pipe.errors import NirspiError
from nirspi_pipe.types import Camera, DepthMap, Image2D, Scene

__all__ = ["TruthDepth"]


@dataclass(frozen=True)
class TruthDepth:
    """The renderer's depth as the SFS stage's output (an oracle for benchmarks).

    Args:
        metric: False (default): relative depth in pixel pitches at the nearest point, as every
            SFS stage returns it; True: z-depth in metres.
    """

    metric: bool = False
    #: the runner hands :meth:`solve` the scene rendered for the SFS grid (``stages.NeedsScene``)
    needs_scene: ClassVar[bool] = True

    def solve(self, image: Image2D, camera: Camera, scene: Scene | None = None) -> DepthMap:
        """The depth map of ``scene`` (rendered for ``camera``; units as ``metric`` says); the
        image is not used."""
        if scene is None:
            raise NirspiError("sfs truth: needs the simulated scene (source=simulator); a recording has no true depth")
        depth = np.asarray(scene.depth_m, dtype=np.float64)
        mask = np.asarray(scene.mask, dtype=bool) & np.isfinite(depth) & (depth > 0)
        n = camera.resolution
        if depth.shape != (n, n):
            raise NirspiError(f"sfs truth: the scene's depth {depth.shape} does not match the camera ({n}x{n})")
        if not mask.any():
            raise NirspiError("sfs truth: the scene covers no pixel at least half (empty mask): no depth to hand on")
        z_ref = float(depth[mask].min())
        info = {
            "model": "truth",
            "depth_units": "m" if self.metric else "pixel_pitch",
            "valid_fraction": float(mask.mean()),
            "z_ref_m": z_ref,
        }
        # off the object 0, as the SFS stages write it (the mask says what is valid)
        if self.metric:
            return DepthMap(np.where(mask, depth, 0.0), mask, metric=True, info=info)
        rel = np.where(mask, (depth - z_ref) * camera.focal_px / z_ref, 0.0)  # pixel pitches at the nearest point
        return DepthMap(rel, mask, metric=False, info=info)
