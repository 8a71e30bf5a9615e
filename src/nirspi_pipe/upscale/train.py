"""``nirspi-train-fsrcnn``: train the FSRCNN weights shipped in ``nirspi_pipe/upscale/weights``.

Needs PyTorch (``pip install 'nirspi-pipe[train]'``); inference does not. The recipe, the data
and how to reproduce the shipped files are in ``docs/upscale.md``. In short: pairs of
(SPI reconstruction at ``n = 64``, true radiance at ``64·scale``; ``--n-lr 8`` for the paper's
8 × 8 LED device, whose weights ship as ``fsrcnn_x4_led8.npz``) from
:func:`nirspi_pipe.upscale.data.training_pairs`; random ``patch + 2·border`` low-res crops with
flips and rotations (whole images mirrored by ``border`` when ``n`` is no larger than the patch); a global residual (the network learns ``hr − bicubic(lr)``; ``--plain``
for the paper's plain FSRCNN); MSE on the central ``patch × patch`` (×scale) region only; Adam with a
cosine learning-rate decay; a fixed number of iterations and seeds (no model selection on the
held-out set). After training it checks that the numpy inference reproduces the PyTorch network,
scores the held-out set against bicubic and writes ``fsrcnn_x{scale}.npz`` with the recipe and
scores in its ``meta``.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from nirspi_pipe.upscale.bicubic import bicubic
from nirspi_pipe.upscale.data import HELDOUT_SAMPLES, TRAIN_SAMPLES, heldout_pairs, training_pairs
from nirspi_pipe.upscale.evaluate import score_heldout, summarise
from nirspi_pipe.upscale.fsrcnn import ConvLayer, FsrcnnWeights, fsrcnn_forward, save_weights

__all__ = ["main", "train_scale"]

_DEFAULT_OUT = Path(__file__).resolve().parent / "weights"


def _import_torch():
    try:
        import torch  # optional dependency: torch
    except ImportError:
        print(
            "nirspi-train-fsrcnn: error: PyTorch is not installed; install the optional extra: "
            "pip install 'nirspi-pipe[train]'",
            file=sys.stderr,
        )
        raise SystemExit(2) from None
    return torch


def _build_net(torch, scale: int, d: int, s: int, m: int):
    nn = torch.nn
    layers: list[Any] = [nn.Conv2d(1, d, 5, padding=2), nn.PReLU(d), nn.Conv2d(d, s, 1), nn.PReLU(s)]
    for _ in range(m):
        layers += [nn.Conv2d(s, s, 3, padding=1), nn.PReLU(s)]
    layers += [nn.Conv2d(s, d, 1), nn.PReLU(d)]
    body = nn.Sequential(*layers)
    deconv = nn.ConvTranspose2d(d, 1, 9, stride=scale, padding=4, output_padding=scale - 1)
    for mod in body:
        if isinstance(mod, nn.Conv2d):
            nn.init.kaiming_normal_(mod.weight, a=0.25, nonlinearity="leaky_relu")
            nn.init.zeros_(mod.bias)
    nn.init.normal_(deconv.weight, std=1e-3)  # FSRCNN paper: deconvolution from N(0, 0.001)
    nn.init.zeros_(deconv.bias)
    return nn.Sequential(body, deconv)


def _to_weights(net, scale: int, residual: bool, border: int, meta: dict[str, Any]) -> FsrcnnWeights:
    body, deconv = net[0], net[1]
    mods = list(body)
    layers = []
    for conv, act in zip(mods[0::2], mods[1::2]):
        layers.append(
            ConvLayer(
                conv.weight.detach().numpy().astype(np.float32),
                conv.bias.detach().numpy().astype(np.float32),
                act.weight.detach().numpy().astype(np.float32),
            )
        )
    return FsrcnnWeights(
        scale=scale,
        layers=tuple(layers),
        deconv_w=deconv.weight.detach().numpy().astype(np.float32),
        deconv_b=deconv.bias.detach().numpy().astype(np.float32),
        residual=residual,
        border=border,
        meta=meta,
    )


def train_scale(scale: int, ns: argparse.Namespace, log=print) -> FsrcnnWeights:
    """Train one scale with the options in ``ns`` (see :func:`main`) and return the weights."""
    torch = _import_torch()
    torch.manual_seed(ns.seed * 10 + scale)
    torch.set_num_threads(ns.threads)
    rng = np.random.default_rng([ns.seed, scale])
    border = 4 + ns.m  # receptive radius in low-res pixels: conv5 2 + m·1 + deconv 2 (≤ 4 + m)

    t0 = time.perf_counter()
    pairs = list(
        training_pairs(
            scale,
            n_lr=ns.n_lr,
            variants=ns.variants,
            n_shapes=ns.shapes,
            n_spheres=ns.spheres,
            noise_max=ns.noise_max,
            noise_min=ns.noise_min,
            seed=ns.data_seed,
        )
    )
    lr = np.stack([p.lr for p in pairs]).astype(np.float32)
    hr = np.stack([p.hr for p in pairs]).astype(np.float32)
    if ns.residual:  # predict hr − bicubic(lr), bicubic over the whole image as at inference
        hr = hr - np.stack([bicubic(p.lr, scale) for p in pairs]).astype(np.float32)
    log(f"x{scale}: {len(pairs)} training images ({lr.shape[1]}² → {hr.shape[1]}²) in {time.perf_counter() - t0:.1f} s")
    # Whole-image mode (a low-res side no larger than the patch, e.g. the device's 8²): the network
    # sees every image whole, mirrored by ``border`` pixels exactly as fsrcnn_forward pads it at
    # inference, and the loss covers the whole image. Symmetric padding of the low-res image by
    # ``border`` and of the target by ``border·scale`` keeps the pixel blocks aligned.
    whole = ns.patch >= ns.n_lr
    patch = ns.n_lr if whole else ns.patch
    if whole:
        lr = np.pad(lr, ((0, 0), (border, border), (border, border)), mode="symmetric")
        hr = np.pad(hr, ((0, 0), (border * scale,) * 2, (border * scale,) * 2), mode="symmetric")

    net = _build_net(torch, scale, ns.d, ns.s, ns.m)
    opt = torch.optim.Adam(net.parameters(), lr=ns.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=ns.iters, eta_min=ns.lr * 0.01)
    lr_t, hr_t = torch.from_numpy(lr), torch.from_numpy(hr)
    win = patch + 2 * border
    n_img, side = lr.shape[0], lr.shape[1]
    losses: list[float] = []
    t0 = time.perf_counter()
    for it in range(ns.iters):
        k = rng.integers(0, n_img, ns.batch)
        ys, xs = rng.integers(0, side - win + 1, (2, ns.batch))
        xb = torch.stack([lr_t[i, y : y + win, x : x + win] for i, y, x in zip(k, ys, xs)])[:, None]
        yb = torch.stack(
            [
                hr_t[
                    i,
                    (y + border) * scale : (y + border + patch) * scale,
                    (x + border) * scale : (x + border + patch) * scale,
                ]
                for i, y, x in zip(k, ys, xs)
            ]
        )[:, None]
        rot, flip = int(rng.integers(4)), bool(rng.integers(2))  # same for LR and HR: blocks stay aligned
        xb, yb = torch.rot90(xb, rot, (2, 3)), torch.rot90(yb, rot, (2, 3))
        if flip:
            xb, yb = torch.flip(xb, (3,)), torch.flip(yb, (3,))
        out = net(xb)[:, :, border * scale : (border + patch) * scale, border * scale : (border + patch) * scale]
        loss = torch.mean((out - yb) ** 2)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        losses.append(float(loss.detach()))
        if (it + 1) % max(ns.iters // 10, 1) == 0:
            recent = float(np.mean(losses[-100:]))
            log(
                f"x{scale}: iter {it + 1}/{ns.iters} mse {recent:.3e} (psnr {-10 * np.log10(recent):.2f} dB) {time.perf_counter() - t0:.0f} s"
            )
    train_s = time.perf_counter() - t0

    meta: dict[str, Any] = {
        "paper": "FSRCNN, Dong, Loy & Tang, ECCV 2016",
        "trained_by": "nirspi-train-fsrcnn",
        "argv": " ".join(ns.argv),
        "d_s_m": [ns.d, ns.s, ns.m],
        "iters": ns.iters,
        "batch": ns.batch,
        "patch_lr": patch,
        "whole_images": whole,
        "border_lr": border,
        "adam_lr": ns.lr,
        "seed": ns.seed,
        "data_seed": ns.data_seed,
        "n_lr": ns.n_lr,
        "variants": ns.variants,
        "shapes": ns.shapes,
        "spheres": ns.spheres,
        "noise_max": ns.noise_max,
        "noise_min": ns.noise_min,
        "train_images": len(pairs),
        "train_samples": list(TRAIN_SAMPLES),
        "heldout_samples": list(HELDOUT_SAMPLES),
        "final_train_mse": float(np.mean(losses[-200:])),
        "train_seconds": round(train_s, 1),
        "heldout_noise": list(ns.heldout_noise),
        "torch": torch.__version__,
    }
    weights = _to_weights(net, scale, ns.residual, border, meta)

    # The numpy inference must reproduce the trained network (same layers, same padding).
    probe = heldout_pairs(scale, 0.0, n_lr=32)[0].lr
    with torch.no_grad():
        xp = np.pad(probe, border, mode="symmetric").astype(np.float32)
        ref = net(torch.from_numpy(xp)[None, None])[0, 0].numpy().astype(np.float64)
    ref = ref[border * scale : -border * scale, border * scale : -border * scale]
    if ns.residual:
        ref = ref + bicubic(probe, scale)
    err = float(np.max(np.abs(fsrcnn_forward(probe, weights) - ref)))
    if err > 1e-4:
        raise RuntimeError(f"numpy inference differs from torch by {err:.2e}")
    summary = summarise(score_heldout(weights, tuple(ns.heldout_noise), n_lr=ns.n_lr))
    meta["numpy_vs_torch_max_abs"] = err
    meta["heldout"] = summary
    for row in summary:
        log(
            f"x{scale} held-out noise_rel={row['noise_rel']:g}: PSNR bicubic {row['psnr_bicubic']:.2f} "
            f"fsrcnn {row['psnr_fsrcnn']:.2f} (gain {row['gain_db']:+.2f} dB); SSIM "
            f"{row['ssim_bicubic']:.4f} → {row['ssim_fsrcnn']:.4f}"
        )
    return weights


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``nirspi-train-fsrcnn``."""
    args = list(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(prog="nirspi-train-fsrcnn", description=__doc__.split("\n\n")[0])
    p.add_argument("--scales", type=int, nargs="+", default=[2, 3, 4], choices=[2, 3, 4])
    p.add_argument(
        "--out", type=Path, default=_DEFAULT_OUT, help="folder for fsrcnn_x{scale}.npz (default: the package's)"
    )
    p.add_argument("--d", type=int, default=32, help="feature channels (paper: d)")
    p.add_argument("--s", type=int, default=8, help="shrunk channels (paper: s)")
    p.add_argument("--m", type=int, default=2, help="mapping layers (paper: m)")
    p.add_argument("--iters", type=int, default=2000)
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--patch", type=int, default=16, help="low-res side of the scored patch centre")
    p.add_argument("--lr", type=float, default=1e-3, help="Adam learning rate (cosine decay to 1%%)")
    p.add_argument("--n-lr", type=int, default=64, help="low-res side of training images (power of two)")
    p.add_argument("--variants", type=int, default=3, help="random crops per training sample image")
    p.add_argument("--shapes", type=int, default=30, help="synthetic shape scenes in the training set")
    p.add_argument("--spheres", type=int, default=10, help="rendered spheres in the training set")
    p.add_argument("--noise-max", type=float, default=2e-3, help="largest training noise_rel")
    p.add_argument(
        "--noise-min", type=float, default=None, help="smallest non-zero training noise_rel (default: noise-max/30)"
    )
    p.add_argument(
        "--heldout-noise",
        type=float,
        nargs="+",
        default=[0.0, 1e-3],
        help="noise_rel levels of the held-out scores written into meta",
    )
    p.add_argument("--name", default="fsrcnn_x{scale}.npz", help="output file name ({scale} is replaced)")
    p.add_argument(
        "--plain", action="store_true", help="the paper's plain FSRCNN (default: learn a correction to bicubic)"
    )
    p.add_argument("--seed", type=int, default=0, help="initialisation and batch seed")
    p.add_argument("--data-seed", type=int, default=20160, help="training-data seed")
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    ns = p.parse_args(args)
    ns.argv = ["nirspi-train-fsrcnn", *args]
    ns.residual = not ns.plain
    ns.out.mkdir(parents=True, exist_ok=True)
    for scale in ns.scales:
        weights = train_scale(scale, ns)
        path = ns.out / ns.name.format(scale=scale)
        save_weights(path, weights)
        print(f"x{scale}: {weights.n_params} parameters -> {path} ({path.stat().st_size / 1024:.1f} kB)")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
