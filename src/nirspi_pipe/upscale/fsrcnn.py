"""Upscale ``fsrcnn``: FSRCNN (Dong, Loy & Tang, ECCV 2016), inference in numpy.

Architecture (the paper's notation): feature extraction conv 5×5 → ``d`` channels, shrinking
conv 1×1 → ``s`` channels, ``m`` mapping convs 3×3 ``s → s``, expanding conv 1×1 → ``d``, each
followed by a per-channel PReLU, then a 9×9 transposed convolution ("deconvolution") with stride
equal to the upscaling factor, to one channel. The weights are trained by
``nirspi-train-fsrcnn`` (:mod:`nirspi_pipe.upscale.train`, PyTorch, optional extra ``train``)
and shipped as small float32 ``.npz`` files in ``nirspi_pipe/upscale/weights/``; this module
needs only numpy.

Layer conventions are PyTorch's, so trained weights drop in unchanged: a convolution is a
cross-correlation with zero padding ``k // 2`` (``Conv2d`` weight ``(out, in, k, k)``); the
deconvolution is ``ConvTranspose2d(d, 1, 9, stride=scale, padding=4, output_padding=scale-1)``
(weight ``(in, out, k, k)``), which maps ``h × w`` to exactly ``h·scale × w·scale``.

Borders: the network is trained on interior patches with the loss cropped ``border`` low-res
pixels from the edges, so it never learned what zero padding means. At inference the input is
mirrored by ``border`` pixels (half-sample symmetric, as ``bicubic`` does) and the output is
cropped back, so every output pixel is computed the way it was trained.
"""

from __future__ import annotations

import hashlib
import json
import warnings
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from nirspi_pipe.errors import ConfigError, NirspiError
from nirspi_pipe.ranges import OneOf, check_ranges
from nirspi_pipe.safeio import read_npz, sanitize_text
from nirspi_pipe.types import Image2D
from nirspi_pipe.upscale.base import as_finite_image, check_scale, finish

__all__ = [
    "ConvLayer",
    "FsrcnnWeights",
    "conv2d",
    "conv_transpose2d",
    "prelu",
    "fsrcnn_forward",
    "load_weights",
    "save_weights",
    "packaged_weights_path",
    "resolve_weights",
    "shipped_weights",
    "FSRCNN",
]

DECONV_KERNEL = 9
DECONV_PADDING = 4


@dataclass(frozen=True)
class ConvLayer:
    """One convolution + PReLU: ``w`` ``(out, in, k, k)``, ``b`` ``(out,)``, ``alpha`` ``(out,)``
    (the negative-side slopes of the per-channel PReLU)."""

    w: np.ndarray
    b: np.ndarray
    alpha: np.ndarray


@dataclass(frozen=True)
class FsrcnnWeights:
    """A trained FSRCNN.

    Attributes:
        scale: upscaling factor (the deconvolution stride).
        layers: feature extraction, shrinking, mapping…, expanding (each conv + PReLU).
        deconv_w: ``(d, 1, 9, 9)`` transposed-convolution weight; ``deconv_b`` ``(1,)`` its bias.
        residual: when True the network predicts a correction added to :func:`bicubic`
            (False for the plain FSRCNN of the paper).
        border: low-resolution pixels mirrored around the input at inference (≥ the receptive
            radius; the training loss ignored that many pixels at patch edges).
        meta: training provenance (data, recipe, seed, held-out scores).
    """

    scale: int
    layers: tuple[ConvLayer, ...]
    deconv_w: np.ndarray
    deconv_b: np.ndarray
    residual: bool = False
    border: int = 8
    meta: dict[str, Any] | None = None

    @property
    def shape(self) -> tuple[int, int, int]:
        """``(d, s, m)`` in the paper's notation."""
        d = self.layers[0].w.shape[0]
        s = self.layers[1].w.shape[0] if len(self.layers) > 2 else d
        return d, s, max(len(self.layers) - 3, 0)

    @property
    def n_params(self) -> int:
        """Number of trainable parameters."""
        n = sum(l.w.size + l.b.size + l.alpha.size for l in self.layers)
        return int(n + self.deconv_w.size + self.deconv_b.size)


