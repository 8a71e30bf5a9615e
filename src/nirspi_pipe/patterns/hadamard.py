"""Fast Walsh–Hadamard transforms and the 2D Hadamard pattern basis.

Index convention (used everywhere in nirspi-pipe)
-------------------------------------------------
For an ``n × n`` image (``n = 2**k``) there are ``N = n²`` patterns. Pattern ``k`` is the outer
product ``P_k = h_i h_jᵀ`` of rows ``i`` and ``j`` of the Sylvester Hadamard matrix ``H_n``
(Eq. 3, natural order), with ``k = i·n + j``. A measurement is ``y_k = Σ P_k ⊙ O`` (Eq. 1 with
α = 1), so measuring every pattern is the 2D transform ``Y = H_n O H_n``. Because
``H_{n²} = H_n ⊗ H_n`` (Eq. 3), this equals the 1D transform of length ``N`` applied to the
image flattened in row-major order, which is what :func:`fwht` computes. ``H`` is symmetric and
``H H = N·I``, so the inverse is the same transform divided by ``N``.

No function here builds an ``N × N`` matrix: the transform is factored into Kronecker factors of
at most 64 × 64 (``H_{2^a} ⊗ H_{2^b} ⊗ …``), each applied as a small dense product, which runs
at BLAS speed in ``O(N log N)`` work.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

__all__ = [
    "is_power_of_two",
    "sylvester",
    "fwht",
    "ifwht",
    "fwht2",
    "ifwht2",
    "pattern",
    "pattern_rows",
]

#: Largest dense Kronecker factor, as log2 of its size. 2**6 = 64 keeps each factor in cache.
_MAX_FACTOR_BITS = 6


def is_power_of_two(n: int) -> bool:
    """Return True when ``n`` is a positive integer power of two (1, 2, 4, …)."""
    return isinstance(n, (int, np.integer)) and n > 0 and (n & (n - 1)) == 0


@lru_cache(maxsize=16)
def _sylvester_cached(n: int) -> np.ndarray:
    h = np.ones((1, 1))
    while h.shape[0] < n:
        h = np.block([[h, h], [h, -h]])  # Eq. (3), Sylvester construction
    h.setflags(write=False)
    return h


def sylvester(n: int) -> np.ndarray:
    """Sylvester Hadamard matrix ``H_n`` in natural order (Eq. 3), entries ±1 (dimensionless).

    Only meant for small ``n`` (it is dense ``n × n``): the 1D factor of a 2D basis, or tests.

    >>> sylvester(2).tolist()
    [[1.0, 1.0], [1.0, -1.0]]
    """
    if not is_power_of_two(n):
        raise ValueError(f"Hadamard order must be a power of two, got {n}")
    return _sylvester_cached(int(n))


def _factor_bits(bits: int) -> list[int]:
    """Split ``bits`` into near-equal chunks of at most ``_MAX_FACTOR_BITS``."""
    if bits == 0:
        return []
    parts = -(-bits // _MAX_FACTOR_BITS)
    base, extra = divmod(bits, parts)
    return [base + 1] * extra + [base] * (parts - extra)


def fwht(x: np.ndarray, axis: int = -1) -> np.ndarray:
    """Unnormalised fast Walsh–Hadamard transform along ``axis`` (natural/Sylvester order).

    Computes ``H_N x`` for each 1D slice of length ``N = 2**k`` along ``axis``, without forming
    ``H_N``. Units are those of ``x`` (sums of ``x``). Applying it twice multiplies by ``N``.

    >>> fwht(np.array([1.0, 0.0, 0.0, 0.0])).tolist()
    [1.0, 1.0, 1.0, 1.0]
    """
    x = np.asarray(x)
    if not np.issubdtype(x.dtype, np.floating):
        x = x.astype(np.float64)
    n = x.shape[axis]
    if not is_power_of_two(n):
        raise ValueError(f"fwht length must be a power of two, got {n}")
    moved = np.moveaxis(x, axis, -1)
    batch_shape = moved.shape[:-1]
    out = np.ascontiguousarray(moved).reshape(-1, n)
    batch = out.shape[0]
    bits = n.bit_length() - 1
    # Index bits are split high→low into factors; factor f acts on its own bit group:
    # H_N = H_{2^b1} ⊗ H_{2^b2} ⊗ … (Eq. 3 applied repeatedly).
    pre = 1
    for b in _factor_bits(bits):
        size = 1 << b
        post = n // (pre * size)
        h = _sylvester_cached(size).astype(out.dtype, copy=False)
        view = out.reshape(batch * pre, size, post)
        if post == 1:
            out = (view[:, :, 0] @ h).reshape(batch, n)  # h is symmetric
        else:
            out = np.matmul(h, view).reshape(batch, n)
        pre *= size
    out = out.reshape(*batch_shape, n)
    return np.moveaxis(out, -1, axis)


def ifwht(y: np.ndarray, axis: int = -1) -> np.ndarray:
    """Inverse of :func:`fwht`: ``H_N y / N`` (same units as the original signal)."""
    y = np.asarray(y)
    return fwht(y, axis=axis) / y.shape[axis]


def fwht2(image: np.ndarray) -> np.ndarray:
    """2D Hadamard coefficients ``H_n O H_n`` of an ``n × n`` image (Eq. 1 for every pattern).

    Returns an ``n × n`` array whose entry ``[i, j]`` is the measurement of pattern
    ``k = i·n + j`` (units: image units × pixels).
    """
    image = np.asarray(image)
    if image.ndim < 2 or image.shape[-1] != image.shape[-2]:
        raise ValueError(f"fwht2 expects square images, got shape {image.shape}")
    n = image.shape[-1]
    if not is_power_of_two(n):
        raise ValueError(f"fwht2 side must be a power of two, got {n}")
    if n <= 1 << _MAX_FACTOR_BITS:
        # Small images: the two dense products H O H are cheaper than reshaping (Eq. 1 for all k).
        if not np.issubdtype(image.dtype, np.floating):
            image = image.astype(np.float64)
        h = _sylvester_cached(n).astype(image.dtype, copy=False)
        return h @ image @ h
    flat = image.reshape(*image.shape[:-2], n * n)
    return fwht(flat, axis=-1).reshape(image.shape)


def ifwht2(coefficients: np.ndarray) -> np.ndarray:
    """Inverse of :func:`fwht2`: the image from its full set of 2D Hadamard coefficients."""
    coefficients = np.asarray(coefficients)
    n = coefficients.shape[-1]
    return fwht2(coefficients) / (n * n)


def pattern_rows(index: np.ndarray | int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Split flat pattern indices ``k`` into the 1D Hadamard row indices ``(i, j)``, ``k = i·n + j``."""
    k = np.asarray(index)
    return k // n, k % n


def pattern(index: int, n: int) -> np.ndarray:
    """The ±1 pattern ``P_k = h_i h_jᵀ`` (``n × n``, dimensionless) for flat index ``k``."""
    if not 0 <= index < n * n:
        raise ValueError(f"pattern index {index} out of range [0, {n * n})")
    h = sylvester(n)
    i, j = pattern_rows(index, n)
    return np.outer(h[i], h[j])
