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

Algorithm (Pati et al. 1993): repeat — pick the atom whose (optionally normalised) correlation
with the residual is largest; orthogonalise it against the chosen ones; remove it from the
residual — until ``‖r‖ ≤ tol·‖y‖``, ``max_atoms`` atoms, or no atom is left. The
orthogonalisation is an incremental Cholesky factor of the support's Gram matrix (see
:func:`omp_core`), and the correlations are updated per atom rather than recomputed.

Ties (symmetric scenes have exactly equal correlations) are broken deterministically: among
the atoms within a relative ``1e-9`` of the best score, the lowest index wins. This is what
makes the ``numpy`` and ``opencl`` back ends, whose sums round differently, pick the same atoms
and agree to ``1e-5``.

Back ends: ``numpy`` (the reference) and ``opencl`` (:mod:`nirspi_pipe.solvers.omp_opencl`,
pyopencl, float64; PoCL on the CPU here), which runs this same algorithm, selection and factor
update included, on the device from the first correlation to the coefficients, with no read-back
per atom, and solves a batch of problems with the same patterns in one go
(:func:`omp_hadamard_batch`).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from typing import Annotated, Any, Protocol, TypeVar

import numpy as np
from scipy.linalg.blas import daxpy, dtpmv

from nirspi_pipe.opencl_devices import check_device, choose, device_label
from nirspi_pipe.patterns.hadamard import sylvester
from nirspi_pipe.ranges import OneOf, Range, check_ranges
from nirspi_pipe.solvers.common import TIE_RTOL, checked_coefficients
from nirspi_pipe.solvers.omp_opencl import DeviceOmp, opencl_context
from nirspi_pipe.types import Acquisition, Image2D

__all__ = ["OMPSolver", "basis_matrix", "haar_matrix", "dct_matrix", "omp_hadamard", "TIE_RTOL"]


@lru_cache(maxsize=16)
def dct_matrix(n: int) -> np.ndarray:
    """Orthonormal DCT-II matrix ``C`` (``n × n``): ``C x = scipy.fft.dct(x, norm='ortho')``."""
    from scipy.fft import dct  # start-up: loads scipy (55 ms here)

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

    def gram(self, p: int, support: np.ndarray) -> np.ndarray:
        """``A_Sᵀ a_p``: the correlations of atom ``p`` with the support's atoms."""

    def project(self, support: np.ndarray, u: np.ndarray) -> np.ndarray:
        """``Aᵀ A_S u`` (``(N,)``): the correlations of the combination ``Σ u_j a_{support_j}``."""


