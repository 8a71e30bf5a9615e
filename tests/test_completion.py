"""solver=completion (issue 36): the linear MMSE completion under a stationary power-law prior."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nirspi_pipe.errors import ConfigError, NirspiError
from nirspi_pipe.patterns import orders as O
from nirspi_pipe.patterns.hadamard import fwht, fwht2
from nirspi_pipe.solvers import completion as C
from nirspi_pipe.solvers.fwht import FWHTSolver
from nirspi_pipe.types import Acquisition

ROOT = Path(__file__).resolve().parents[1]
PRIOR = C.PowerLawPrior(alpha=3.0, f0=1.5, mean=0.3)


def dense_covariance(prior: C.PowerLawPrior, n: int) -> np.ndarray:
    """``C`` ``(N, N)`` straight from the definition: the covariance function (inverse FFT of the
    ``2n`` torus spectrum, normalised at lag 0) read at every pixel pair's lag."""
    c = np.real(np.fft.ifft2(prior.spectrum(n)))
    c /= c[0, 0]
    i, j = np.divmod(np.arange(n * n), n)
    return c[(i[:, None] - i[None, :]) % (2 * n), (j[:, None] - j[None, :]) % (2 * n)]


def smooth_image(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:n, 0:n] / n
    img = 0.4 + 0.2 * np.sin(2 * np.pi * (xx + 0.3 * yy)) + 0.1 * np.cos(6 * yy)
    return img + 0.01 * rng.standard_normal((n, n))


def acquisition(img: np.ndarray, idx: np.ndarray, sigma: float = 0.0, seed: int = 0) -> Acquisition:
    n = img.shape[0]
    y = fwht(img.ravel())[idx] + sigma * np.random.default_rng(seed).standard_normal(idx.size)
    return Acquisition(n=n, indices=idx, y_pos=y, derived={"declared_noise_sigma": sigma})


def test_covariance_apply_is_the_stationary_matrix_and_positive_semidefinite():
    n = 8
    dense = dense_covariance(PRIOR, n)
    x = np.random.default_rng(1).standard_normal((5, n, n))
    got = PRIOR.covariance_apply(x).reshape(5, -1)
    np.testing.assert_allclose(got, x.reshape(5, -1) @ dense, atol=1e-12)
    np.testing.assert_allclose(dense, dense.T, atol=1e-14)
    assert np.linalg.eigvalsh(dense).min() > -1e-12


@pytest.mark.parametrize("sigma", [0.5, 3.0])
@pytest.mark.parametrize("order", ["zigzag", "random"])
def test_matches_the_dense_linear_mmse_formula(sigma, order):
    """x̂ = μ + sCAᵀ(sACAᵀ + σ²I)⁻¹(y − Aμ), with the matrices written out (8², any order)."""
    n = 8
    idx = O.ORDERS[order](0.3).select(n)
    img = smooth_image(n)
    acq = acquisition(img, idx, sigma)
    y = acq.coefficients()
    s = 0.02
    got, info = C.complete(n, idx, y, sigma, PRIOR, scale=s)
    h = fwht(np.eye(n * n))  # H_N, rows = patterns
    a = h[idx]
    cov = s * dense_covariance(PRIOR, n)
    mu = np.full(n * n, y[list(idx).index(0)] / n**2 if 0 in idx else PRIOR.mean)
    want = mu + cov @ a.T @ np.linalg.solve(a @ cov @ a.T + sigma**2 * np.eye(idx.size), y - a @ mu)
    np.testing.assert_allclose(got.ravel(), want, atol=1e-4 * np.abs(want).max())
    assert info["prior_scale"] == s


@pytest.mark.parametrize("order", ["zigzag", "cake_cutting", "random", "basic"])
def test_noise_free_keeps_every_measured_coefficient(order):
    n = 16
    idx = O.ORDERS[order](0.25).select(n)
    img = smooth_image(n)
    out = C.CompletionSolver(noise=0.0, alpha=PRIOR.alpha, f0=PRIOR.f0).solve(acquisition(img, idx))
    y = fwht(img.ravel())[idx]
    np.testing.assert_allclose(fwht2(out.data).ravel()[idx], y, atol=1e-3 * np.abs(y).max())


