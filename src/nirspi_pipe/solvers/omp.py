"""Solver ``omp``: orthogonal matching pursuit in a sparsifying basis (the paper's OMP-GPU, ref. 27).

Model
-----
The image ``X`` (``n × n``) is sparse in an orthonormal 2D basis: ``S = B X Bᵀ`` with ``B`` an
``n × n`` orthonormal matrix (the orthonormal DCT-II, or the orthonormal Haar matrix, applied
along both axes). The Hadamard measurements are ``Y = H X H = M S Mᵀ`` with ``M = H Bᵀ``
(``n × n``), sampled at the measured ``(i, j)``. So atom ``p = (a, b)`` (coefficient ``S[a, b]``)
has the column ``A[k, p] = M[i_k, a] · M[j_k, b]`` (``O(m)`` to build) and the correlation of a
residual with every atom is ``G = Mᵀ R M`` (``R``: the residual scattered on the ``n × n``
Hadamard grid), two ``n × n`` products, ``O(n³) = O(N^{3/2})``. No ``N × N`` (nor ``m × N``)
matrix is ever formed.

Algorithm (Pati et al. 1993): repeat — pick the atom whose normalised correlation with the
residual is largest; orthogonalise its column against the chosen ones (classical Gram–Schmidt,
twice: CGS2); remove it from the residual — until ``‖r‖ ≤ tol·‖y‖``, ``max_atoms`` atoms, or
no atom is left. Then ``R s = Qᵀ y`` (triangular) gives the coefficients on the support.

Ties (symmetric scenes have exactly equal correlations) are broken deterministically: among
the atoms within a relative ``1e-9`` of the best score, the lowest index wins. This is what
makes the ``numpy`` and ``opencl`` back ends, whose sums round differently, pick the same atoms
and agree to ``1e-5``.

Back ends: ``numpy`` (the reference) and ``opencl`` (:mod:`nirspi_pipe.solvers.omp_opencl`,
pyopencl, float64; PoCL on the CPU here), which runs the correlation ``Mᵀ R M`` and the
Gram–Schmidt products in OpenCL kernels. The selection rule, the bookkeeping and the final
triangular solve are shared host code.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache
from typing import Protocol

import numpy as np
from scipy.linalg import solve_triangular

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.patterns.hadamard import sylvester
from nirspi_pipe.solvers.common import checked_coefficients, require_hadamard
from nirspi_pipe.types import Acquisition, Image2D

__all__ = ["OMPSolver", "basis_matrix", "haar_matrix", "dct_matrix", "omp_hadamard", "TIE_RTOL"]

#: Relative window within which correlation scores count as tied (lowest atom index wins).
TIE_RTOL = 1e-9


@lru_cache(maxsize=16)
def dct_matrix(n: int) -> np.ndarray:
    """Orthonormal DCT-II matrix ``C`` (``n × n``): ``C x = scipy.fft.dct(x, norm='ortho')``."""
    from scipy.fft import dct

    c = dct(np.eye(n), norm="ortho", axis=0)
    c.setflags(write=False)
    return c


@lru_cache(maxsize=16)
def haar_matrix(n: int) -> np.ndarray:
    """Orthonormal Haar matrix ``W`` (``n × n``, ``n`` a power of two): row 0 the scaling
    function, then the wavelets from coarse to fine. ``W Wᵀ = I``."""
    w = np.ones((1, 1))
    while w.shape[0] < n:
        k = w.shape[0]
        top = np.kron(w, [1.0, 1.0])
        bottom = np.kron(np.eye(k), [1.0, -1.0])
        w = np.vstack([top, bottom]) / np.sqrt(2.0)
    w.setflags(write=False)
    return w


def basis_matrix(name: str, n: int) -> np.ndarray:
    """The ``n × n`` orthonormal analysis matrix ``B`` of basis ``name`` (``dct`` or ``haar``)."""
    if name == "dct":
        return dct_matrix(n)
    if name == "haar":
        return haar_matrix(n)
    raise ValueError(f"unknown basis {name!r}")


class OmpBackend(Protocol):
    """The two heavy steps of OMP; the host code drives them."""

    def correlate(self, residual: np.ndarray) -> np.ndarray:
        """``Mᵀ R M`` raveled (``(N,)``), ``R`` the residual scattered on the measured cells."""

    def orthogonalize(self, column: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        """CGS2 of ``column`` against the first ``k`` stored unit vectors: ``(q, Qᵀ column)``."""

    def store(self, q: np.ndarray, k: int) -> None:
        """Store unit vector ``q`` as the ``k``-th basis vector."""


class NumpyOmpBackend:
    """Reference back end: numpy matrix products."""

    def __init__(self, m_mat: np.ndarray, rows: np.ndarray, cols: np.ndarray, k_max: int) -> None:
        self.m, self.rows, self.cols = m_mat, rows, cols
        self.n = m_mat.shape[0]
        self.q = np.zeros((k_max, rows.size))

    def correlate(self, residual: np.ndarray) -> np.ndarray:
        r = np.zeros((self.n, self.n))
        r[self.rows, self.cols] = residual
        return (self.m.T @ r @ self.m).ravel()

    def orthogonalize(self, column: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
        if k == 0:
            return column.copy(), np.zeros(0)
        qk = self.q[:k]
        c1 = qk @ column
        q = column - qk.T @ c1
        c2 = qk @ q
        q -= qk.T @ c2
        return q, c1 + c2

    def store(self, q: np.ndarray, k: int) -> None:
        self.q[k] = q


def pick_atom(score: np.ndarray) -> int:
    """Index of the best score with the deterministic tie rule (lowest index within
    :data:`TIE_RTOL`); −1 when no score is positive."""
    best = float(score.max())
    if not best > 0.0:
        return -1
    return int(np.flatnonzero(score >= best * (1.0 - TIE_RTOL))[0])


def omp_hadamard(
    y: np.ndarray,
    n: int,
    indices: np.ndarray,
    basis: str = "dct",
    max_atoms: int = 1000,
    tol: float = 1e-6,
    backend: str = "numpy",
    normalize: bool = False,
) -> tuple[np.ndarray, dict]:
    """OMP for Hadamard measurements ``y`` at flat ``indices``; returns ``(image, info)``.

    ``image`` is ``n × n`` in the units of ``y`` per pixel (relative radiance for calibrated
    coefficients); ``info`` has ``iterations`` (atoms chosen), ``stop_reason``,
    ``relative_residual`` and ``backend``.
    """
    idx = np.asarray(indices, dtype=np.int64)
    rows, cols = idx // n, idx % n
    b = basis_matrix(basis, n)
    m_mat = np.ascontiguousarray(sylvester(n) @ b.T)  # M = H Bᵀ
    size, m = n * n, idx.size
    k_max = int(max(0, min(max_atoms, m, size)))
    ny = float(np.linalg.norm(y))
    info: dict = {"backend": backend, "basis": basis}
    if ny == 0.0 or k_max == 0:
        info.update(iterations=0, stop_reason="zero_measurements" if ny == 0.0 else "max_atoms",
                    relative_residual=0.0 if ny == 0.0 else 1.0)
        return np.zeros((n, n)), info

    m2 = m_mat * m_mat
    colnorm = np.sqrt(np.maximum((m2[rows].T @ m2[cols]).ravel(), 0.0))  # ‖A[:, p]‖
    usable = colnorm > 1e-12 * float(colnorm.max())
    if normalize:
        inv_norm = np.where(usable, 1.0 / np.where(usable, colnorm, 1.0), 0.0)
    else:
        inv_norm = np.ones_like(colnorm)

    engine: OmpBackend
    if backend == "numpy":
        engine = NumpyOmpBackend(m_mat, rows, cols, k_max)
    else:
        from nirspi_pipe.solvers.omp_opencl import OpenCLOmpBackend

        engine = OpenCLOmpBackend(m_mat, rows, cols, k_max)

    r = y.astype(np.float64).copy()
    tri = np.zeros((k_max, k_max))
    qty = np.zeros(k_max)
    support: list[int] = []
    stop = "max_atoms"
    k = 0
    while k < k_max:
        score = np.abs(engine.correlate(r)) * inv_norm
        score[~usable] = -1.0
        p = pick_atom(score)
        if p < 0:
            stop = "exhausted"
            break
        a_idx, b_idx = divmod(p, n)
        column = m_mat[rows, a_idx] * m_mat[cols, b_idx]
        q, c = engine.orthogonalize(column, k)
        nq = float(np.linalg.norm(q))
        usable[p] = False
        if nq <= 1e-10 * float(np.linalg.norm(column)):
            continue  # linearly dependent on the support: skip the atom
        q /= nq
        engine.store(q, k)
        tri[:k, k] = c
        tri[k, k] = nq
        qty[k] = float(q @ y)
        r -= float(q @ r) * q
        support.append(p)
        k += 1
        if float(np.linalg.norm(r)) <= tol * ny:
            stop = "residual_tol"
            break
    coeffs = np.zeros(size)
    if k:
        coeffs[np.asarray(support)] = solve_triangular(tri[:k, :k], qty[:k])
    s = coeffs.reshape(n, n)
    image = b.T @ s @ b  # X = Bᵀ S B
    info.update(iterations=k, stop_reason=stop, relative_residual=float(np.linalg.norm(r)) / ny)
    return image, info


@dataclass(frozen=True)
class OMPSolver:
    """Solver ``omp``: orthogonal matching pursuit in a DCT or Haar basis (see module doc).

    Attributes:
        basis: ``dct`` (orthonormal DCT-II) or ``haar`` (orthonormal separable Haar).
        sparsity: atoms at most, as a fraction of the measurements ``m`` (0, 1].
        max_atoms: hard cap on atoms (cost grows as ``atoms · (n³ + m · atoms)``); null = none.
        tol: stop when ``‖r‖ ≤ tol · ‖y‖``.
        backend: ``numpy`` (reference) or ``opencl`` (pyopencl, float64).
    """

    basis: str = "dct"
    sparsity: float = 0.25
    max_atoms: int | None = 1000
    tol: float = 1e-6
    backend: str = "numpy"
    normalize: bool = False

    def __post_init__(self) -> None:
        if self.basis not in ("dct", "haar"):
            raise ConfigError("basis", self.basis, "dct or haar")
        if not (0.0 < float(self.sparsity) <= 1.0):
            raise ConfigError("sparsity", self.sparsity, "a fraction of the measurements in (0, 1]")
        if self.max_atoms is not None and (not isinstance(self.max_atoms, (int, np.integer)) or self.max_atoms < 1):
            raise ConfigError("max_atoms", self.max_atoms, "an integer >= 1, or null")
        if not (np.isfinite(self.tol) and 0 <= self.tol < 1):
            raise ConfigError("tol", self.tol, "a relative tolerance in [0, 1)")
        if self.backend not in ("numpy", "opencl"):
            raise ConfigError("backend", self.backend, "numpy or opencl")

    def atoms(self, m: int) -> int:
        """Atom budget for ``m`` measurements."""
        k = int(math.ceil(float(self.sparsity) * m))
        return k if self.max_atoms is None else min(k, int(self.max_atoms))

    def solve(self, acquisition: Acquisition) -> Image2D:
        require_hadamard(acquisition, "omp")
        y = checked_coefficients(acquisition, "omp")
        image, info = omp_hadamard(
            y,
            acquisition.n,
            acquisition.indices,
            basis=self.basis,
            max_atoms=self.atoms(len(y)),
            tol=float(self.tol),
            backend=self.backend,
            normalize=bool(self.normalize),
        )
        return Image2D(image, info=info)