def prelu(x: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Per-channel PReLU of ``x`` ``(c, h, w)``: ``x`` where positive, ``alpha[c]·x`` elsewhere."""
    return np.where(x > 0, x, alpha[:, None, None] * x)


def conv2d(x: np.ndarray, w: np.ndarray, b: np.ndarray) -> np.ndarray:
    """'Same' 2D cross-correlation with zero padding ``k // 2`` (PyTorch ``Conv2d``).

    ``x`` ``(in, h, w)``, ``w`` ``(out, in, k, k)`` with odd ``k``, ``b`` ``(out,)`` → ``(out, h, w)``.
    Computed as one matrix product over the sliding windows (im2col).
    """
    co, ci, k, k2 = w.shape
    if k != k2 or k % 2 != 1 or x.shape[0] != ci:
        raise ValueError(f"conv2d: weight {w.shape} does not fit input {x.shape}")
    if k == 1:
        out = np.tensordot(w[:, :, 0, 0], x, axes=(1, 0))
    else:
        p = k // 2
        xp = np.pad(x, ((0, 0), (p, p), (p, p)))
        win = sliding_window_view(xp, (k, k), axis=(1, 2))  # (in, h, w, k, k)
        out = np.tensordot(w, win, axes=([1, 2, 3], [0, 3, 4]))  # (out, h, w)
    return out + b[:, None, None]


def conv_transpose2d(
    x: np.ndarray, w: np.ndarray, b: np.ndarray, stride: int, padding: int, output_padding: int
) -> np.ndarray:
    """2D transposed convolution (PyTorch ``ConvTranspose2d``).

    ``x`` ``(in, h, w)``, ``w`` ``(in, out, k, k)``, ``b`` ``(out,)``. Input pixel ``(i, j)``
    adds ``x[:, i, j] · w`` into the output window starting at ``(i·stride − padding,
    j·stride − padding)``. Output side ``(h − 1)·stride − 2·padding + k + output_padding``.
    """
    ci, co, k, _ = w.shape
    if x.shape[0] != ci:
        raise ValueError(f"conv_transpose2d: weight {w.shape} does not fit input {x.shape}")
    _, h, wd = x.shape
    oh = (h - 1) * stride - 2 * padding + k + output_padding
    ow = (wd - 1) * stride - 2 * padding + k + output_padding
    contrib = np.tensordot(w, x, axes=(0, 0))  # (out, k, k, h, w)
    fh = max((h - 1) * stride + k, padding + oh)
    fw = max((wd - 1) * stride + k, padding + ow)
    full = np.zeros((co, fh, fw), dtype=np.result_type(x, w))
    span_h, span_w = (h - 1) * stride + 1, (wd - 1) * stride + 1
    for ky in range(k):
        for kx in range(k):
            full[:, ky : ky + span_h : stride, kx : kx + span_w : stride] += contrib[:, ky, kx]
    return full[:, padding : padding + oh, padding : padding + ow] + b[:, None, None]


def fsrcnn_forward(image: np.ndarray, weights: FsrcnnWeights) -> np.ndarray:
    """Run FSRCNN on a 2D image (relative radiance) → ``(h·scale, w·scale)`` float64, unclipped.

    The input is mirrored by ``weights.border`` pixels, the network runs in float64 (the weights
    are stored in float32), and the output is cropped back to the image (see the module docstring).
    float64, not float32: the 3D path shades the upscaled image, and float32 rounding differed by
    ~1e-7 between OpenBLAS kernel sets (Haswell vs Sandybridge), enough to flip a point of the fused
    cloud (issue 12; ``bash .ci/reproduce-cpus.sh``).
    """
    from nirspi_pipe.upscale.bicubic import bicubic  # import circle: nirspi_pipe.upscale.bicubic imports this module

    s, pad = weights.scale, weights.border
    lr = np.asarray(image, dtype=np.float64)
    x = np.pad(lr, pad, mode="symmetric")[None]
    for layer in weights.layers:
        x = prelu(conv2d(x, layer.w, layer.b), layer.alpha)
    y = conv_transpose2d(x, weights.deconv_w, weights.deconv_b, s, DECONV_PADDING, s - 1)[0]
    h, w = lr.shape
    y = y[pad * s : pad * s + h * s, pad * s : pad * s + w * s].astype(np.float64)
    if weights.residual:
        y = y + bicubic(lr, s)
    return y


#: ``upscale.backend`` of ``upscale=fsrcnn``: numpy (float64, the reference) or torch (float32).
BACKENDS = ("numpy", "torch")
#: ``upscale.device`` of the torch back end: ``auto`` is CUDA when torch sees a GPU, else the CPU.
DEVICES = ("auto", "cpu", "cuda")


def torch_device(device: str) -> str:
    """The torch device (``cpu``/``cuda``) for ``upscale.device``; :class:`NirspiError` (one
    line) for ``cuda`` where torch has no CUDA, :class:`ConfigError` without torch."""
    if device not in DEVICES:
        raise ConfigError("device", device, ", ".join(DEVICES))
    try:
        import torch  # optional dependency: torch
    except ImportError:
        raise ConfigError(
            "backend", "torch", "numpy, or torch once installed (pip install 'nirspi-pipe[train]')"
        ) from None
    cuda = bool(torch.cuda.is_available())
    if device == "cuda" and not cuda:
        raise NirspiError(
            f"upscale.device=cuda: torch {torch.__version__} sees no CUDA GPU here; use upscale.device=cpu or auto"
        )
    return "cuda" if device == "cuda" or (device == "auto" and cuda) else "cpu"


class _Tf32:
    """Allow or forbid TF32 in CUDA matmuls and cuDNN convolutions for one call, then restore
    torch's settings as they were (``torch.backends.cuda.matmul.allow_tf32``,
    ``torch.backends.cudnn.allow_tf32``)."""

    def __init__(self, torch: Any, on: bool) -> None:
        self.torch, self.on = torch, bool(on)

    def __enter__(self) -> None:
        b = self.torch.backends
        self.saved = (b.cuda.matmul.allow_tf32, b.cudnn.allow_tf32)
        b.cuda.matmul.allow_tf32 = self.on
        b.cudnn.allow_tf32 = self.on

    def __exit__(self, *exc: object) -> None:
        b = self.torch.backends
        b.cuda.matmul.allow_tf32, b.cudnn.allow_tf32 = self.saved


def fsrcnn_forward_torch(
    image: np.ndarray, weights: FsrcnnWeights, device: str = "cpu", tf32: bool = False
) -> np.ndarray:
    """:func:`fsrcnn_forward` with torch's float32 layers on ``device`` (``cpu``/``cuda``), as
    ``nirspi-train-fsrcnn`` runs the network; float64 out. ``tf32``: allow TensorFloat-32 in
    cuDNN's convolutions (faster on Ampere and later, error ~1e-3 against numpy instead of ~1e-6,
    measured on an H200: docs/gpu.md); off by default, restored after the call."""
    import torch  # optional dependency: torch
    from torch.nn import functional as F  # optional dependency: torch

    from nirspi_pipe.upscale.bicubic import bicubic  # import circle: nirspi_pipe.upscale.bicubic imports this module

    def f32(a: np.ndarray) -> Any:
        return torch.from_numpy(np.array(a, dtype=np.float32)).to(device)  # a writable float32 copy

    s, pad = weights.scale, weights.border
    lr = np.asarray(image, dtype=np.float64)
    x = torch.from_numpy(np.pad(lr, pad, mode="symmetric").astype(np.float32))[None, None].to(device)
    with torch.no_grad(), _Tf32(torch, tf32):
        for layer in weights.layers:
            x = F.conv2d(x, f32(layer.w), f32(layer.b), padding=layer.w.shape[-1] // 2)
            x = F.prelu(x, f32(layer.alpha))
        y = F.conv_transpose2d(
            x, f32(weights.deconv_w), f32(weights.deconv_b), stride=s, padding=DECONV_PADDING, output_padding=s - 1
        )
        out = y[0, 0].cpu().numpy().astype(np.float64)
    h, wd = lr.shape
    out = out[pad * s : pad * s + h * s, pad * s : pad * s + wd * s]
    return out + bicubic(lr, s) if weights.residual else out


def save_weights(path: str | Path, weights: FsrcnnWeights) -> None:
    """Write ``weights`` as a compressed float32 ``.npz`` (no pickles; ``meta`` as JSON text)."""
    arrays: dict[str, Any] = {}  # Any: numpy types savez(**kwds) as arrays or allow_pickle: bool
    for i, layer in enumerate(weights.layers):
        arrays[f"conv{i}_w"] = layer.w.astype(np.float32)
        arrays[f"conv{i}_b"] = layer.b.astype(np.float32)
        arrays[f"conv{i}_a"] = layer.alpha.astype(np.float32)
    arrays["deconv_w"] = weights.deconv_w.astype(np.float32)
    arrays["deconv_b"] = weights.deconv_b.astype(np.float32)
    arrays["scale"] = np.array(weights.scale, dtype=np.int64)
    arrays["residual"] = np.array(weights.residual)
    arrays["border"] = np.array(weights.border, dtype=np.int64)
    arrays["meta"] = np.array(json.dumps(weights.meta or {}, sort_keys=True))
    np.savez_compressed(path, **arrays)


def _weight_array(z: dict[str, np.ndarray], key: str, ndim: int) -> np.ndarray:
    """``z[key]``, once it is an ``ndim``-D numeric array with finite values."""
    if key not in z:
        raise ValueError(f"key '{key}' missing")
    a = z[key]
    if a.dtype.kind not in "fiub" or a.ndim != ndim:
        raise ValueError(f"key '{key}': expected a {ndim}-D numeric array, got {a.dtype} of shape {a.shape}")
    if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
        raise ValueError(f"key '{key}': non-finite values")
    return np.asarray(a)


def _conv_layers(z: dict[str, np.ndarray]) -> tuple[list[ConvLayer], int]:
    """The convolution layers ``conv{i}_w/_b/_a``, each following the previous one's channels
    (from 1), and the last layer's output channels."""
    n = sum(1 for k in z if k.startswith("conv") and k.endswith("_w"))
    if not 2 <= n <= 64:
        raise ValueError(f"{n} conv layers (expected 2-64: conv0_w, conv1_w, ...)")
    layers = []
    channels = 1
    for i in range(n):
        w = _weight_array(z, f"conv{i}_w", 4)
        b = _weight_array(z, f"conv{i}_b", 1)
        a = _weight_array(z, f"conv{i}_a", 1)
        out, cin, k1, k2 = w.shape
        if cin != channels or k1 != k2 or k1 % 2 != 1 or b.shape != (out,) or a.shape != (out,):
            raise ValueError(
                f"key 'conv{i}_w': shape {w.shape} does not follow {channels} input channels "
                "(odd square kernels; bias and PReLU slopes of one value per output)"
            )
        layers.append(ConvLayer(w, b, a))
        channels = out
    return layers, channels


