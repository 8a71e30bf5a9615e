"""``nirspi-orders``: draw every scan order as Fig. 2 of the paper does.

For each order, the top panel is the path of the first patterns over the sequency plane
(``u`` down, ``v`` across; DC at the top left), coloured by measurement rank; the bottom panel
is the first patterns themselves, in measurement order (white = +1, black = −1).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from nirspi_pipe.patterns.hadamard import is_power_of_two, pattern
from nirspi_pipe.patterns.orders import ORDERS, ScanOrderBase, Spiral, sequency_of_rows

__all__ = ["draw_orders", "main"]


def _orders() -> dict[str, ScanOrderBase]:
    out: dict[str, ScanOrderBase] = {name: cls() for name, cls in ORDERS.items()}
    out["spiral (centre)"] = Spiral(start="centre")
    return out


def draw_orders(path: str | Path, n: int = 8, n_patterns: int = 16, dpi: int = 120) -> Path:
    """Write a PNG grid of every order at side ``n`` (``n²`` patterns, 8 → the paper's
    ``H_64``), with the first ``n_patterns`` patterns shown below each path. Returns the path."""
    import matplotlib  # start-up: loads matplotlib and numpy (596 ms here)

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # start-up: loads matplotlib and numpy (1714 ms here)

    orders = _orders()
    seq = sequency_of_rows(n)
    cols = len(orders)
    strip = int(np.ceil(np.sqrt(n_patterns)))
    fig, axes = plt.subplots(2, cols, figsize=(2.2 * cols, 4.6), gridspec_kw={"height_ratios": [1, 1]})
    for ax_path, ax_pat, (name, order) in zip(axes[0], axes[1], orders.items()):
        k = order.order(n)
        u, v = seq[k // n], seq[k % n]
        rank = np.empty(n * n)
        rank[u * n + v] = np.arange(n * n)
        ax_path.imshow(rank.reshape(n, n), cmap="viridis", interpolation="nearest")
        ax_path.plot(v, u, "-", color="white", lw=1.0)
        ax_path.plot(v[0], u[0], "o", color="red", ms=4)
        dc = "DC first" if order.dc_first else "DC not first"
        ax_path.set_title(f"{name}\n({dc})", fontsize=8)
        ax_path.set_xticks([])
        ax_path.set_yticks([])
        mosaic = np.ones((strip * (n + 1) - 1, strip * (n + 1) - 1)) * 0.5
        for r, idx in enumerate(k[:n_patterns]):
            y0, x0 = (r // strip) * (n + 1), (r % strip) * (n + 1)
            mosaic[y0 : y0 + n, x0 : x0 + n] = (pattern(int(idx), n) + 1) / 2
        ax_pat.imshow(mosaic, cmap="gray", vmin=0, vmax=1, interpolation="nearest")
        ax_pat.set_title(f"first {n_patterns}", fontsize=7)
        ax_pat.axis("off")
    fig.suptitle(f"Scan orders over the {n}x{n} sequency plane (H_{n * n}); red dot = first pattern", fontsize=9)
    fig.tight_layout()
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=dpi)
    plt.close(fig)
    return out


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``nirspi-orders``."""
    parser = argparse.ArgumentParser(prog="nirspi-orders", description=__doc__)
    parser.add_argument("-o", "--output", default="orders.png", help="PNG file to write")
    parser.add_argument("-n", type=int, default=8, help="side of the pattern grid (power of two; 8 = H_64)")
    parser.add_argument("--patterns", type=int, default=16, help="first patterns shown per order")
    ns = parser.parse_args(argv)

    if not is_power_of_two(ns.n) or not 2 <= ns.n <= 64:
        parser.error(f"-n={ns.n} is not allowed; allowed: a power of two from 2 to 64")
    out = draw_orders(ns.output, ns.n, ns.patterns)
    print(f"nirspi-orders: {len(_orders())} orders -> {out}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
