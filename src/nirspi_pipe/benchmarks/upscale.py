"""``nirspi-bench upscale``: FSRCNN against bicubic on the held-out images, quality and speed.

Quality: PSNR (dB) and SSIM of the packaged FSRCNN weights and of bicubic interpolation, both
upscaling the same ``fwht`` reconstruction of a ``64 × 64`` camera, scored against the true
radiance at ``64·scale`` (held-out set of :func:`nirspi_pipe.upscale.data.heldout_pairs`: the
scikit-image samples camera, astronaut, coins, moon; the paper's sphere at 200 and 150 mm; four
synthetic scenes from a seed the training never uses), noise-free and with detector noise.

Speed: median time of the numpy FSRCNN inference and of bicubic interpolation on the same
image in the same run; the ratio ``fsrcnn / bicubic`` is the cost of the network over the
interpolation it is compared with.
"""

from __future__ import annotations

import argparse

import numpy as np

from nirspi_pipe.benchmarks import median_time_s
from nirspi_pipe.upscale.bicubic import bicubic
from nirspi_pipe.upscale.evaluate import score_heldout, summarise
from nirspi_pipe.upscale.fsrcnn import fsrcnn_forward, load_weights


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="nirspi-bench upscale", description=__doc__.split("\n\n")[0])
    parser.add_argument("--scales", type=int, nargs="+", default=[2, 3, 4], choices=[2, 3, 4])
    parser.add_argument("--noise", type=float, nargs="+", default=[0.0, 1e-3], help="source noise_rel levels")
    parser.add_argument("--size", type=int, default=64, help="low-res side for the timing")
    parser.add_argument("--repeat", type=int, default=7)
    parser.add_argument("--per-image", action="store_true", help="also print every held-out image")
    ns = parser.parse_args(argv)

    rows = []
    print(
        f"{'scale':>5} {'noise_rel':>9} {'n':>3} {'PSNR bicubic':>12} {'PSNR fsrcnn':>11} {'gain dB':>8} "
        f"{'SSIM bicubic':>12} {'SSIM fsrcnn':>11}"
    )
    for scale in ns.scales:
        weights = load_weights(scale)
        per = score_heldout(weights, tuple(ns.noise))
        rows += per
        for r in summarise(per):
            print(
                f"{f'x{scale}':>5} {r['noise_rel']:>9.0e} {r['images']:>3} {r['psnr_bicubic']:>12.2f} "
                f"{r['psnr_fsrcnn']:>11.2f} {r['gain_db']:>+8.2f} {r['ssim_bicubic']:>12.4f} {r['ssim_fsrcnn']:>11.4f}"
            )
    if ns.per_image:
        print()
        print(f"{'scale':>5} {'noise_rel':>9} {'image':>12} {'PSNR bic':>9} {'PSNR fsr':>9} {'gain':>7}")
        for r in rows:
            print(
                f"{'x' + str(r['scale']):>5} {r['noise_rel']:>9.0e} {r['image']:>12} {r['psnr_bicubic']:>9.2f} "
                f"{r['psnr_fsrcnn']:>9.2f} {r['gain_db']:>+7.2f}"
            )
    losers = sorted({(r["scale"], r["noise_rel"]) for r in summarise(rows) if r["gain_db"] <= 0})
    print(
        "fsrcnn beats bicubic in mean PSNR at every scale and noise level"
        if not losers
        else f"fsrcnn does NOT beat bicubic at (scale, noise_rel) {losers}"
    )

    print()
    print(f"{'scale':>5} {'size':>9} {'fsrcnn ms':>10} {'bicubic ms':>11} {'ratio':>7}")
    img = np.random.default_rng(0).uniform(0, 1, (ns.size, ns.size))
    for scale in ns.scales:
        weights = load_weights(scale)
        t_net = median_time_s(lambda: fsrcnn_forward(img, weights), ns.repeat)
        t_bic = median_time_s(lambda: bicubic(img, scale), ns.repeat)
        out = f"{ns.size}²→{ns.size * scale}²"
        print(f"{f'x{scale}':>5} {out:>9} {t_net * 1e3:>10.2f} {t_bic * 1e3:>11.2f} {t_net / t_bic:>7.1f}")
    return 0