def _weight_scalars(z: dict[str, np.ndarray]) -> dict[str, Any]:
    """``scale`` (an integer 2-8), ``residual`` and ``border`` (an integer 0-64)."""
    scalars = {}
    for key in ("scale", "residual", "border"):
        v = _weight_array(z, key, 0)
        scalars[key] = v.item()
    if not (isinstance(scalars["scale"], int) and 2 <= scalars["scale"] <= 8):
        raise ValueError(f"key 'scale': {scalars['scale']!r} is not an integer 2-8")
    if not (isinstance(scalars["border"], int) and 0 <= scalars["border"] <= 64):
        raise ValueError(f"key 'border': {scalars['border']!r} is not an integer 0-64")
    return scalars


def _weight_meta(z: dict[str, np.ndarray]) -> Any:
    """The ``meta`` JSON string's value ({} without one)."""
    meta_raw = z.get("meta")
    if meta_raw is None:
        return {}
    if meta_raw.dtype.kind not in "US" or meta_raw.ndim != 0:
        raise ValueError("key 'meta': expected a JSON string")
    return json.loads(str(meta_raw.item()))


def _read_weights(path: str | Path) -> FsrcnnWeights:
    """Read and check a weights file: bounded NPZ reading (:func:`nirspi_pipe.safeio.read_npz`,
    weights are small: 64 MB at most), then every array's shape against the architecture, so a
    hostile file fails here with one line instead of deep inside the forward pass."""
    z = read_npz(path, str(path), budget=64 << 20, mmap=False)
    layers, channels = _conv_layers(z)
    deconv_w, deconv_b = _weight_array(z, "deconv_w", 4), _weight_array(z, "deconv_b", 1)
    if deconv_w.shape != (channels, 1, DECONV_KERNEL, DECONV_KERNEL) or deconv_b.shape != (1,):
        raise ValueError(
            f"key 'deconv_w': shape {deconv_w.shape}, expected {(channels, 1, DECONV_KERNEL, DECONV_KERNEL)}"
        )
    scalars = _weight_scalars(z)
    meta = _weight_meta(z)
    return FsrcnnWeights(
        scale=int(scalars["scale"]),
        layers=tuple(layers),
        deconv_w=deconv_w,
        deconv_b=deconv_b,
        residual=bool(scalars["residual"]),
        border=int(scalars["border"]),
        meta=meta if isinstance(meta, dict) else {"meta": meta},
    )