def test_full_noise_free_sampling_is_exact():
    n = 8
    img = smooth_image(n)
    idx = O.Zigzag(1.0).select(n)
    out = C.CompletionSolver(noise=0.0).solve(acquisition(img, idx))
    np.testing.assert_allclose(out.data, img, atol=1e-4)


def test_completion_beats_zero_filling_on_a_smooth_image():
    n = 32
    img = smooth_image(n)
    for order in ("zigzag", "cake_cutting"):
        acq = acquisition(img, O.ORDERS[order](0.1).select(n))
        err_c = np.linalg.norm(C.CompletionSolver().solve(acq).data - img)
        err_z = np.linalg.norm(FWHTSolver().solve(acq).data - img)
        assert err_c < 0.7 * err_z


def test_noise_aware_denoises_the_measured_coefficients():
    """With noise, trusting the data (σ = 0) is worse than the declared σ, and both beat
    zero-filling; the declared σ is what ``noise: auto`` reads."""
    n = 32
    img = smooth_image(n)
    idx = O.Zigzag(0.5).select(n)
    acq = acquisition(img, idx, sigma=4.0)
    auto = C.CompletionSolver().solve(acq)
    exact = C.CompletionSolver(noise=0.0).solve(acq)
    zero = FWHTSolver().solve(acq)
    e = {k: np.linalg.norm(v.data - img) for k, v in {"auto": auto, "exact": exact, "zero": zero}.items()}
    assert auto.info["noise_method"] == "declared" and auto.info["noise_sigma"] == pytest.approx(4.0)
    assert e["auto"] < 0.5 * e["exact"] and e["auto"] < 0.5 * e["zero"]


@settings(max_examples=8, deadline=None)
@given(st.floats(0.001, 10.0), st.integers(0, 2**16))
def test_scale_is_fitted_by_marginal_likelihood(s_true, seed):
    """Images drawn from the prior at amplitude s: the fitted s is within 25 % of it."""
    n = 16
    rng = np.random.default_rng(seed)
    idx = O.Zigzag(0.5).select(n)
    w, v = np.linalg.eigh(dense_covariance(PRIOR, n))
    img = 0.5 + (v * np.sqrt(np.maximum(w, 0) * s_true)) @ rng.standard_normal(n * n)
    y = fwht(img)[idx] + 0.1 * rng.standard_normal(idx.size)
    _, info = C.complete(n, idx, y, 0.1, PRIOR)
    assert info["prior_scale"] == pytest.approx(s_true, rel=0.25)


def test_maps_are_cached_and_the_cache_is_bounded(monkeypatch):
    n = 8
    idx = O.Zigzag(0.5).select(n)
    C.clear_cache()
    first = C.completion_maps(n, idx, PRIOR)
    assert C.completion_maps(n, idx, PRIOR) is first
    assert first.vt.shape == first.v2.shape == (idx.size, idx.size) and first.vt.dtype == np.float32
    assert first.nbytes == pytest.approx(2 * idx.size * idx.size * 4, rel=0.05)
    monkeypatch.setattr(C._CACHE, "budget", first.nbytes + 1)
    other = C.completion_maps(n, O.CakeCutting(0.5).select(n), PRIOR)
    assert C.completion_maps(n, O.CakeCutting(0.5).select(n), PRIOR) is other
    assert C.completion_maps(n, idx, PRIOR) is not first  # evicted, rebuilt


@pytest.mark.parametrize(
    ("kwargs", "key"),
    [
        ({"noise": "loud"}, "noise"),
        ({"noise": -1.0}, "noise"),
        ({"alpha": -1.0}, "alpha"),
        ({"f0": 0.0}, "f0"),
        ({"refine": "l1"}, "refine"),
    ],
)
def test_bad_config_names_the_key(kwargs, key):
    with pytest.raises(ConfigError) as err:
        C.CompletionSolver(**kwargs)
    assert err.value.key == key


