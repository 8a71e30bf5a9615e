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
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from typing import Any, Protocol, TypeVar

import numpy as np
from scipy.linalg.blas import dtpmv

from nirspi_pipe.errors import ConfigError
from nirspi_pipe.patterns.hadamard import sylvester
from nirspi_pipe.solvers.common import checked_coefficients
from nirspi_pipe.types import Acquisition, Image2D

__all__ = ["OMPSolver", "basis_matrix", "haar_matrix", "dct_matrix", "omp_hadamard", "TIE_RTOL"]

#: Relative window within which correlation scores count as tied (lowest atom index wins).
TIE_RTOL = 1e-9
#: Support columns kept for the residual while they fit in this many bytes (assumed: a typical
#: 2 MiB per-core L2 cache; beyond it the memory-bound product loses to the in-cache transform,
#: measured with ``nirspi-bench omp``: 64² 0.92× the reference with columns, 1.24× without).
COLUMN_CACHE_BYTES = 2 << 20


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
    """The transforms OMP needs; the host code (Cholesky updates, selection) drives them."""

    def correlate(self, residual: np.ndarray) -> np.ndarray:
        """``Aᵀ r`` raveled (``(N,)``): ``Mᵀ R M``, ``R`` the residual scattered on the measured cells."""

    def gram(self, column: np.ndarray, support: np.ndarray) -> np.ndarray:
        """``(Aᵀ a)[support]``: the correlations of ``column`` with the support's atoms."""

    def synthesize(self, coeffs: np.ndarray) -> np.ndarray:
        """``A s`` (``(m,)``): ``(M S Mᵀ)`` at the measured cells, ``S`` the ``n × n`` coefficients."""


class NumpyOmpBackend:
    """Reference back end: the separable transform ``M = H Bᵀ`` as matrix products, restricted to
    the Hadamard rows ``U`` and columns ``V`` that hold a measurement (``R`` is zero elsewhere; a
    low-sequency order at 25 % uses about 70 % of each), and a product whose result is needed
    only at some cells is done once and finished per cell."""

    def __init__(self, m_mat: np.ndarray, rows: np.ndarray, cols: np.ndarray, k_max: int) -> None:
        self.n = m_mat.shape[0]
        used_rows, self.rows = np.unique(rows, return_inverse=True)
        used_cols, self.cols = np.unique(cols, return_inverse=True)
        self.mu_t = np.ascontiguousarray(m_mat[used_rows].T)  # (n, |U|)
        self.mu = np.ascontiguousarray(m_mat[used_rows])  # (|U|, n)
        self.mv = np.ascontiguousarray(m_mat[used_cols])  # (|V|, n)
        self.mv_t = np.ascontiguousarray(self.mv.T)  # (n, |V|)
        self.grid = np.zeros((used_rows.size, used_cols.size))
        #: multiply–adds of one synthesis (two products), for omp_core's choice of residual route
        self.synth_cost = float(self.n * self.n * (used_rows.size + used_cols.size))

    def _scatter_left(self, values: np.ndarray) -> np.ndarray:
        """``Mᵀ R`` (``(n, |V|)``) for ``R`` the values scattered on the measured cells."""
        self.grid[self.rows, self.cols] = values
        out = self.mu_t @ self.grid
        self.grid[self.rows, self.cols] = 0.0
        return out

    def correlate(self, residual: np.ndarray) -> np.ndarray:
        return (self._scatter_left(residual) @ self.mv).ravel()

    def gram(self, column: np.ndarray, support: np.ndarray) -> np.ndarray:
        t = self._scatter_left(column)
        a_idx, b_idx = np.divmod(support, self.n)
        return np.einsum("ij,ij->i", t[a_idx], self.mv_t[b_idx])

    def synthesize(self, coeffs: np.ndarray) -> np.ndarray:
        return (self.mu @ coeffs.reshape(self.n, self.n) @ self.mv_t)[self.rows, self.cols]  # (M S Mᵀ)[i_k, j_k]


def pick_atom(score: np.ndarray) -> int:
    """Index of the best score with the deterministic tie rule (lowest index within
    :data:`TIE_RTOL`); −1 when no score is positive."""
    best = float(score.max())
    if not best > 0.0:
        return -1
    return int(np.flatnonzero(score >= best * (1.0 - TIE_RTOL))[0])


T = TypeVar("T")