@lru_cache(maxsize=8)
def _load_cached(path: str) -> FsrcnnWeights:
    return _read_weights(path)


def packaged_weights_path(scale: int) -> Path:
    """Path of the shipped weights for ``scale`` (``nirspi_pipe/upscale/weights/fsrcnn_x{s}.npz``)."""
    return _weights_folder() / f"fsrcnn_x{int(scale)}.npz"


@lru_cache(maxsize=1)
def _weights_folder() -> Path:
    """The package's weights folder, looked up once per process (the installed package does not
    move while it runs; ``importlib.resources`` and the folder listing below cost about 1 ms a
    call, and every upscaled job asked five times)."""
    return Path(str(resources.files("nirspi_pipe.upscale") / "weights"))


@lru_cache(maxsize=1)
def shipped_weights() -> tuple[str, ...]:
    """File names of the weights shipped in the package (``nirspi_pipe/upscale/weights``)."""
    return tuple(sorted(p.name for p in _weights_folder().glob("*.npz")))


def resolve_weights(scale: int, path: str | Path | None = None) -> Path:
    """The weights file for ``scale``: the packaged ``fsrcnn_x{scale}.npz`` when ``path`` is None;
    the name of a shipped file (:func:`shipped_weights`, e.g. ``fsrcnn_x4_led8.npz``) is always the
    packaged file, never a file of that name in the working directory; anything else is a path
    (``./fsrcnn_x4_led8.npz`` names the working directory's file explicitly)."""
    if path is None:
        return packaged_weights_path(scale)
    if str(path) in shipped_weights():
        return packaged_weights_path(scale).with_name(str(path))
    return Path(path).expanduser()


