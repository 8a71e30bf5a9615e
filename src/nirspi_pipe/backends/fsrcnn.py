"""FSRCNN inference's back ends: numpy (reference, float64) and torch (float32, as trained; CPU
and CUDA), fixtures and bounds (:data:`FSRCNN`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from nirspi_pipe.backends.harness import Backend, Family, Tolerance

__all__ = ["FSRCNN", "FsrcnnCase"]


# --- FSRCNN inference: numpy (reference, float64) and torch (float32, as trained) --------------


@dataclass(frozen=True)
class FsrcnnCase:
    """A network and a low-resolution image."""

    weights: Any  # nirspi_pipe.upscale.fsrcnn.FsrcnnWeights
    image: np.ndarray
    #: ``trained-x…`` fixtures: the torch network of ``nirspi-train-fsrcnn`` (``upscale.train``)
    #: that ``weights`` were exported from; the torch back end runs it, so its export is checked too.
    module: Any = None


_FSRCNN_FIXTURES = (
    "shipped-x2",
    "shipped-x3",
    "shipped-x4",
    "random-x3-plain",
    "trained-x2",
    "trained-x3",
    "trained-x4",
)


def _fsrcnn_fixture(name: str) -> FsrcnnCase:
    # start-up: loads scipy, charset_normalizer (233 ms here)
    from nirspi_pipe.upscale.fsrcnn import (
        ConvLayer,
        FsrcnnWeights,
        load_weights,
    )

    kind, scale_s, *_ = name.split("-")
    scale = int(scale_s[1:])
    rng = np.random.default_rng(scale)
    yy, xx = np.mgrid[0:9, 0:11] / 10.0
    image = np.clip(0.5 + 0.3 * np.sin(6 * xx + 3 * yy) + 0.05 * rng.standard_normal((9, 11)), 0, 1)
    if kind == "shipped":
        return FsrcnnCase(load_weights(scale), image)
    if kind == "trained":  # a fresh network as nirspi-train-fsrcnn builds it, exported (needs torch)
        import torch  # optional dependency: torch

        # start-up: loads scipy, charset_normalizer (298 ms here)
        from nirspi_pipe.upscale.train import (
            _build_net,
            _to_weights,
        )

        torch.manual_seed(scale)
        net = _build_net(torch, scale, 6, 3, 2)
        return FsrcnnCase(_to_weights(net, scale, residual=False, border=6, meta={}), image, net)
    d, s = 6, 3  # (d, s, m) = (6, 3, 2), weights of order one so that rounding shows
    shapes = [(d, 1, 5), (s, d, 1), (s, s, 3), (s, s, 3), (d, s, 1)]
    layers = tuple(
        ConvLayer(
            rng.normal(0, 0.5, (o, i, k, k)).astype(np.float32),
            rng.normal(0, 0.1, o).astype(np.float32),
            rng.uniform(0.0, 0.5, o).astype(np.float32),
        )
        for o, i, k in shapes
    )
    deconv_w = rng.normal(0, 0.2, (d, 1, 9, 9)).astype(np.float32)
    return FsrcnnCase(FsrcnnWeights(scale, layers, deconv_w, np.array([0.1], np.float32), border=6), image)


def _fsrcnn_numpy(case: FsrcnnCase) -> np.ndarray:
    from nirspi_pipe.upscale.fsrcnn import fsrcnn_forward  # start-up: loads scipy, charset_normalizer (233 ms here)

    return fsrcnn_forward(case.image, case.weights)


def _fsrcnn_torch(case: FsrcnnCase) -> np.ndarray:
    """The network as ``nirspi-train-fsrcnn`` runs it: torch's float32 layers on the mirrored image
    (the training network itself for a ``trained`` fixture), cropped, plus the bicubic image for
    residual weights (upscale/train.py's own check), on the CPU."""
    # start-up: loads scipy, charset_normalizer (233 ms here)
    from nirspi_pipe.upscale.fsrcnn import (
        fsrcnn_forward_torch,
    )

    if case.module is None:
        return fsrcnn_forward_torch(case.image, case.weights, "cpu")
    import torch  # optional dependency: torch

    from nirspi_pipe.upscale.bicubic import bicubic  # start-up: loads scipy, charset_normalizer (200 ms here)

    w, s, pad = case.weights, case.weights.scale, case.weights.border
    x = torch.from_numpy(np.pad(case.image, pad, mode="symmetric").astype(np.float32))[None, None]
    with torch.no_grad():
        y = case.module(x)
    h, wd = case.image.shape
    out = y[0, 0].numpy().astype(np.float64)[pad * s : pad * s + h * s, pad * s : pad * s + wd * s]
    return out + bicubic(case.image, s) if w.residual else out


def _fsrcnn_torch_cuda(case: FsrcnnCase) -> np.ndarray:
    """:func:`_fsrcnn_torch` on CUDA with TF32 off (``upscale.device=cuda``, the default ``tf32: false``)."""
    # start-up: loads scipy, charset_normalizer (233 ms here)
    from nirspi_pipe.upscale.fsrcnn import (
        fsrcnn_forward_torch,
    )

    return fsrcnn_forward_torch(case.image, case.weights, "cuda", tf32=False)


def _cuda_unavailable() -> str | None:
    why = _torch_unavailable()
    if why is not None:
        return why
    import torch  # optional dependency: torch

    return None if torch.cuda.is_available() else "torch sees no CUDA GPU here"


def _torch_unavailable() -> str | None:
    try:
        # optional dependency: torch
        import torch  # noqa: F401 - only whether it imports
    except ImportError:
        return "torch is not installed (pip install 'nirspi-pipe[train]')"
    return None


def _fsrcnn_compare(case: FsrcnnCase, a: np.ndarray, b: np.ndarray) -> dict[str, float]:
    return {"shape": float(a.shape != b.shape), "max_abs": float(np.max(np.abs(a - b))) if a.shape == b.shape else 1.0}


FSRCNN = Family(
    name="fsrcnn",
    reference=Backend("numpy", _fsrcnn_numpy, lambda: None),
    alternatives=(
        Backend("torch", _fsrcnn_torch, _torch_unavailable, marks=("torch",)),
        Backend("torch-cuda", _fsrcnn_torch_cuda, _cuda_unavailable, marks=("torch",)),
    ),
    fixture_names=_FSRCNN_FIXTURES,
    make_fixture=_fsrcnn_fixture,
    compare=_fsrcnn_compare,
    tolerances={
        "shape": Tolerance(0, "both crop to (h·scale, w·scale): the same output size"),
        "max_abs": Tolerance(
            1e-5,
            "torch runs in float32, numpy in float64; the cases include the trained-x2/x3/x4 fixtures "
            "(the training network against its exported weights). The float32 rounding it stands for, measured by "
            "running fsrcnn_forward's layers in float32 with numpy on these 4 fixtures: max |dy| = 1.6e-7 "
            "(shipped weights), 1.5e-6 (random net); torch 2.11 on an H200 with TF32 off: 1.5e-6 (with "
            "TF32 on: 1.3e-3, over the bound, hence upscale.tf32 false by default)",
        ),
    },
)
