"""Scan orders: permutations of the ``n²`` Hadamard pattern indices.

An order is a permutation of the flat indices ``k = i·n + j`` (natural Sylvester rows ``i`` and
``j``, see :mod:`nirspi_pipe.patterns.hadamard`). ``ratio`` keeps the first ``round(ratio·n²)``
of them (at least one). Orders are computed in ``O(N log N)`` or better; none builds an
``N × N`` matrix.

The sequency plane
------------------
Most orders are defined over the 2D *sequency plane*: pattern ``h_i h_jᵀ`` sits at ``(u, v)``
where ``u`` and ``v`` are the sequencies (numbers of sign changes) of rows ``i`` and ``j``. DC is
at ``(0, 0)``; ``u`` grows with vertical detail, ``v`` with horizontal detail. The natural →
sequency map is the classical Gray-code / bit-reversal relation (:func:`sequency_of_rows`),
``O(n log n)``; an order over the plane is then mapped back to natural flat indices.

The paper's Fig. 2 draws Basic, Hilbert, Zig-Zag and Spiral curves over the ``H_64`` grid (8 × 8
patterns); see ``docs/reconstruction.md`` for how each is read here.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from typing import Annotated

import numpy as np

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.patterns.hadamard import fwht2, is_power_of_two
from nirspi_pipe.ranges import OneOf, Range, check_ranges
from nirspi_pipe.scene.objects import load_gray_image

__all__ = [
    "ScanOrderBase",
    "Basic",
    "Sequency",
    "Hilbert",
    "Zigzag",
    "Spiral",
    "CakeCutting",
    "RussianDoll",
    "Random",
    "Variance",
    "ORDERS",
    "n_selected",
    "sequency_of_rows",
    "rows_of_sequency",
    "sequency_plane",
    "from_plane",
    "hilbert_d2xy",
    "block_counts",
    "DEFAULT_TRAINING",
]


def n_selected(ratio: float, n_patterns: int) -> int:
    """Number of patterns measured at sampling ``ratio`` out of ``n_patterns`` (at least 1)."""
    return max(1, min(n_patterns, int(round(float(ratio) * n_patterns))))


def _check_n(n: int) -> int:
    if not is_power_of_two(n):
        raise ValueError(f"scan orders need a power-of-two side, got {n}")
    return int(n)


def _bit_reverse(x: np.ndarray, bits: int) -> np.ndarray:
    out = np.zeros_like(x)
    for b in range(bits):
        out |= ((x >> b) & 1) << (bits - 1 - b)
    return out


def _gray_inverse(g: np.ndarray, bits: int) -> np.ndarray:
    out = g.copy()
    shift = 1
    while shift < max(bits, 1):
        out ^= out >> shift
        shift <<= 1
    return out


def sequency_of_rows(n: int) -> np.ndarray:
    """Sequency (number of sign changes, 0 … n−1) of each natural Sylvester row of ``H_n``.

    Row ``i`` of the natural ``H_n`` is the Walsh function of sequency
    ``s = gray⁻¹(bitreverse(i))`` (the classical natural ↔ Walsh relation). ``O(n log n)``.

    >>> sequency_of_rows(4).tolist()
    [0, 3, 1, 2]
    """
    n = _check_n(n)
    bits = n.bit_length() - 1
    i = np.arange(n, dtype=np.int64)
    return _gray_inverse(_bit_reverse(i, bits), bits)


def rows_of_sequency(n: int) -> np.ndarray:
    """Inverse of :func:`sequency_of_rows`: the natural row index of each sequency 0 … n−1."""
    seq = sequency_of_rows(n)
    rows = np.empty_like(seq)
    rows[seq] = np.arange(n, dtype=np.int64)
    return rows


def sequency_plane(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Sequency coordinates ``(u, v)`` of every natural flat index ``k = i·n + j`` (each ``(N,)``)."""
    seq = sequency_of_rows(n)
    k = np.arange(n * n, dtype=np.int64)
    return seq[k // n], seq[k % n]


def from_plane(n: int, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Natural flat indices of the patterns at sequency coordinates ``(u, v)``."""
    rows = rows_of_sequency(n)
    return rows[np.asarray(u, dtype=np.int64)] * n + rows[np.asarray(v, dtype=np.int64)]


def hilbert_d2xy(n: int, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cells ``(x, y)`` of the Hilbert curve over an ``n × n`` grid at curve positions ``d``.

    Vectorised form of the classical iterative construction; the curve starts at ``(0, 0)`` and
    ends at ``(n − 1, 0)``. ``O(N log n)`` for all ``N = n²`` positions.
    """
    n = _check_n(n)
    t = np.asarray(d, dtype=np.int64).copy()
    x = np.zeros_like(t)
    y = np.zeros_like(t)
    s = 1
    while s < n:
        rx = 1 & (t // 2)
        ry = 1 & (t ^ rx)
        # rotate the quadrant
        flip = (ry == 0) & (rx == 1)
        x = np.where(flip, s - 1 - x, x)
        y = np.where(flip, s - 1 - y, y)
        swap = ry == 0
        x, y = np.where(swap, y, x), np.where(swap, x, y)
        x = x + s * rx
        y = y + s * ry
        t //= 4
        s *= 2
    return x, y


@dataclass(frozen=True)
class ScanOrderBase:
    """Common part of all scan orders: the sampling ratio and truncation.

    Attributes:
        ratio: fraction of the ``n²`` patterns measured, in (0, 1].
    """

    ratio: Annotated[float, Range(0.0, 1.0, "a fraction", lo_open=True)] = 1.0

    #: Whether ``order(n)[0]`` is always the DC (all-ones) pattern, index 0.
    dc_first = True

    def __post_init__(self) -> None:
        check_ranges(self)

    def order(self, n: int) -> np.ndarray:
        """The full permutation of ``n²`` flat pattern indices (int64)."""
        raise NotImplementedError

    def select(self, n: int) -> np.ndarray:
        """The first ``round(ratio · n²)`` indices of :meth:`order` (at least one)."""
        full = self.order(n)
        return full[: n_selected(self.ratio, full.size)]


def _plane_order(n: int, *keys_last_primary: np.ndarray) -> np.ndarray:
    """Natural flat indices sorted by keys over the sequency plane (last key primary, like
    ``np.lexsort``); keys are arrays over plane cells ``c = u·n + v``."""
    cells = np.lexsort(keys_last_primary)
    return from_plane(n, cells // n, cells % n)


def _plane_coords(n: int) -> tuple[np.ndarray, np.ndarray]:
    c = np.arange(n * n, dtype=np.int64)
    return c // n, c % n


@dataclass(frozen=True)
class Basic(ScanOrderBase):
    """The paper's *Basic* order (Fig. 2a): natural Sylvester order, ``k = 0, 1, …, n² − 1``."""

    def order(self, n: int) -> np.ndarray:
        return np.arange(n * n, dtype=np.int64)


@dataclass(frozen=True)
class Sequency(ScanOrderBase):
    """Order ``sequency``: ascending total sequency ``u + v`` (sign changes down a column plus
    along a row); ties by ``max(u, v)`` (more isotropic first), then ``u``."""

    def order(self, n: int) -> np.ndarray:
        u, v = _plane_coords(_check_n(n))
        return _plane_order(n, u, np.maximum(u, v), u + v)


@dataclass(frozen=True)
class Hilbert(ScanOrderBase):
    """The paper's *Hilbert* order (Fig. 2b, ref. 22): the Hilbert curve over the sequency
    plane, starting at DC ``(0, 0)``. Neighbouring patterns in time have neighbouring
    sequencies, and every prefix of length ``4^l`` is a compact ``2^l × 2^l`` block."""

    def order(self, n: int) -> np.ndarray:
        n = _check_n(n)
        x, y = hilbert_d2xy(n, np.arange(n * n, dtype=np.int64))
        return from_plane(n, y, x)


@dataclass(frozen=True)
class Zigzag(ScanOrderBase):
    """The paper's *Zig-Zag* order (Fig. 2c, ref. 23): the JPEG zig-zag over the sequency plane,
    anti-diagonals ``u + v = s`` in turn, alternating direction."""

    def order(self, n: int) -> np.ndarray:
        u, v = _plane_coords(_check_n(n))
        s = u + v
        along = np.where(s % 2 == 0, -u, u)  # even diagonals climb (u falls), odd ones descend
        return _plane_order(n, along, s)


@dataclass(frozen=True)
class Spiral(ScanOrderBase):
    """The paper's *Spiral* order (Fig. 2d, ref. 24).

    Attributes:
        start: ``corner`` (default): a square spiral about DC. Walsh spectra have no negative
            sequencies, so a spiral about DC folds into the quadrant as L-shaped shells
            ``max(u, v) = r``, walked alternately out and back (a continuous path); DC first.
            ``centre``: a square spiral from the centre of the sequency plane outwards, the
            literal reading of a centre-out spiral drawn over the pattern grid; DC is not first
            (it is reached in the last shell).
    """

    start: Annotated[str, OneOf(("corner", "centre"))] = "corner"

    @property
    def dc_first(self) -> bool:  # type: ignore[override]
        return self.start == "corner"

    def order(self, n: int) -> np.ndarray:
        u, v = _plane_coords(_check_n(n))
        if self.start == "corner":
            r = np.maximum(u, v)
            t = np.where(u == r, v, 2 * r - u)  # along the L: (r,0)→(r,r)→(0,r)
            along = np.where(r % 2 == 0, t, -t)
            return _plane_order(n, along, r)
        c = (n - 1) / 2.0
        du, dv = u - c, v - c
        ring = np.maximum(np.abs(du), np.abs(dv))
        angle = np.arctan2(du, dv)  # clockwise on screen (u grows downwards)
        return _plane_order(n, angle, ring)


def block_counts(n: int) -> np.ndarray:
    """Connected regions of each pattern ``h_i h_jᵀ`` by natural flat index, ``(N,)`` int64.

    A row of sequency ``s`` has ``s + 1`` constant runs, and in the outer product adjacent runs
    differ in sign, so the pattern has ``(s_i + 1)(s_j + 1)`` blocks (4-connectivity). ``O(N)``.
    """
    u, v = sequency_plane(n)
    return (u + 1) * (v + 1)


@dataclass(frozen=True)
class CakeCutting(ScanOrderBase):
    """Order ``cake_cutting`` (Yu 2019): ascending number of connected regions ("cake
    pieces") of each pattern, ties kept in natural order (a stable sort), as in the paper."""

    def order(self, n: int) -> np.ndarray:
        return np.argsort(block_counts(_check_n(n)), kind="stable").astype(np.int64)


@dataclass(frozen=True)
class RussianDoll(ScanOrderBase):
    """Order ``russian_doll`` (Sun et al. 2017): nested sub-Hadamard bases.

    A row of ``H_n`` is an up-sampled row of ``H_{2^l}`` exactly when its sequency is below
    ``2^l``. Doll ``l`` holds the patterns whose two rows both are; so after ``4^l``
    measurements the acquisition is a *complete* ``2^l × 2^l`` Hadamard basis and the fast
    inverse gives the exact image at that resolution. Within a doll, patterns go by ascending
    total sequency ``u + v`` (then ``u``).
    """

    def order(self, n: int) -> np.ndarray:
        u, v = _plane_coords(_check_n(n))
        level = np.maximum(_bit_length(u), _bit_length(v))
        return _plane_order(n, u, u + v, level)


def _bit_length(x: np.ndarray) -> np.ndarray:
    out = np.zeros_like(x)
    y = x.copy()
    while np.any(y):
        out += y > 0
        y >>= 1
    return out


@dataclass(frozen=True)
class Random(ScanOrderBase):
    """Order ``random``: a uniformly random permutation from ``numpy.random.default_rng(seed)``.

    Attributes:
        seed: integer seed (the same seed gives the same order at every ``n``).
        pin_dc: put DC first; by default it is not (DC is wherever the permutation puts it,
            so at low ratios the image mean is often unmeasured).
    """

    seed: Annotated[int, Range(0, None, "an integer", integer=True)] = 0
    pin_dc: bool = False

    @property
    def dc_first(self) -> bool:  # type: ignore[override]
        return bool(self.pin_dc)

    def order(self, n: int) -> np.ndarray:
        n = _check_n(n)
        perm = np.random.default_rng(int(self.seed)).permutation(n * n).astype(np.int64)
        return _pin_dc(perm) if self.pin_dc else perm


def _pin_dc(perm: np.ndarray) -> np.ndarray:
    return np.concatenate([[0], perm[perm != 0]]).astype(np.int64)


#: Default training set of ``Variance``: scikit-image samples shipped with the package (no
#: network), excluding ``camera`` and ``astronaut``, which are test scenes.
DEFAULT_TRAINING = (
    "skimage:coins",
    "skimage:moon",
    "skimage:text",
    "skimage:page",
    "skimage:clock",
    "skimage:chelsea",
    "skimage:coffee",
    "skimage:rocket",
    "skimage:brick",
    "skimage:gravel",
)


@lru_cache(maxsize=32)
def _coefficient_variance(n: int, images: tuple[str, ...]) -> np.ndarray:
    """Variance over the training images of each 2D Hadamard coefficient (natural flat index),
    images centre-cropped to a square and resized to ``n × n`` (values in [0, 1])."""
    from skimage.transform import resize  # start-up: loads scipy, charset_normalizer, lazy_loader (419 ms here)

    coeffs = []
    for path in images:
        img = load_gray_image(path)
        h, w = img.shape
        s = min(h, w)
        top, left = (h - s) // 2, (w - s) // 2
        square = img[top : top + s, left : left + s]
        small = resize(square, (n, n), anti_aliasing=True, mode="reflect")
        coeffs.append(fwht2(small).ravel())
    return np.var(np.stack(coeffs), axis=0)


@dataclass(frozen=True)
class Variance(ScanOrderBase):
    """Order ``variance``: coefficients ranked by decreasing variance over training images.

    The variance of a coefficient over a set of natural images is the energy a pattern
    measures beyond what the set has in common; for a linear reconstruction from the first
    ``m`` patterns it is the order that minimises the expected error over that set (a
    Karhunen–Loève argument restricted to the Hadamard basis). Cost ``O(T · N log N)`` for
    ``T`` training images, cached per ``n``.

    Attributes:
        images: training images (files or ``skimage:<name>``); default: ten scikit-image
            samples that ship with the package (not ``camera``/``astronaut``, the test scenes).
        pin_dc: put DC first (default). DC carries the image mean; its variance over a set can
            be smaller than that of coarse patterns, so unpinned it may come later.
    """

    images: tuple[str, ...] = field(default=DEFAULT_TRAINING)
    pin_dc: bool = True

    def __post_init__(self) -> None:
        super().__post_init__()
        if isinstance(self.images, str) or not len(self.images):
            raise ConfigError("images", self.images, "a non-empty list of image files or skimage:<name>")
        object.__setattr__(self, "images", tuple(str(p) for p in self.images))

    @property
    def dc_first(self) -> bool:  # type: ignore[override]
        return bool(self.pin_dc)

    def order(self, n: int) -> np.ndarray:
        var = _coefficient_variance(_check_n(n), self.images)
        perm = np.argsort(-var, kind="stable").astype(np.int64)
        return _pin_dc(perm) if self.pin_dc else perm


#: Every order by its config name (``scan=<name>``).
ORDERS: dict[str, type[ScanOrderBase]] = {
    "basic": Basic,
    "sequency": Sequency,
    "hilbert": Hilbert,
    "zigzag": Zigzag,
    "spiral": Spiral,
    "cake_cutting": CakeCutting,
    "russian_doll": RussianDoll,
    "random": Random,
    "variance": Variance,
}
