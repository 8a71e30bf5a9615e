"""The fast transforms against dense Hadamard products, and their algebra."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from nirspi_pipe.patterns.hadamard import (
    fwht,
    fwht2,
    ifwht,
    ifwht2,
    is_power_of_two,
    pattern,
    sylvester,
)


@pytest.mark.parametrize("n", [1, 2, 4, 8, 16, 64, 128, 256, 1024, 4096])
def test_fwht_equals_scipy_hadamard_product(n: int) -> None:
    x = np.random.default_rng(n).standard_normal((3, n))
    np.testing.assert_allclose(fwht(x), x @ scipy.linalg.hadamard(n).T, atol=1e-9 * n)


@pytest.mark.parametrize("n", [2, 4, 8, 16, 32, 64, 128])
def test_fwht2_is_h_o_h(n: int) -> None:
    img = np.random.default_rng(n).random((n, n))
    h = scipy.linalg.hadamard(n)
    np.testing.assert_allclose(fwht2(img), h @ img @ h, atol=1e-9 * n * n)
    # Sylvester: H_{n²} = H_n ⊗ H_n, so the 2D transform is the 1D one of the row-major image
    if n <= 32:
        np.testing.assert_allclose(fwht2(img).ravel(), scipy.linalg.hadamard(n * n) @ img.ravel(), atol=1e-9 * n * n)


def test_patterns_follow_index_convention() -> None:
    n = 8
    img = np.random.default_rng(1).random((n, n))
    coeffs = fwht2(img).ravel()
    for k in range(n * n):
        p = pattern(k, n)
        assert set(np.unique(p)) <= {-1.0, 1.0}
        assert np.isclose((p * img).sum(), coeffs[k])  # Eq. (1) with alpha = 1
    assert np.all(pattern(0, n) == 1.0)  # k = 0 is the DC pattern


def test_sylvester_orthogonality() -> None:
    h = sylvester(16)
    np.testing.assert_array_equal(h @ h.T, 16 * np.eye(16))  # H Hᵀ = n I


@settings(max_examples=60, deadline=None)
@given(
    k=st.integers(min_value=0, max_value=12),
    data=st.data(),
)
def test_fwht_is_its_own_inverse_up_to_n(k: int, data: st.DataObject) -> None:
    n = 1 << k
    x = data.draw(arrays(np.float64, n, elements=st.floats(-1e6, 1e6, allow_nan=False)))
    scale = max(1.0, float(np.max(np.abs(x))))
    np.testing.assert_allclose(fwht(fwht(x)), n * x, atol=1e-9 * n * scale)
    np.testing.assert_allclose(ifwht(fwht(x)), x, atol=1e-9 * scale)


@settings(max_examples=30, deadline=None)
@given(k=st.integers(min_value=1, max_value=7), seed=st.integers(0, 2**32 - 1))
def test_fwht2_roundtrip(k: int, seed: int) -> None:
    n = 1 << k
    img = np.random.default_rng(seed).random((n, n))
    np.testing.assert_allclose(ifwht2(fwht2(img)), img, atol=1e-12)


@pytest.mark.parametrize("bad", [0, 3, 6, 100, -4])
def test_non_power_of_two_rejected(bad: int) -> None:
    assert not is_power_of_two(bad)
    with pytest.raises(ValueError):
        sylvester(bad)
    if bad > 0:
        with pytest.raises(ValueError, match="power of two"):
            fwht(np.zeros(bad))


def test_fwht_along_axis_and_integer_input() -> None:
    x = np.arange(32).reshape(4, 8)
    np.testing.assert_allclose(fwht(x, axis=0), scipy.linalg.hadamard(4) @ x)
    np.testing.assert_allclose(fwht(x, axis=1), x @ scipy.linalg.hadamard(8))
