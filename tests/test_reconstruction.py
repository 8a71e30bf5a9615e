"""Scan orders × solvers (issue #4): permutations, exact full sampling, DC first, stability."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nirspi_pipe.errors import ConfigError, NirspiError
from nirspi_pipe.patterns.hadamard import fwht2, pattern, sylvester
from nirspi_pipe.patterns.orders import ORDERS, Spiral, block_counts, sequency_of_rows
from nirspi_pipe.solvers.correlation import CorrelationSolver
from nirspi_pipe.solvers.fista_tv import FistaTVSolver
from nirspi_pipe.solvers.fwht import FWHTSolver
from nirspi_pipe.solvers.lstsq import LstsqSolver
from nirspi_pipe.solvers.omp import OMPSolver, haar_matrix
from nirspi_pipe.types import Acquisition

N_SIDE = 16

ORDER_CASES = [pytest.param(cls(), id=name) for name, cls in ORDERS.items()]
ORDER_CASES.append(pytest.param(Spiral(start="centre"), id="spiral_centre"))

#: Solvers configured so that full sampling must be exact (no regulariser bias, atoms enough).
EXACT_SOLVERS = {
    "fwht": FWHTSolver(),
    "correlation": CorrelationSolver(chunk=37),
    "lstsq": LstsqSolver(),
    "fista_tv": FistaTVSolver(lam=0.0),
    "omp": OMPSolver(sparsity=1.0, max_atoms=None, tol=1e-12),
}
DEFAULT_SOLVERS = {
    "fwht": FWHTSolver(),
    "correlation": CorrelationSolver(),
    "lstsq": LstsqSolver(),
    "fista_tv": FistaTVSolver(),
    "omp": OMPSolver(),
}


def _scene(n: int, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:n, 0:n] / n
    disc = ((yy - 0.5) ** 2 + (xx - 0.45) ** 2 < 0.1).astype(float)
    return np.clip(0.2 + 0.6 * disc * (1 - yy) + 0.05 * rng.random((n, n)), 0, 1)


def _acquire(image: np.ndarray, indices: np.ndarray) -> Acquisition:
    c = fwht2(image).ravel()[indices]
    return Acquisition(n=image.shape[0], indices=np.asarray(indices, dtype=np.int64), y_pos=c)


@pytest.mark.parametrize("order", ORDER_CASES)
@pytest.mark.parametrize("n", [2, 8, 32])
def test_order_is_a_permutation(order, n):
    p = order.order(n)
    assert p.dtype == np.int64 and p.shape == (n * n,)
    assert np.array_equal(np.sort(p), np.arange(n * n))


@pytest.mark.parametrize("order", ORDER_CASES)
def test_order_declares_dc_first_truthfully(order):
    for n in (4, 16, 64):
        first_is_dc = bool(order.order(n)[0] == 0)
        if order.dc_first:
            assert first_is_dc
    # an order that says DC is not first must show it somewhere (spiral centre, random)
    if not order.dc_first:
        assert any(order.order(n)[0] != 0 for n in (4, 16, 64))


@pytest.mark.parametrize("order", ORDER_CASES)
@pytest.mark.parametrize("solver_name", list(EXACT_SOLVERS))
def test_ratio_one_reconstructs_exactly(order, solver_name):
    img = _scene(N_SIDE)
    acq = _acquire(img, order.order(N_SIDE))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a clean full acquisition must not warn
        out = EXACT_SOLVERS[solver_name].solve(acq)
    np.testing.assert_allclose(out.data, img, atol=1e-8)
    assert "iterations" in out.info and "stop_reason" in out.info


@pytest.mark.parametrize("solver_name", list(DEFAULT_SOLVERS))
def test_default_solvers_near_exact_at_full_sampling(solver_name):
    img = _scene(N_SIDE)
    out = DEFAULT_SOLVERS[solver_name].solve(_acquire(img, np.arange(N_SIDE**2)))
    err = np.sqrt(np.mean((out.data - img) ** 2))
    assert err < (0.05 if solver_name in ("fista_tv", "omp") else 1e-10)


def test_sequency_map_counts_sign_changes():
    for n in (2, 4, 8, 32, 128):
        h = sylvester(n)
        assert np.array_equal((np.diff(h, axis=1) != 0).sum(axis=1), sequency_of_rows(n))


def test_block_counts_match_connected_regions():
    from scipy.ndimage import label

    n = 8
    counts = block_counts(n)
    for k in range(n * n):
        p = pattern(k, n)
        assert label(p > 0)[1] + label(p < 0)[1] == counts[k]


def test_russian_doll_prefixes_are_complete_coarse_bases():
    n = 16
    order = ORDERS["russian_doll"]().order(n)
    for level in range(1, 5):
        side = 2**level
        img = np.kron(_scene(side), np.ones((n // side, n // side)))
        out = FWHTSolver().solve(_acquire(img, order[: side * side]))
        np.testing.assert_allclose(out.data, img, atol=1e-10)


def test_random_is_seeded_and_variance_uses_training_images():
    a, b, c = ORDERS["random"](seed=3), ORDERS["random"](seed=3), ORDERS["random"](seed=4)
    assert np.array_equal(a.order(8), b.order(8)) and not np.array_equal(a.order(8), c.order(8))
    v1 = ORDERS["variance"](images=["skimage:moon", "skimage:coins"]).order(16)
    v2 = ORDERS["variance"](images=["skimage:text", "skimage:page"]).order(16)
    assert v1[0] == 0 and not np.array_equal(v1, v2)


def test_bad_config_values_raise_config_error():
    with pytest.raises(ConfigError):
        ORDERS["spiral"](start="middle")
    with pytest.raises(ConfigError):
        ORDERS["basic"](ratio=0.0)
    with pytest.raises(ConfigError):
        OMPSolver(basis="wavelet")
    with pytest.raises(ConfigError):
        FistaTVSolver(lam=-1.0)


def test_haar_matrix_is_orthonormal():
    w = haar_matrix(32)
    np.testing.assert_allclose(w @ w.T, np.eye(32), atol=1e-12)


def test_explicit_patterns_use_a_general_operator():
    n = 8
    rng = np.random.default_rng(0)
    img = _scene(n)
    p = rng.choice([-1.0, 1.0], size=(80, n * n))
    acq = Acquisition(n=n, indices=np.arange(80), y_pos=p @ img.ravel(), patterns=p)
    out = LstsqSolver().solve(acq)
    np.testing.assert_allclose(out.data, img, atol=1e-8)  # overdetermined, full rank
    out = FistaTVSolver(lam=0.0, max_iter=2000, tol=1e-12).solve(acq)
    np.testing.assert_allclose(out.data, img, atol=1e-4)
    assert np.all(np.isfinite(CorrelationSolver().solve(acq).data))
    out = OMPSolver(sparsity=1.0, tol=1e-12).solve(acq)  # explicit patterns: the dense OMP (issue #15)
    np.testing.assert_allclose(out.data, img, atol=1e-8)
    with pytest.raises(NirspiError):
        FWHTSolver().solve(acq)


# --- stability ----------------------------------------------------------------------------


@pytest.mark.parametrize("solver_name", list(DEFAULT_SOLVERS))
def test_all_zero_measurements_warn_and_stay_finite(solver_name):
    acq = Acquisition(n=N_SIDE, indices=np.arange(64), y_pos=np.zeros(64))
    with pytest.warns(UserWarning, match="all 64 measurements are zero"):
        out = DEFAULT_SOLVERS[solver_name].solve(acq)
    assert np.all(np.isfinite(out.data)) and not np.any(out.data)


@pytest.mark.parametrize("solver_name", list(DEFAULT_SOLVERS))
def test_one_saturated_pattern_warns_and_stays_finite(solver_name):
    img = _scene(N_SIDE)
    order = ORDERS["zigzag"]().order(N_SIDE)[:128]
    c = fwht2(img).ravel()[order]
    c[17] = 1e12  # a saturated reading
    acq = Acquisition(n=N_SIDE, indices=order, y_pos=c)
    with pytest.warns(UserWarning, match="saturated or corrupted"):
        out = DEFAULT_SOLVERS[solver_name].solve(acq)
    assert np.all(np.isfinite(out.data))


@pytest.mark.parametrize("saturated", [0, 3])
def test_out_of_bound_warning_blames_saturation_only_when_counted(saturated):
    img = _scene(N_SIDE)
    order = ORDERS["zigzag"]().order(N_SIDE)[:128]
    c = fwht2(img).ravel()[order]
    c[17] = 1e12  # out of bounds: noise in dense fog, or a saturated reading
    acq = Acquisition(n=N_SIDE, indices=order, y_pos=c, derived={"saturated_patterns": saturated})
    with pytest.warns(UserWarning) as caught:
        DEFAULT_SOLVERS["fwht"].solve(acq)
    text = " ".join(str(w.message) for w in caught)
    if saturated:
        assert "3 readings at full scale" in text
    else:
        assert "no reading saturated" in text and "saturated or" not in text


@pytest.mark.parametrize("solver_name", list(DEFAULT_SOLVERS))
def test_dc_only_warns_flat_field(solver_name):
    img = _scene(N_SIDE)
    sel = ORDERS["cake_cutting"](ratio=1e-4).select(N_SIDE)
    assert sel.tolist() == [0]
    with pytest.warns(UserWarning, match="only the DC pattern"):
        out = DEFAULT_SOLVERS[solver_name].solve(_acquire(img, sel))
    assert np.all(np.isfinite(out.data))
    np.testing.assert_allclose(out.data, img.mean(), rtol=1e-6, atol=1e-9)


@settings(max_examples=25, deadline=None)
@given(
    scale=st.floats(min_value=0.0, max_value=1e6),
    ratio=st.floats(min_value=0.01, max_value=1.0),
    name=st.sampled_from(["zigzag", "random", "spiral", "variance"]),
)
def test_no_nan_for_extreme_scales(scale, ratio, name):
    img = _scene(8) * scale
    acq = _acquire(img, ORDERS[name](ratio=ratio).select(8))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for solver in (FWHTSolver(), LstsqSolver(), FistaTVSolver(max_iter=10), OMPSolver()):
            assert np.all(np.isfinite(solver.solve(acq).data))


def test_non_finite_measurements_are_replaced_with_a_warning():
    c = fwht2(_scene(8)).ravel()
    c[5] = np.nan
    with pytest.warns(UserWarning, match="non-finite"):
        out = FWHTSolver().solve(Acquisition(n=8, indices=np.arange(64), y_pos=c))
    assert np.all(np.isfinite(out.data))