class NumpyOmpBackend:
    """Reference back end: the separable transform ``M = H Bᵀ`` as matrix products, restricted to
    the Hadamard rows ``U`` and columns ``V`` that hold a measurement (``R`` is zero elsewhere; a
    low-sequency order at 25 % uses about 70 % of each).

    :meth:`project` synthesises only from the basis rows and columns the support uses, in the
    order they joined it (``M_U[:, a_S] S_c M_V[:, b_S]ᵀ``, with ``S_c`` the support's
    coefficients on those rows and columns), keeps the measured cells with a 0/1 mask, and
    correlates: no gather or scatter of ``m`` values."""

    def __init__(self, m_mat: np.ndarray, rows: np.ndarray, cols: np.ndarray, k_max: int) -> None:
        self.n = n = m_mat.shape[0]
        used_rows, u_of = np.unique(rows, return_inverse=True)
        used_cols, v_of = np.unique(cols, return_inverse=True)
        self.cells = u_of * used_cols.size + v_of  # measured cells, flat on the |U| × |V| grid
        self.mu_t = np.ascontiguousarray(m_mat[used_rows].T)  # (n, |U|)
        self.mv = np.ascontiguousarray(m_mat[used_cols])  # (|V|, n)
        self.mv_t = np.ascontiguousarray(self.mv.T)  # (n, |V|)
        self.grid = np.zeros((used_rows.size, used_cols.size))
        self.flat = self.grid.ravel()  # a view: flat scatters are 4× faster than (row, col) ones
        self.mask = np.zeros_like(self.grid)
        self.mask.ravel()[self.cells] = 1.0
        # the support's basis rows a (columns of M_U, stored as rows of M_Uᵀ) and columns b, in
        # the order they joined the support; slot[a] is a's position there (−1: not yet)
        self.sel_a = np.zeros((n, used_rows.size))
        self.sel_b = np.zeros((n, used_cols.size))
        self.slot_a = np.full(n, -1, dtype=np.int64)
        self.slot_b = np.full(n, -1, dtype=np.int64)
        self.na = self.nb = self.known = 0
        self.pos_a = np.zeros(k_max, dtype=np.int64)
        self.pos_b = np.zeros(k_max, dtype=np.int64)
        self.coef = np.zeros((n, n))
        self.synth = np.empty_like(self.grid)
        self.left = np.empty((n, used_cols.size))
        self.out = np.empty((n, n))  # project's result, overwritten by the next call

    def correlate(self, residual: np.ndarray) -> np.ndarray:
        self.flat[self.cells] = residual
        out = (self.mu_t @ self.grid) @ self.mv
        self.flat[self.cells] = 0.0
        return out.ravel()

    def gram(self, p: int, support: np.ndarray) -> np.ndarray:
        # a_p on the grid is mask ⊙ (x yᵀ), x = M_U[:, a], y = M_V[:, b]; so
        # A_Sᵀ a_p = ((M_Uᵀ[a_S] ⊙ x) mask) ⊙ y) M_V[:, b_S] read at the support's cells
        k = support.size
        self._admit(support)
        a, b = divmod(p, self.n)
        left = (self.sel_a[: self.na] * self.mu_t[a]) @ self.mask  # (na, |V|)
        left *= self.mv_t[b]
        return (left @ self.sel_b[: self.nb].T)[self.pos_a[:k], self.pos_b[:k]]

    def _admit(self, support: np.ndarray) -> None:
        """Record the atoms of ``support`` that joined since the last call (the support only grows
        within one solve; a shorter one starts over)."""
        if support.size < self.known:
            self.slot_a[:], self.slot_b[:], self.coef[:] = -1, -1, 0.0
            self.na = self.nb = self.known = 0
        for j in range(self.known, support.size):
            a, b = divmod(int(support[j]), self.n)
            if self.slot_a[a] < 0:
                self.slot_a[a], self.sel_a[self.na] = self.na, self.mu_t[a]
                self.na += 1
            if self.slot_b[b] < 0:
                self.slot_b[b], self.sel_b[self.nb] = self.nb, self.mv_t[b]
                self.nb += 1
            self.pos_a[j], self.pos_b[j] = self.slot_a[a], self.slot_b[b]
        self.known = support.size

    def project(self, support: np.ndarray, u: np.ndarray) -> np.ndarray:
        k = support.size
        self._admit(support)
        na, nb = self.na, self.nb
        self.coef[self.pos_a[:k], self.pos_b[:k]] = u  # overwrites every earlier support cell
        part = self.sel_a[:na].T @ self.coef[:na, :nb]  # (|U|, nb)
        synth = np.matmul(part, self.sel_b[:nb], out=self.synth)  # (|U|, |V|): A_S u, Hadamard rows × cols
        synth *= self.mask
        np.matmul(np.matmul(self.mu_t, synth, out=self.left), self.mv, out=self.out)
        return self.out.ravel()


def pick_atom(score: np.ndarray) -> int:
    """Index of the best score with the deterministic tie rule (lowest index within
    :data:`TIE_RTOL`); −1 when no score is positive."""
    best = float(score.max())
    if not best > 0.0:
        return -1
    return int(np.argmax(score >= best * (1.0 - TIE_RTOL)))  # the first index in the window


T = TypeVar("T")