def test_explicit_patterns_are_refused():
    acq = Acquisition(n=4, indices=np.arange(4), y_pos=np.ones(4), patterns=np.ones((4, 16)))
    with pytest.raises(NirspiError, match="solver=completion needs a Hadamard acquisition"):
        C.CompletionSolver().solve(acq)


def test_shipped_prior_and_its_training_set_are_disjoint_from_the_benchmarks():
    """The prior loads, and none of its training images is one of experiments/heldout's 24."""
    import ast

    prior = C.default_prior()
    assert 0 < prior.alpha < 6 and prior.f0 > 0 and 0 < prior.mean < 1
    src = (ROOT / "experiments" / "heldout" / "heldout_cs.py").read_text()
    names: set[str] = set()
    for node in ast.walk(ast.parse(src)):
        if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", "") in ("IMAGES", "TUNING"):
            names |= {e.value for e in node.value.elts}  # type: ignore[attr-defined]
    assert len(names) == 24
    names.add("cat")  # scikit-image's cat is chelsea
    lines = (ROOT / "experiments" / "prior" / "training.txt").read_text().splitlines()
    training = [ln.split(":")[1].split(".")[0] for ln in lines if ln.strip() and not ln.startswith("#")]
    assert training and not set(training) & names


@pytest.mark.parametrize("alpha_true", [2.0, 5.0])
def test_auto_alpha_picks_the_exponent_the_image_was_drawn_from(alpha_true):
    """Images drawn from a power-law prior: of the exponents {2, 5}, the marginal likelihood picks
    the one they were drawn from (3 seeds each)."""
    n = 16
    idx = O.Zigzag(0.25).select(n)
    candidates = [C.PowerLawPrior(a, PRIOR.f0, PRIOR.mean) for a in (2.0, 5.0)]
    w, v = np.linalg.eigh(dense_covariance(C.PowerLawPrior(alpha_true, PRIOR.f0), n))
    for seed in range(3):
        img = 0.5 + (v * np.sqrt(np.maximum(w, 0) * 0.01)) @ np.random.default_rng(seed).standard_normal(n * n)
        y = fwht(img)[idx] + 0.05 * np.random.default_rng(seed + 10).standard_normal(idx.size)
        _, info = C.complete(n, idx, y, 0.05, candidates)
        assert info["alpha"] == alpha_true


def test_auto_alpha_chooses_among_the_shipped_exponents():
    acq = acquisition(smooth_image(16), O.Zigzag(0.25).select(16))
    out = C.CompletionSolver().solve(acq)
    assert out.info["alpha"] in C.default_alphas() and len(C.default_alphas()) == 3


def test_leave_one_out_ratio_matches_brute_force():
    """``_loo_ratio``'s closed form equals predicting each measured coefficient from the others by
    the Gaussian conditional mean, one at a time (8², noisy)."""
    n, sigma, s = 8, 2.0, 0.03
    idx = O.Zigzag(0.4).select(n)
    img = smooth_image(n, seed=3)
    r = fwht(img.ravel())[idx] + sigma * np.random.default_rng(4).standard_normal(idx.size)
    r[0] = 0.0  # DC removed (μ at the measured mean)
    maps = C.completion_maps(n, idx, PRIOR)
    z = (maps.vt @ r.astype(np.float32)).astype(np.float64)
    fit = C._Fit(maps, z, s, sigma**2, 0.0)
    live = np.arange(idx.size) != 0
    denom = s * maps.lam + sigma**2
    k_r = (maps.vt.T @ (z / denom).astype(np.float32)).astype(np.float64)
    got = C._loo_ratio(fit, denom, live, r, k_r)
    a = fwht(np.eye(n * n))[idx]
    k = s * a @ dense_covariance(PRIOR, n) @ a.T + sigma**2 * np.eye(idx.size)
    loo = []
    for i in np.flatnonzero(live):
        o = np.arange(idx.size) != i
        loo.append(r[i] - k[i, o] @ np.linalg.solve(k[np.ix_(o, o)], r[o]))
    want = np.sum(np.square(loo)) / np.sum(r[live] ** 2)
    assert got == pytest.approx(want, rel=1e-3)