def _one_blas_thread(fn: Callable[..., T]) -> Callable[..., T]:
    """Run ``fn`` with one BLAS thread. Every product of the OMP loop is small (a few million
    multiply-adds), and on the project's 2-core machines OpenBLAS's second thread made the loop
    11x slower (128² at 25 %: 14.6 s against 1.3 s, an in-process solve with and without
    OPENBLAS_NUM_THREADS=1; ``nirspi-bench omp`` times it)."""
    import functools

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> T:
        from threadpoolctl import threadpool_limits

        with threadpool_limits(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

    return wrapper


@_one_blas_thread
def omp_core(
    y: np.ndarray,
    engine: OmpBackend,
    column: Callable[[int], np.ndarray],
    colnorm: np.ndarray,
    k_max: int,
    tol: float,
    normalize: bool,
) -> tuple[np.ndarray, int, str, float]:
    """OMP with an incremental Cholesky factor of the support's Gram matrix ``A_SᵀA_S = L Lᵀ``,
    kept as its inverse ``L⁻¹`` (lower triangular; adding an atom appends a row and leaves the
    others unchanged).

    Per atom: the Gram column ``A_Sᵀ a_p`` by the transform, ``w = L⁻¹ A_Sᵀa_p`` and the new row of
    ``L⁻¹`` (two matrix–vector products, ``O(k²)``), ``z = L⁻¹ A_Sᵀ y`` and the coefficients
    ``s = L⁻ᵀ z`` updated in ``O(k)``, then the residual ``y − A s`` (synthesis) and its correlation
    ``Aᵀ r`` (analysis). ``‖r‖² = ‖y‖² − ‖z‖²`` gives the stopping test without forming ``r``.
    Returns ``(coefficients (N,), atoms, stop_reason, ‖r‖/‖y‖)``.
    """
    size = colnorm.size
    ny = float(np.linalg.norm(y))
    usable = colnorm > 1e-12 * float(colnorm.max())
    # selection weight; 0 for atoms already chosen or invisible (score 0 is never picked)
    weight = np.where(usable, 1.0 / np.where(usable, colnorm, 1.0), 0.0) if normalize else usable.astype(np.float64)
    aty = engine.correlate(y)
    g = aty
    # L⁻¹ stored as Uᵀ, U upper triangular packed by columns: column j of U (row j of L⁻¹) is
    # ap[j(j+1)/2 : (j+1)(j+2)/2], so adding an atom appends; BLAS tpmv reads only the triangle.
    ap = np.zeros(k_max * (k_max + 1) // 2)
    z = np.zeros(k_max)
    s_sup = np.zeros(k_max)  # coefficients on the support, in support order
    support = np.zeros(k_max, dtype=np.int64)
    coeffs = np.zeros(size)
    score = np.empty(size)
    # The residual y − A_S s from the stored support columns costs m·k multiply–adds, read from
    # memory; the synthesis transform costs about synth_cost, in cache. Keep the columns while the
    # stored product is cheaper and they fit in COLUMN_CACHE_BYTES.
    synth_cost = float(getattr(engine, "synth_cost", 0.0))
    m = y.size
    keep_cols = int(min(k_max, synth_cost // max(m, 1), COLUMN_CACHE_BYTES // (8 * max(m, 1))))
    acols = np.zeros((keep_cols, m))
    stop, k, res, z2 = "max_atoms", 0, 1.0, 0.0
    while k < k_max:
        np.multiply(np.abs(g, out=score), weight, out=score)
        p = pick_atom(score)
        if p < 0:
            stop = "exhausted"
            break
        weight[p] = 0.0
        a = column(p)
        a2 = float(a @ a)
        start = k * (k + 1) // 2
        if k:
            w = dtpmv(k, ap, engine.gram(a, support[:k]), lower=0, trans=1)  # L⁻¹ A_Sᵀ a
            d2 = a2 - float(w @ w)
        else:
            w, d2 = np.zeros(0), a2
        if not d2 > 1e-20 * a2:
            continue  # linearly dependent on the support: skip the atom
        d = np.sqrt(d2)
        if k:
            ap[start : start + k] = dtpmv(k, ap, w, lower=0, trans=0) * (-1.0 / d)  # −(wᵀ L⁻¹)/d
        ap[start + k] = 1.0 / d
        z[k] = (float(aty[p]) - float(w @ z[:k])) / d
        support[k] = p
        if k < keep_cols:
            acols[k] = a
        s_sup[: k + 1] += z[k] * ap[start : start + k + 1]  # s = L⁻ᵀ z, one new term
        z2 += z[k] * z[k]
        k += 1
        res = float(np.sqrt(max(ny * ny - z2, 0.0))) / ny
        if res <= tol:
            stop = "residual_tol"
            break
        if k < k_max:
            if k <= keep_cols:
                g = engine.correlate(y - s_sup[:k] @ acols[:k])
            else:
                coeffs[support[:k]] = s_sup[:k]
                g = engine.correlate(y - engine.synthesize(coeffs))
    coeffs[:] = 0.0
    coeffs[support[:k]] = s_sup[:k]
    return coeffs, k, stop, res


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
        info.update(
            iterations=0,
            stop_reason="zero_measurements" if ny == 0.0 else "max_atoms",
            relative_residual=0.0 if ny == 0.0 else 1.0,
        )
        return np.zeros((n, n)), info

    m2 = m_mat * m_mat
    colnorm = np.sqrt(np.maximum((m2[rows].T @ m2[cols]).ravel(), 0.0))  # ‖A[:, p]‖

    engine: OmpBackend
    if backend == "numpy":
        engine = NumpyOmpBackend(m_mat, rows, cols, k_max)
    else:
        from nirspi_pipe.solvers.omp_opencl import OpenCLOmpBackend

        engine = OpenCLOmpBackend(m_mat, rows, cols, k_max)

    def column(p: int) -> np.ndarray:
        a_idx, b_idx = divmod(p, n)
        return m_mat[rows, a_idx] * m_mat[cols, b_idx]

    coeffs, k, stop, res = omp_core(np.asarray(y, np.float64), engine, column, colnorm, k_max, tol, normalize)
    s = coeffs.reshape(n, n)
    image = b.T @ s @ b  # X = Bᵀ S B
    info.update(iterations=k, stop_reason=stop, relative_residual=res)
    return image, info


class DenseOmpBackend:
    """Explicit patterns: ``A = P (Bᵀ ⊗ Bᵀ)``, each pattern's 2D basis transform, an ``(m, N)``
    matrix the size of the patterns themselves."""

    def __init__(self, patterns: np.ndarray, b: np.ndarray) -> None:
        n = b.shape[0]
        p = np.asarray(patterns, dtype=np.float64).reshape(-1, n, n)
        self.a = np.ascontiguousarray((b @ p @ b.T).reshape(p.shape[0], n * n))

    def correlate(self, residual: np.ndarray) -> np.ndarray:
        return residual @ self.a

    def gram(self, column: np.ndarray, support: np.ndarray) -> np.ndarray:
        return column @ self.a[:, support]

    def synthesize(self, coeffs: np.ndarray) -> np.ndarray:
        nz = np.flatnonzero(coeffs)
        return self.a[:, nz] @ coeffs[nz]


def omp_explicit(
    y: np.ndarray, n: int, patterns: np.ndarray, basis: str, max_atoms: int, tol: float, normalize: bool
) -> tuple[np.ndarray, dict]:
    """OMP for measurements ``y = P x`` with explicit patterns ``P`` (``(m, n²)``, any values)."""
    b = basis_matrix(basis, n)
    engine = DenseOmpBackend(patterns, b)
    m, size = engine.a.shape
    k_max = int(max(0, min(max_atoms, m, size)))
    ny = float(np.linalg.norm(y))
    info: dict = {"backend": "numpy", "basis": basis}
    if ny == 0.0 or k_max == 0:
        info.update(
            iterations=0,
            stop_reason="zero_measurements" if ny == 0.0 else "max_atoms",
            relative_residual=0.0 if ny == 0.0 else 1.0,
        )
        return np.zeros((n, n)), info
    colnorm = np.linalg.norm(engine.a, axis=0)
    coeffs, k, stop, res = omp_core(
        np.asarray(y, np.float64), engine, lambda p: engine.a[:, p], colnorm, k_max, tol, normalize
    )
    image = b.T @ coeffs.reshape(n, n) @ b
    info.update(iterations=k, stop_reason=stop, relative_residual=res)
    return image, info


@dataclass(frozen=True)
class OMPSolver:
    """Solver ``omp``: orthogonal matching pursuit in a DCT or Haar basis (see module doc).

    Attributes:
        basis: ``dct`` (orthonormal DCT-II) or ``haar`` (orthonormal separable Haar).
        sparsity: atoms at most, as a fraction of the measurements ``m`` (0, 1].
        max_atoms: hard cap on atoms (cost grows as ``atoms · (n³ + m · atoms)``); null = none.
        tol: stop when ``‖r‖ ≤ tol · ‖y‖``.
        backend: ``auto`` (OpenCL on a GPU, else numpy), ``numpy`` (reference) or ``opencl``
            (pyopencl, float64).
    """

    basis: str = "dct"
    sparsity: float = 0.25
    max_atoms: int | None = 1000
    tol: float = 1e-6
    backend: str = "auto"
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
        if self.backend not in ("auto", "numpy", "opencl"):
            raise ConfigError("backend", self.backend, "auto, numpy or opencl")
        if self.backend == "opencl":
            from nirspi_pipe.solvers.omp_opencl import opencl_context

            opencl_context()  # build the kernels now (or fail in one line), never inside a timed solve

    def effective_backend(self) -> str:
        """``auto``: ``opencl`` on a GPU that builds the kernels, else ``numpy`` — on PoCL's CPU
        device OpenCL OMP is slower than numpy (``nirspi-bench omp``; docs/reconstruction.md)."""
        if self.backend != "auto":
            return self.backend
        from nirspi_pipe.solvers.omp_opencl import gpu_available

        return "opencl" if gpu_available() else "numpy"

    def atoms(self, m: int) -> int:
        """Atom budget for ``m`` measurements."""
        k = int(math.ceil(float(self.sparsity) * m))
        return k if self.max_atoms is None else min(k, int(self.max_atoms))

    def solve(self, acquisition: Acquisition) -> Image2D:
        y = checked_coefficients(acquisition, "omp")
        if acquisition.patterns is not None:
            image, info = omp_explicit(
                y,
                acquisition.n,
                acquisition.patterns,
                self.basis,
                self.atoms(len(y)),
                float(self.tol),
                bool(self.normalize),
            )
            return Image2D(image, info=info)
        image, info = omp_hadamard(
            y,
            acquisition.n,
            acquisition.indices,
            basis=self.basis,
            max_atoms=self.atoms(len(y)),
            tol=float(self.tol),
            backend=self.effective_backend(),
            normalize=bool(self.normalize),
        )
        return Image2D(image, info=info)
