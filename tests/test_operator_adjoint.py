"""The measurement operator and its adjoint (issue 27): ``<A x, r> = <x, Aᵀ r>`` for every form the
solvers use (the fast Hadamard operator, an explicit pattern matrix, FISTA-TV's batched operator
on its dense and its transform paths, held-out rows included), and the fast operator measures
what the patterns of :func:`nirspi_pipe.patterns.hadamard.pattern` measure."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from nirspi_pipe.patterns.hadamard import fwht2, pattern
from nirspi_pipe.solvers.common import hadamard_operator, measurement_operator
from nirspi_pipe.solvers.fista_tv import DENSE_MAX_PIXELS, _batch_operator
from nirspi_pipe.types import Acquisition

#: Both sides of ``<A x, r> = <x, Aᵀ r>`` are sums of N·m products of O(1) numbers; float64 rounding
#: leaves a relative gap of a few 1e-16 × sqrt(N·m). 1e-12 is far above it and far below any
#: wrong sign, index or scale (which give gaps of order 1).
RTOL = 1e-12


@st.composite
def cases(draw: st.DrawFn) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """A side ``n`` (2 to 32, both FISTA paths), measured indices in any order, ``x`` and ``r``."""
    n = draw(st.sampled_from([2, 4, 8, 16, 32]))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    m = draw(st.integers(1, n * n))
    idx = rng.permutation(n * n)[:m].astype(np.int64)
    return n, idx, rng.normal(size=n * n), rng.normal(size=m)


def _gap(ax: np.ndarray, r: np.ndarray, x: np.ndarray, atr: np.ndarray) -> float:
    lhs, rhs = float(ax @ r), float(x @ atr)
    scale = float(np.linalg.norm(ax) * np.linalg.norm(r) + np.linalg.norm(x) * np.linalg.norm(atr))
    return abs(lhs - rhs) / scale


@settings(max_examples=60, deadline=None)
@given(cases())
def test_fast_hadamard_operator_is_adjoint_and_measures_the_patterns(case) -> None:  # type: ignore[no-untyped-def]
    n, idx, x, r = case
    op = hadamard_operator(n, idx)
    assert _gap(op.matvec(x), r, x, op.rmatvec(r)) < RTOL
    explicit = np.stack([pattern(int(k), n).ravel() for k in idx])  # the ±1 patterns a device shows
    np.testing.assert_allclose(op.matvec(x), explicit @ x, rtol=0, atol=1e-9 * n * n)
    np.testing.assert_allclose(op.rmatvec(r), explicit.T @ r, rtol=0, atol=1e-9 * n * n)
    np.testing.assert_allclose(op.matvec(x)[np.argsort(idx)], fwht2(x.reshape(n, n)).ravel()[np.sort(idx)], atol=1e-9)


@settings(max_examples=40, deadline=None)
@given(cases(), st.integers(0, 2**32 - 1))
def test_explicit_and_batched_operators_are_adjoint(case, seed: int) -> None:  # type: ignore[no-untyped-def]
    n, idx, x, r = case
    rng = np.random.default_rng(seed)
    hadamard = Acquisition(n=n, indices=idx, y_pos=np.zeros(idx.size))
    patterns = rng.choice([0.0, 1.0], size=(idx.size, n * n)) - rng.uniform(0, 1, size=(idx.size, n * n))
    explicit = Acquisition(n=n, indices=idx, y_pos=np.zeros(idx.size), patterns=patterns)
    op = measurement_operator(explicit)
    assert _gap(op.matvec(x), r, x, op.rmatvec(r)) < RTOL
    held = np.sort(rng.permutation(idx.size)[: max(1, idx.size // 2)])
    for acq in (hadamard, explicit):
        for rows in (None, held):
            fwd, adj = _batch_operator(acq, rows)
            xb = np.stack([x, -2.0 * x + 1.0])  # a batch of two
            rb = np.stack([r, r[::-1]]) if rows is None else np.stack([r[rows], r[rows][::-1]])
            axb, atrb = fwd(xb), adj(rb)
            for b in range(2):
                assert _gap(axb[b], rb[b], xb[b], atrb[b]) < RTOL
            if acq.patterns is None:  # the dense path (≤ 16²) and the transform path agree with the operator
                full = hadamard_operator(n, idx if rows is None else idx[rows])
                np.testing.assert_allclose(axb[0], full.matvec(x), atol=1e-9 * n * n)


def test_both_batched_paths_are_exercised() -> None:
    assert 16 * 16 <= DENSE_MAX_PIXELS < 32 * 32