def test_guard_returns_zero_filling_on_a_walsh_sparse_image():
    """A checkerboard aligned with the patterns is a few Walsh coefficients: the power law smears
    it, the white prior predicts the measurements better, and the guard returns the zero-filled
    image (noise-free: exactly ``fwht``'s)."""
    n = 32
    yy, xx = np.mgrid[0:n, 0:n]
    img = 0.2 + 0.6 * (((yy // 4) + (xx // 4)) % 2)
    acq = acquisition(img, O.Zigzag(0.25).select(n))
    guarded = C.CompletionSolver().solve(acq)
    plain = C.CompletionSolver(guard=False).solve(acq)
    zero = FWHTSolver().solve(acq).data
    assert guarded.info["loo_ratio"] > 1 and guarded.info["alpha"] == 0.0
    np.testing.assert_allclose(guarded.data, zero, atol=1e-9)
    assert np.linalg.norm(plain.data - img) > np.linalg.norm(zero - img)


@pytest.mark.parametrize("sigma", [0.0, 0.05])
def test_refine_tv_starts_from_the_completion_and_only_lowers_fista_tvs_objective(sigma):
    """``refine: tv`` is ``fista_tv`` (monotone FISTA) started from the completion estimate: at the
    weight it chose, its objective ``½‖Ax − y‖²/N + λ TV(x)`` is no higher than the completion's,
    and the completion's record is kept under ``completion_*``."""
    from nirspi_pipe.solvers.fista_tv import total_variation

    n = 16
    img = smooth_image(n)
    idx = O.Zigzag(0.25).select(n)
    acq = acquisition(img, idx, sigma)
    start = C.CompletionSolver(noise=sigma).solve(acq)
    out = C.CompletionSolver(noise=sigma, refine="tv").solve(acq)
    y = acq.y_pos
    lam = float(out.info["lam"])
    assert out.info["lam_rule"] == "cv" and lam >= 0

    def objective(x: np.ndarray) -> float:
        r = fwht(x.ravel())[idx] - y
        return 0.5 * float(r @ r) / n**2 + lam * float(total_variation(x[None])[0])

    assert objective(out.data) <= objective(start.data) + 1e-12
    assert out.info["completion_alpha"] == start.info["alpha"]
    # the lower hold-out score wins: the completion itself, or TV from it
    own, tv = out.info["cv_score_completion"], out.info["cv_score"]
    assert out.info["refine_chosen"] == ("completion" if own <= tv else "tv")
    if own <= tv:
        np.testing.assert_array_equal(out.data, start.data)


def test_fista_tv_starts_where_it_is_told():
    """``FistaTVSolver.solve(acq, start=…)``: with λ = 0 one gradient step (step 1/L = 1 on the
    Hadamard path) from ``x0`` sets the measured coefficients to the data and keeps ``x0``'s
    unmeasured ones, so the result is exactly the start's completion by the data."""
    from nirspi_pipe.solvers.fista_tv import FistaTVSolver

    n = 16
    img = smooth_image(n)
    idx = O.Zigzag(0.25).select(n)
    acq = acquisition(img, idx)
    x0 = smooth_image(n, seed=3)[::-1]
    out = FistaTVSolver(lam=0.0, max_iter=1).solve(acq, start=lambda rows: x0)
    coef = fwht(x0.ravel())
    coef[idx] = acq.y_pos
    np.testing.assert_allclose(out.data.ravel(), fwht(coef) / n**2, atol=1e-9)
    assert not np.allclose(out.data, FistaTVSolver(lam=0.0, max_iter=1).solve(acq).data, atol=1e-3)


def _oracle_module(monkeypatch):
    """experiments/heldout/oracle_bound.py (it imports its sibling heldout_cs)."""
    import importlib.util

    folder = ROOT / "experiments" / "heldout"
    monkeypatch.syspath_prepend(str(folder))
    spec = importlib.util.spec_from_file_location("oracle_bound", folder / "oracle_bound.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, module)  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def test_oracle_spectrum_prior_is_the_power_law_when_given_its_spectrum(monkeypatch):
    """The oracle script's SpectrumPrior, handed the power law's own torus spectrum, gives the
    completion that PowerLawPrior gives (same maps up to float32), noise-free and with noise."""
    ob = _oracle_module(monkeypatch)
    n = 16
    spec = PRIOR.spectrum(n)
    same = ob.SpectrumPrior(name="test-power-law", spectrum=spec / spec.mean(), mean=PRIOR.mean)
    img = smooth_image(n, 3)
    idx = O.Zigzag(0.3).select(n)
    y = fwht2(img).ravel()[idx]
    for sigma in (0.0, 0.5):
        a = C.complete(n, idx, y, sigma, PRIOR)[0]
        b = C.complete(n, idx, y, sigma, same)[0]
        np.testing.assert_allclose(b, a, atol=1e-5)


def test_oracle_own_prior_is_positive_definite_and_exact_on_its_image(monkeypatch):
    """The image's own spectrum: its ``n × n`` covariance is positive definite (the floor), its
    ring average is constant on rings, and with every coefficient measured the completion under
    either returns the image (noise-free)."""
    ob = _oracle_module(monkeypatch)
    n = 8
    img = smooth_image(n, 5)
    own = ob.own_prior("test-own", img)
    radial = ob.radial_prior(own)
    for prior in (own, radial):
        cov = prior.covariance_apply(np.eye(n * n).reshape(-1, n, n)).reshape(n * n, n * n)
        assert np.linalg.eigvalsh(0.5 * (cov + cov.T)).min() > 0
        idx = np.arange(n * n)
        np.testing.assert_allclose(C.complete(n, idx, fwht2(img).ravel(), 0.0, prior)[0], img, atol=1e-6)
    f = np.fft.fftfreq(2 * n) * n
    ring = np.rint(np.hypot(f[:, None], f[None, :]))
    for r in np.unique(ring):
        assert np.ptp(radial.spectrum[ring == r]) < 1e-12 * radial.spectrum.max()


@pytest.mark.parametrize("sigma", [0.0, 0.3])
def test_image_is_the_mmse_map_applied_to_the_data(sigma):
    """The image is ``μ + G·(s z / (sλ + σ²))`` with the explicit ``N × m`` map ``G = C Aᵀ V`` (what
    the solver cached until it applied ``C Aᵀ`` by transforms instead): equal to float32 rounding."""
    n = 16
    idx = O.CakeCutting(0.3).select(n)
    img = smooth_image(n, 7)
    y = fwht2(img).ravel()[idx] + sigma * np.random.default_rng(8).standard_normal(idx.size)
    got, info = C.complete(n, idx, y, sigma, PRIOR)
    maps = C.completion_maps(n, idx, PRIOR)
    mu = y[0] / (n * n)
    r = y.copy()
    r[0] -= mu * n * n
    z = maps.vt.astype(np.float64) @ r
    s = info["prior_scale"]
    noise2 = max(sigma**2, C.EXACT_FLOOR * s * float(maps.lam[-1]))
    a = fwht(np.eye(n * n))[idx]
    g = dense_covariance(PRIOR, n) @ a.T @ maps.vt.T.astype(np.float64)
    want = mu + g @ (s * z / (s * maps.lam + noise2))
    np.testing.assert_allclose(got.ravel(), want, atol=1e-4 * np.abs(want).max())
