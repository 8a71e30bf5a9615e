"""OMP (issue #15): the transform-based engine and the incremental updates against a dense,
textbook OMP that forms ``A`` and solves the least-squares problem from scratch at every atom."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nirspi_pipe.patterns.hadamard import sylvester
from nirspi_pipe.solvers.omp import NumpyOmpBackend, basis_matrix, omp_explicit, omp_hadamard


def _dense(n: int, indices: np.ndarray, basis: str) -> np.ndarray:
    """``A`` (``m × N``): atom ``(a, b)`` sampled at Hadamard cell ``(i, j)`` is ``M[i, a] M[j, b]``."""
    m_mat = sylvester(n) @ basis_matrix(basis, n).T
    rows, cols = np.divmod(indices, n)
    return np.einsum("ka,kb->kab", m_mat[rows], m_mat[cols]).reshape(indices.size, n * n)


def _textbook_omp(a: np.ndarray, y: np.ndarray, atoms: int) -> tuple[np.ndarray, list[int]]:
    """Pati et al. 1993 verbatim: argmax |Aᵀr|, then least squares on the whole support."""
    support: list[int] = []
    coeffs = np.zeros(a.shape[1])
    r = y.copy()
    for _ in range(atoms):
        score = np.abs(a.T @ r)
        score[support] = 0.0
        support.append(int(np.argmax(score)))
        sol = np.linalg.lstsq(a[:, support], y, rcond=None)[0]
        r = y - a[:, support] @ sol
    coeffs[support] = sol
    return coeffs, support


def _case(n: int, ratio: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    indices = np.sort(rng.choice(n * n, size=max(4, int(ratio * n * n)), replace=False))
    return indices, rng.standard_normal(indices.size)


@settings(max_examples=12, deadline=None)
@given(
    n=st.sampled_from([8, 16]),
    ratio=st.floats(0.15, 0.6),
    seed=st.integers(0, 10_000),
    basis=st.sampled_from(["dct", "haar"]),
)
def test_omp_matches_the_textbook_algorithm(n: int, ratio: float, seed: int, basis: str) -> None:
    indices, y = _case(n, ratio, seed)
    atoms = max(1, indices.size // 3)
    a = _dense(n, indices, basis)
    want, want_support = _textbook_omp(a, y, atoms)
    image, info = omp_hadamard(y, n, indices, basis=basis, max_atoms=atoms, tol=0.0)
    b = basis_matrix(basis, n)
    got = (b @ image @ b.T).ravel()
    assert info["iterations"] == atoms
    assert set(np.flatnonzero(np.abs(got) > 1e-9 * np.abs(got).max())) <= set(want_support)
    np.testing.assert_allclose(got, want, atol=1e-9 * float(np.abs(want).max()))
    # the dense engine (explicit patterns) runs the same core on A itself
    patterns = b.T @ a.reshape(-1, n, n) @ b  # the patterns whose basis transforms are A's rows
    dense_image, _ = omp_explicit(y, n, patterns.reshape(-1, n * n), basis, atoms, 0.0, normalize=False)
    np.testing.assert_allclose(dense_image, image, atol=1e-9 * float(np.abs(image).max()))


@pytest.mark.parametrize("basis", ["dct", "haar"])
def test_engine_gram_and_projection_equal_the_dense_products(basis: str) -> None:
    n = 16
    indices, _ = _case(n, 0.4, 3)
    a = _dense(n, indices, basis)
    m_mat = np.ascontiguousarray(sylvester(n) @ basis_matrix(basis, n).T)
    rows, cols = np.divmod(indices, n)
    engine = NumpyOmpBackend(m_mat, rows, cols, k_max=40)
    rng = np.random.default_rng(0)
    order = rng.permutation(n * n)[:40]
    for k in (1, 7, 40, 5):  # growing support, then a shorter one (a new solve) starts over
        support = order[:k]
        u = rng.standard_normal(k)
        np.testing.assert_allclose(engine.project(support, u), a.T @ (a[:, support] @ u), atol=1e-12)
        p = int(order[-1] if k < 40 else order[0])
        np.testing.assert_allclose(engine.gram(p, support), a[:, support].T @ a[:, p], atol=1e-12)
    r = rng.standard_normal(indices.size)
    np.testing.assert_allclose(engine.correlate(r), a.T @ r, atol=1e-12)


def _device_or_skip() -> None:
    from nirspi_pipe.errors import NirspiError
    from nirspi_pipe.solvers.omp_opencl import opencl_context

    try:
        opencl_context()
    except NirspiError as exc:
        pytest.skip(str(exc))


@pytest.mark.parametrize("mode", ["kernels", "workgroup"])
@pytest.mark.parametrize(("basis", "normalize", "tol"), [("dct", False, 0.0), ("haar", True, 0.0), ("dct", False, 0.2)])
def test_device_batch_equals_numpy_one_by_one(basis: str, normalize: bool, tol: float, mode: str) -> None:
    """Issue 33: the device OMP solves a batch of problems with the same patterns in one go;
    each equals the numpy solve to 1e-10 with the same atoms and stop reason (a zero problem, a
    tolerance met early and the atom budget included)."""
    from nirspi_pipe.solvers.omp import omp_hadamard_batch

    _device_or_skip()
    n = 16
    indices, _ = _case(n, 0.3, 7)
    rng = np.random.default_rng(1)
    ys = rng.standard_normal((4, indices.size))
    ys[2] = 0.0
    images, infos = omp_hadamard_batch(
        ys, n, indices, basis, max_atoms=25, tol=tol, normalize=normalize, opencl_mode=mode
    )
    stops = set()
    for y, image, info in zip(ys, images, infos):
        want, winfo = omp_hadamard(y, n, indices, basis=basis, max_atoms=25, tol=tol, normalize=normalize)
        assert (info["iterations"], info["stop_reason"]) == (winfo["iterations"], winfo["stop_reason"])
        assert info["relative_residual"] == pytest.approx(winfo["relative_residual"], abs=1e-12)
        assert np.max(np.abs(image - want)) <= 1e-10
        stops.add(info["stop_reason"])
    assert "zero_measurements" in stops