@lru_cache(maxsize=8)
def weights_sha256(path: str) -> str:
    """SHA-256 of a weights file (hex), for the record."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def load_weights(scale: int, path: str | Path | None = None) -> FsrcnnWeights:
    """Load FSRCNN weights: the packaged ones for ``scale``, a shipped file by name, or the file
    ``path`` (:func:`resolve_weights`).

    Raises :class:`ConfigError` (key ``weights``) when the file is missing, unreadable or trained
    for another scale.
    """
    file = resolve_weights(scale, path)
    if not file.is_file():
        raise ConfigError(
            "weights",
            str(path) if path else None,
            f"an existing .npz file or a shipped name ({', '.join(shipped_weights())}); {file} not found",
        )
    try:
        weights = _load_cached(str(file.resolve()))
    except Exception as exc:  # noqa: BLE001 - any unreadable file is a config problem
        raise ConfigError(
            "weights", str(file), f"an FSRCNN .npz written by nirspi-train-fsrcnn ({sanitize_text(exc)})"
        ) from None
    if weights.scale != int(scale):
        raise ConfigError("weights", str(file), f"weights trained for scale {scale} (this file is ×{weights.scale})")
    return weights


@dataclass(frozen=True)
class FSRCNN:
    """Upscale ``fsrcnn``: the paper's CS-SRCNN step, super-resolving the SPI reconstruction.

    Attributes:
        scale: upscaling factor, 2, 3 or 4.
        weights: path of an ``.npz`` from ``nirspi-train-fsrcnn``, or the name of a shipped file
            (``fsrcnn_x4_led8.npz``: ×4 for the 8 × 8 LED device); null uses the packaged
            ``fsrcnn_x{scale}.npz`` (trained on 64² inputs).
        clip: clip the result to the physical range [0, 1].
        backend: ``numpy`` (float64, the reference) or ``torch`` (float32 layers, optional extra
            ``train``; parity 1e-5 with TF32 off, tests/test_parity.py).
        device: torch back end only: ``auto`` (CUDA when torch sees a GPU, else the CPU),
            ``cpu`` or ``cuda`` (one-line error where there is no CUDA).
        tf32: torch on CUDA only: allow TensorFloat-32 convolutions (faster; max error 1.3e-3
            against numpy instead of 1.5e-6, measured on an H200: docs/gpu.md). Off by default.
    """

    scale: int = 2
    weights: str | None = None
    clip: bool = True
    backend: Annotated[str, OneOf(BACKENDS)] = "numpy"
    device: Annotated[str, OneOf(DEVICES)] = "auto"
    tf32: Annotated[bool, OneOf((True, False), "true or false")] = False

    def __post_init__(self) -> None:
        check_scale(self.scale)
        check_ranges(self)
        if self.backend == "torch":
            torch_device(self.device)  # torch installed, CUDA there if asked: fail at build time
        load_weights(int(self.scale), self.weights)  # fail at build time, not after the solver

    def upscale(self, image: Image2D) -> Image2D:
        net = load_weights(int(self.scale), self.weights)
        x = as_finite_image(image.data, "fsrcnn")
        if self.backend == "torch":
            dev = torch_device(self.device)
            y = fsrcnn_forward_torch(x, net, dev, bool(self.tf32) and dev == "cuda")
        else:
            dev = "cpu"
            y = fsrcnn_forward(x, net)
        if not np.all(np.isfinite(y)):  # cannot happen with finite weights; never pass NaN on
            warnings.warn("upscale=fsrcnn: non-finite output replaced by 0", stacklevel=2)
            y = np.nan_to_num(y, nan=0.0, posinf=0.0, neginf=0.0)
        y = finish(y, self.clip)
        d, s, m = net.shape
        file = resolve_weights(int(self.scale), self.weights).resolve()
        packaged = file.parent == packaged_weights_path(int(self.scale)).resolve().parent
        info = {
            "model": "fsrcnn",
            "scale": int(self.scale),
            "shape": list(y.shape),
            "weights": Path(self.weights).name if self.weights else f"fsrcnn_x{self.scale}.npz",
            "weights_file": f"package:{file.name}" if packaged else str(file),
            "weights_sha256": weights_sha256(str(file)),
            "d": d,
            "s": s,
            "m": m,
            "residual": net.residual,
            "n_params": net.n_params,
            "backend": self.backend,
            "device": dev,
            "tf32": bool(self.tf32) and dev == "cuda",
        }
        return Image2D(y, info=info)
