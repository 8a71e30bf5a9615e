"""nirspi_pipe.stats on synthetic data whose answer is known: clustered standard errors against
their analytic values, Holm's adjusted p-values by hand, the false-claim rate of a null effect over
many simulated data sets (bounded loops), and the power to find and replicate a real one."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from nirspi_pipe.stats import (
    across_families,
    claims_sentence,
    clustered_mean_se,
    family_sentence,
    holm,
    paired_difference,
    pairwise,
    replicated_claims,
    split_seeds,
)

SCANS = ["basic", "hilbert", "zigzag", "spiral"]
SCENES = ["sphere", "torus", "cube", "u_shape"]


def _frame(rng, n_seeds, effects, tau, sigma, klux=(5.0, 15.0), object_spread=10.0):
    """One synthetic sweep: value = object level + scan effect + a seed×scan term shared by every
    object and kLux of that seed (sd ``tau``) + independent job noise (sd ``sigma``)."""
    obj = rng.normal(0, object_spread, len(SCENES))
    w = rng.normal(0, tau, (n_seeds, len(SCANS)))
    rows = []
    for j, scan in enumerate(SCANS):
        for s, scene in enumerate(SCENES):
            for seed in range(n_seeds):
                for k in klux:
                    rows.append((scan, scene, seed, k, obj[s] + effects[j] + w[seed, j]))
    df = pd.DataFrame(rows, columns=["scan", "scene", "seed", "illumination.klux", "value"])
    df["value"] += rng.normal(0, sigma, len(df))
    return df


def test_clustered_se_equal_clusters_is_se_of_cluster_means():
    rng = np.random.default_rng(1)
    y = rng.normal(size=(7, 3))
    mean, se, n, g = clustered_mean_se(y.ravel(), np.repeat(np.arange(7), 3))
    assert (n, g) == (21, 7)
    assert mean == pytest.approx(y.mean())
    assert se == pytest.approx(y.mean(axis=1).std(ddof=1) / np.sqrt(7), rel=1e-12)
    # one value per cluster: the ordinary s/√N
    _, se1, _, _ = clustered_mean_se(y.ravel(), np.arange(21))
    assert se1 == pytest.approx(y.ravel().std(ddof=1) / np.sqrt(21), rel=1e-12)
    # fewer than two clusters: no standard error; non-finite values are dropped
    assert np.isnan(clustered_mean_se(np.ones(3), np.zeros(3))[1])
    assert clustered_mean_se(np.array([1.0, np.nan, 3.0]), np.arange(3))[:1] == (2.0,)
    with pytest.raises(ValueError, match="differ in shape"):
        clustered_mean_se(np.ones(3), np.zeros(2))


def test_clustered_se_matches_analytic_for_correlated_pairs():
    """Two paired differences per seed (5 and 15 kLux) correlated at r = 0.81, the correlation the
    issue measured: Var(mean) = σ²(1 + r)/(2G). The clustered SE recovers it; treating the pairs as
    independent gives σ²/(2G), √1.81 = 1.35× too small."""
    rng = np.random.default_rng(2)
    g, r, reps = 20, 0.81, 400
    cov = np.array([[1.0, r], [r, 1.0]])
    chol = np.linalg.cholesky(cov)
    analytic = (1 + r) / (2 * g)
    means, se2, naive2 = [], [], []
    labels = np.repeat(np.arange(g), 2)
    for _ in range(reps):
        d = (rng.normal(size=(g, 2)) @ chol.T).ravel()
        m, se, _, _ = clustered_mean_se(d, labels)
        means.append(m)
        se2.append(se**2)
        naive2.append(clustered_mean_se(d, np.arange(d.size))[1] ** 2)
    assert np.var(means) == pytest.approx(analytic, rel=0.2)  # the estimator's true spread
    assert np.mean(se2) == pytest.approx(analytic, rel=0.1)  # the clustered SE estimates it
    assert np.sqrt(np.mean(se2) / np.mean(naive2)) == pytest.approx(np.sqrt(1 + r), rel=0.08)


def test_holm_by_hand():
    p = [0.01, 0.04, 0.03, 0.005]
    # sorted 0.005, 0.01, 0.03, 0.04 -> 4·0.005, 3·0.01, 2·0.03, max(1·0.04, 0.06)
    np.testing.assert_allclose(holm(p), [0.03, 0.06, 0.06, 0.02])
    out = holm([0.02, np.nan, 0.5])
    assert np.isnan(out[1])
    np.testing.assert_allclose(out[[0, 2]], [0.04, 0.5])
    assert holm([0.9, 0.8]).max() <= 1.0


def test_paired_difference_on_a_frame():
    rng = np.random.default_rng(3)
    df = _frame(rng, 6, [0, 0, 0, 2.0], tau=1.0, sigma=0.5)
    out = paired_difference(df, "value", "spiral", "basic")
    wide = df.pivot_table(index=["scene", "seed", "illumination.klux"], columns="scan", values="value")
    d = (wide["spiral"] - wide["basic"]).groupby(level="seed").mean()
    assert out["n"] == 4 * 6 * 2 and out["clusters"] == 6
    assert out["diff"] == pytest.approx(d.mean())
    assert out["se"] == pytest.approx(d.std(ddof=1) / np.sqrt(6))
    assert 0 <= out["p"] <= 1


@pytest.mark.slow  # 200 simulated sweeps: 25 s of CPU (pandas in nirspi_pipe.stats)
def test_null_effect_not_claimed_at_more_than_the_nominal_rate():
    """No scan effect, a seed-shared term as large as the job noise: over 200 simulated sweeps of
    20 seeds, the clustered, Holm-corrected pairwise family rejects at most at the nominal 5 % (plus
    Monte Carlo slack), replicated claims are rarer still, and the naive test that treats the pairs
    as independent rejects far more often (so this test can fail)."""
    rng = np.random.default_rng(4)
    reps = 200
    fwer = naive = claimed = 0
    for _ in range(reps):
        df = _frame(rng, 20, [0, 0, 0, 0], tau=1.0, sigma=1.0)
        fwer += bool((pairwise(df, "value", SCANS)["p_holm"] < 0.05).any())
        naive += bool((pairwise(df, "value", SCANS, cluster="none")["p_holm"] < 0.05).any())
        claimed += bool((replicated_claims(df, "value", SCANS, higher_is_better=True)["claim"] != "").any())
    slack = 3 * np.sqrt(0.05 * 0.95 / reps)
    assert fwer / reps <= 0.05 + slack
    assert claimed / reps <= 0.05
    assert naive / reps > 0.3


def test_real_effect_is_claimed_and_replicated_in_the_right_direction():
    rng = np.random.default_rng(5)
    df = _frame(rng, 20, [0, 0, 0, 1.5], tau=0.5, sigma=0.5)
    c = replicated_claims(df, "value", SCANS, higher_is_better=True)
    won = c[c["claim"] != ""]
    assert set(won["claim"]) == {"spiral"} and len(won) == 3
    assert "Spiral better than Basic" in claims_sentence(c, {"spiral": "Spiral", "basic": "Basic"})
    # the same data as a cost (lower is better): Spiral is now the worst of the four
    c2 = replicated_claims(df, "value", SCANS, higher_is_better=False)
    assert set(c2.loc[c2["claim"] != "", "claim"]) == {"basic", "hilbert", "zigzag"}
    # an effect present in one half of the seeds only is not claimed
    half = df.copy()
    half.loc[(half["scan"] == "spiral") & (half["seed"] >= 10), "value"] -= 1.5
    assert (replicated_claims(half, "value", SCANS, higher_is_better=True)["claim"] == "").all()


def test_too_few_seeds_support_no_claim():
    rng = np.random.default_rng(6)
    df = _frame(rng, 3, [0, 0, 0, 50.0], tau=0.1, sigma=0.1)
    assert (replicated_claims(df, "value", SCANS, higher_is_better=True)["claim"] == "").all()
    assert claims_sentence(replicated_claims(df, "value", SCANS, higher_is_better=True)) == "none"


def test_split_seeds_is_disjoint_and_covers():
    a, b = split_seeds([3, 1, 0, 2, 2, 19, 10])
    assert a == [0, 1, 2] and b == [3, 10, 19]
    assert split_seeds(range(20)) == (list(range(10)), list(range(10, 20)))


def test_across_families_is_holm_over_all_pairs_and_never_claims_more():
    """Holm over every pair of many families is stricter than within each: p_holm_all ≥ p_holm
    row by row, so every all-pair claim is also a per-family claim; a strong effect survives it,
    and 48 null families (Figure 9's count) give no all-pair claim (issue 34)."""
    rng = np.random.default_rng(6)
    fams = []
    for f in range(48):
        effects = [0, 0, 0, 1.5] if f == 0 else [0, 0, 0, 0]
        c = replicated_claims(_frame(rng, 20, effects, tau=0.5, sigma=0.5), "value", SCANS, higher_is_better=True)
        c.insert(0, "family", f)
        fams.append(c)
    claims = across_families(pd.concat(fams, ignore_index=True))
    assert len(claims) == 288
    np.testing.assert_allclose(claims["p_holm_all"], holm(claims["p"].to_numpy()))
    assert (claims["p_holm_all"] >= claims["p_holm"] - 1e-15).all()
    assert (claims["p_holm_all_1"] >= claims["p_holm_1"] - 1e-15).all()
    all_claims = claims[claims["claim_all"] != ""]
    assert (all_claims["claim_all"] == all_claims["claim"]).all()
    assert set(all_claims["family"]) == {0} and set(all_claims["claim_all"]) == {"spiral"}
    text = family_sentence(claims)
    assert "48 families (288 pairs)" in text and "48 × 0.05² = 0.12" in text
    assert f"{len(all_claims)} claim" in text


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 60), st.floats(0.0, 0.5))
def test_wide_is_pivot_tables_mean(seed: int, rows: int, nan_share: float) -> None:
    """``stats._wide`` (groupby + unstack, issue 42 item 6) is ``pivot_table(aggfunc="mean")``:
    the same rows, columns, order and values, with NaN values, missing pairs, duplicate rows
    and all-NaN scans."""
    from nirspi_pipe.stats import _wide

    rng = np.random.default_rng(seed)
    frame = pd.DataFrame(
        {
            "scene": rng.choice(["sphere", "torus"], rows),
            "seed": rng.integers(0, 4, rows),
            "illumination.klux": rng.choice([5.0, 15.0], rows),
            "scan": rng.choice(["basic", "hilbert", "zigzag"], rows),
            "v": np.where(rng.random(rows) < nan_share, np.nan, rng.normal(size=rows)),
        }
    )
    frame.loc[frame["scan"] == "zigzag", "v"] = np.nan if seed % 2 else frame["v"]
    keys = ["scene", "seed", "illumination.klux"]
    expected = frame.pivot_table(index=keys, columns="scan", values="v", aggfunc="mean")
    got = _wide(frame, "v", "scan", keys)
    pd.testing.assert_frame_equal(got, expected.astype(np.float64), check_exact=True)