def _one_blas_thread(fn: Callable[..., T]) -> Callable[..., T]:
    """Run ``fn`` with one BLAS thread. Every product of the OMP loop is small (a few million
    multiply-adds), and on the project's 2-core machines OpenBLAS's second thread made the loop
    11x slower (128² at 25 %: 14.6 s against 1.3 s, an in-process solve with and without
    OPENBLAS_NUM_THREADS=1; ``nirspi-bench omp`` times it)."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> T:
        with _blas_controller().limit(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

    return wrapper


@lru_cache(maxsize=1)
def _blas_controller() -> Any:
    """threadpoolctl's view of the loaded BLAS libraries, found once per process: finding them
    (``threadpool_limits`` does it on every call) cost 1.8 ms per solve, as much as an 8² OMP
    solve (cProfile of 20 Figure 9 jobs)."""
    from threadpoolctl import ThreadpoolController  # start-up: loads threadpoolctl (4 ms here)

    return ThreadpoolController()


@_one_blas_thread
def omp_core(
    y: np.ndarray,
    engine: OmpBackend,
    colnorm: np.ndarray,
    k_max: int,
    tol: float,
    normalize: bool,
) -> tuple[np.ndarray, int, str, float]:
    """OMP with an incremental Cholesky factor of the support's Gram matrix ``A_SᵀA_S = L Lᵀ``,
    kept as its inverse ``L⁻¹`` (lower triangular; adding an atom appends a row and leaves the
    others unchanged). ``Q = A_S L⁻ᵀ`` are the orthonormalised atoms (never formed: row ``k`` of
    ``L⁻¹`` holds ``q_k`` as a combination of the support's atoms).

    Per atom ``p``:

    * ``w = Qᵀ a_p = L⁻¹ A_Sᵀ a_p``: the Gram column ``A_Sᵀ a_p`` (``engine.gram``) and one
      triangular product (``O(k²)``);
    * ``d² = ‖a_p‖² − ‖w‖²``, the new row of ``L⁻¹`` ``[−wᵀL⁻¹, 1]/d`` (``O(k²)``), and
      ``z_k = q_kᵀ y = (a_pᵀy − w·z)/d``; the coefficients ``s = L⁻ᵀ z`` gain one term (``O(k)``);
    * the residual ``r ← r − z_k q_k`` changes the correlations by ``−z_k Aᵀ q_k``: one
      synthesis of ``q_k`` from its ``k`` atoms and one correlation (``engine.project``).

    ``‖r‖² = ‖y‖² − ‖z‖²`` gives the stopping test without forming ``r``.
    Returns ``(coefficients (N,), atoms, stop_reason, ‖r‖/‖y‖)``.
    """
    size = colnorm.size
    ny = float(np.linalg.norm(y))
    # selection weight; 0 for atoms already chosen or invisible (score 0 is never picked)
    weight = selection_weight(colnorm, normalize)
    aty = engine.correlate(y)
    g = aty.copy()  # Aᵀ r, updated per atom
    # L⁻¹ stored as Uᵀ, U upper triangular packed by columns: column j of U (row j of L⁻¹) is
    # ap[j(j+1)/2 : (j+1)(j+2)/2], so adding an atom appends; BLAS tpmv reads only the triangle.
    ap = np.zeros(k_max * (k_max + 1) // 2)
    z = np.zeros(k_max)
    s_sup = np.zeros(k_max)  # coefficients on the support, in support order
    support = np.zeros(k_max, dtype=np.int64)
    score = np.empty(size)
    stop, k, res, z2 = "max_atoms", 0, 1.0, 0.0
    while k < k_max:
        np.multiply(np.abs(g, out=score), weight, out=score)
        p = pick_atom(score)
        if p < 0:
            stop = "exhausted"
            break
        weight[p] = 0.0
        a2 = float(colnorm[p]) ** 2
        start = k * (k + 1) // 2
        if not k:
            w, d2 = np.zeros(0), a2
        else:
            w = dtpmv(k, ap, engine.gram(p, support[:k]), lower=0, trans=1)  # L⁻¹ A_Sᵀ a
            d2 = a2 - float(w @ w)
        if not d2 > 1e-20 * a2:
            continue  # linearly dependent on the support: skip the atom
        d = np.sqrt(d2)
        if k:
            ap[start : start + k] = dtpmv(k, ap, w, lower=0, trans=0) * (-1.0 / d)  # −(wᵀ L⁻¹)/d
        ap[start + k] = 1.0 / d
        zk = (float(aty[p]) - float(w @ z[:k])) / d
        z[k] = zk
        support[k] = p
        s_sup[: k + 1] += zk * ap[start : start + k + 1]  # s = L⁻ᵀ z, one new term
        z2 += zk * zk
        k += 1
        res = float(np.sqrt(max(ny * ny - z2, 0.0))) / ny
        if res <= tol:
            stop = "residual_tol"
            break
        if k < k_max:
            daxpy(engine.project(support[:k], ap[start : start + k]), g, a=-zk)  # r −= z_k q_k: g −= z_k Aᵀq_k
    coeffs = np.zeros(size)
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
    device: str = "auto",
    opencl_mode: str | None = None,
) -> tuple[np.ndarray, dict]:
    """OMP for Hadamard measurements ``y`` at flat ``indices``; returns ``(image, info)``.
    ``backend`` ``opencl`` solves on the device ``device`` names (:mod:`nirspi_pipe.opencl_devices`), laid
    out as ``opencl_mode`` says (:meth:`~nirspi_pipe.solvers.omp_opencl.DeviceOmp.solve`).

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

    if backend == "opencl":
        engine_cl = DeviceOmp(m_mat, rows, cols, colnorm, k_max, device)
        coeffs_b, atoms, stops, resids = engine_cl.solve(
            y[None, :], selection_weight(colnorm, normalize), tol, opencl_mode
        )
        coeffs, k, stop, res = coeffs_b[0], int(atoms[0]), stops[0], float(resids[0])
    else:
        engine = NumpyOmpBackend(m_mat, rows, cols, k_max)
        coeffs, k, stop, res = omp_core(np.asarray(y, np.float64), engine, colnorm, k_max, tol, normalize)
    s = coeffs.reshape(n, n)
    image = b.T @ s @ b  # X = Bᵀ S B
    info.update(iterations=k, stop_reason=stop, relative_residual=res)
    return image, info


def selection_weight(colnorm: np.ndarray, normalize: bool) -> np.ndarray:
    """OMP's selection weight per atom (:func:`omp_core`): ``1/‖a_p‖`` (``normalize``) or 1 for
    the atoms the measurements see, 0 for the invisible ones (score 0 is never picked)."""
    usable = colnorm > 1e-12 * float(colnorm.max())
    if normalize:
        return np.where(usable, 1.0 / np.where(usable, colnorm, 1.0), 0.0)
    return usable.astype(np.float64)


def omp_hadamard_batch(
    ys: np.ndarray,
    n: int,
    indices: np.ndarray,
    basis: str = "dct",
    max_atoms: int = 1000,
    tol: float = 1e-6,
    normalize: bool = False,
    device: str = "auto",
    opencl_mode: str | None = None,
) -> tuple[np.ndarray, list[dict]]:
    """OMP of ``B`` independent problems measured with the same patterns (``ys``: ``(B, m)``, one
    row per problem: tiles, the images of a sweep) in one device solve, every kernel launch
    serving all of them (:class:`~nirspi_pipe.solvers.omp_opencl.DeviceOmp`). Returns the images
    ``(B, n, n)`` and one ``info`` per problem, each what :func:`omp_hadamard` gives."""
    ys = np.atleast_2d(np.asarray(ys, np.float64))
    idx = np.asarray(indices, dtype=np.int64)
    rows, cols = idx // n, idx % n
    b = basis_matrix(basis, n)
    m_mat = np.ascontiguousarray(sylvester(n) @ b.T)
    k_max = int(max(1, min(max_atoms, idx.size, n * n)))
    m2 = m_mat * m_mat
    colnorm = np.sqrt(np.maximum((m2[rows].T @ m2[cols]).ravel(), 0.0))
    engine = DeviceOmp(m_mat, rows, cols, colnorm, k_max, device)
    coeffs, atoms, stops, resids = engine.solve(ys, selection_weight(colnorm, normalize), tol, opencl_mode)
    images = b.T @ coeffs.reshape(-1, n, n) @ b
    infos = [
        {
            "backend": "opencl",
            "basis": basis,
            "iterations": int(k),
            "stop_reason": stop,
            "relative_residual": float(res),
        }
        for k, stop, res in zip(atoms, stops, resids)
    ]
    return images, infos


class DenseOmpBackend:
    """Explicit patterns: ``A = P (Bᵀ ⊗ Bᵀ)``, each pattern's 2D basis transform, an ``(m, N)``
    matrix the size of the patterns themselves. The support's columns are copied once, as they
    join, into a ``(k_max, m)`` block, so the per-atom products read them contiguously."""

    def __init__(self, patterns: np.ndarray, b: np.ndarray, k_max: int) -> None:
        n = b.shape[0]
        p = np.asarray(patterns, dtype=np.float64).reshape(-1, n, n)
        self.a = np.ascontiguousarray((b @ p @ b.T).reshape(p.shape[0], n * n))
        self.cols = np.zeros((k_max, self.a.shape[0]))
        self.known = 0

    def _admit(self, support: np.ndarray) -> None:
        if support.size < self.known:  # a new solve
            self.known = 0
        for j in range(self.known, support.size):
            self.cols[j] = self.a[:, support[j]]
        self.known = support.size

    def correlate(self, residual: np.ndarray) -> np.ndarray:
        return residual @ self.a

    def gram(self, p: int, support: np.ndarray) -> np.ndarray:
        self._admit(support)
        return self.cols[: support.size] @ self.a[:, p]

    def project(self, support: np.ndarray, u: np.ndarray) -> np.ndarray:
        self._admit(support)
        return (u @ self.cols[: support.size]) @ self.a


def omp_explicit(
    y: np.ndarray, n: int, patterns: np.ndarray, basis: str, max_atoms: int, tol: float, normalize: bool
) -> tuple[np.ndarray, dict]:
    """OMP for measurements ``y = P x`` with explicit patterns ``P`` (``(m, n²)``, any values)."""
    b = basis_matrix(basis, n)
    m = len(patterns)
    k_max = int(max(0, min(max_atoms, m, n * n)))
    engine = DenseOmpBackend(patterns, b, k_max)
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
    coeffs, k, stop, res = omp_core(np.asarray(y, np.float64), engine, colnorm, k_max, tol, normalize)
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
        backend: ``auto`` (OpenCL where it was measured faster than numpy on the device at this
            size, :func:`nirspi_pipe.opencl_devices.choose`; numpy where nothing was measured, and on
            PoCL's CPU device), ``numpy`` (reference) or ``opencl`` (pyopencl, float64, the
            whole solve on the device).
        device: the OpenCL device: ``auto``, ``cpu``, ``gpu`` or ``<platform>:<device>``
            (:mod:`nirspi_pipe.opencl_devices`; ``auto`` honours ``PYOPENCL_CTX``).
    """

    basis: Annotated[str, OneOf(("dct", "haar"))] = "dct"
    sparsity: Annotated[float, Range(0.0, 1.0, "a fraction of the measurements", lo_open=True)] = 0.25
    max_atoms: Annotated[int | None, Range(1, None, "an integer", integer=True)] = 1000
    tol: Annotated[float, Range(0.0, 1.0, "a relative tolerance", hi_open=True)] = 1e-6
    backend: Annotated[str, OneOf(("auto", "numpy", "opencl"))] = "auto"
    normalize: bool = False
    device: str = "auto"

    def __post_init__(self) -> None:
        check_ranges(self)
        check_device(self.device)
        if self.backend == "opencl":
            opencl_context(self.device)  # build the kernels now (or fail in one line), never inside a timed solve

    def effective_backend(self, size: int = 64) -> str:
        """The back end of a solve of an ``size × size`` image. ``auto``: ``opencl`` where a device
        builds the kernels and OpenCL OMP was measured faster than numpy on it at that size
        (:func:`nirspi_pipe.opencl_devices.choose`), else ``numpy``: on PoCL's CPU device the device OMP is
        slower than numpy (``nirspi-bench omp --opencl``; docs/reconstruction.md)."""
        if self.backend != "auto":
            return self.backend

        try:
            ctx, _, _ = opencl_context(self.device)
        except Exception:  # noqa: BLE001 - no working device: numpy
            return "numpy"
        return choose("omp", ctx.devices[0], int(size))[0]

    def device_name(self, backend: str) -> str:
        """The record's name of the device a solve on ``backend`` ran on."""
        if backend != "opencl":
            return "cpu (numpy)"

        return device_label(opencl_context(self.device)[0].devices[0])

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
            info.update(device="cpu (numpy)", device_requested=self.device)
            return Image2D(image, info=info)
        backend = self.effective_backend(acquisition.n)
        image, info = omp_hadamard(
            y,
            acquisition.n,
            acquisition.indices,
            basis=self.basis,
            max_atoms=self.atoms(len(y)),
            tol=float(self.tol),
            backend=backend,
            normalize=bool(self.normalize),
            device=self.device,
        )
        info.update(device=self.device_name(backend), device_requested=self.device, backend_requested=self.backend)
        return Image2D(image, info=info)
