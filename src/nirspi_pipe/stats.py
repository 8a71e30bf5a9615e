"""Statistics behind every table cell and every ranking (docs/paper.md, *Statistics*).

Pure functions on numpy arrays and pandas frames (scipy for the t distribution).

**Cell means and their standard errors, clustered by seed.** A table cell pools jobs (objects ×
seeds, × kLux where a table pools the levels). Jobs that share a seed share the detector noise
and the background/fog trajectories in time, so they are not independent: the standard error of
the cell mean is the cluster-robust one with the seed as the cluster (:func:`clustered_mean_se`):
``SE² = G/(G−1) · Σ_g (Σ_{i∈g} (y_i − ȳ))² / N²`` for ``N`` values in ``G`` clusters, which for
equal cluster sizes is exactly ``var(cluster means)/G``. It keeps the correlation of the jobs
within a seed (and treats the objects, a fixed design, as part of each cluster).

**Paired differences.** The scans of one ``(object, seed, kLux)`` see the same noise and the same
trajectories, so ``metric(A) − metric(B)`` is a paired difference. Pairs that share a seed (the
5 and 15 kLux cells of one object and seed, the four objects of one seed) are correlated, so the
difference's standard error is clustered by seed too; its t statistic has ``G − 1`` degrees of
freedom (:func:`paired_difference`).

**Rankings.** All pairwise comparisons between the scans of one cell form one family, corrected
by Holm's step-down method (:func:`holm`). A "better than" claim is made only when it holds after
Holm *and* replicates, with the same sign, on two disjoint seed sets (the first and the second
half of the sorted seeds, :func:`split_seeds`; the experiments run seeds 0–19, so the halves are
0–9 and 10–19): :func:`replicated_claims`.

**Across families.** Holm controls the error within one family (6 pairs) only; a table has many
families (Figure 9: 48 = 4 objects × 4 kLux × 3 scores). Two things bound the sweep-wide error:
the replication rule (the halves use disjoint seeds, so under no true difference a family yields a
claim with probability at most ``α² = 0.0025``; F families, at most ``F·α²`` expected false
claims, 0.12 for Figure 9's 48) and, reported beside it, Holm over *all* the pairs of a table at
once (:func:`across_families`: ``p_holm_all`` on all seeds, ``claim_all`` when it holds in both
halves with the halves' own all-pair Holm), which controls the family-wise error over the whole
table at 5 %.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd
from scipy import stats as _st

__all__ = [
    "ALPHA",
    "PAIR_KEYS",
    "cell_summary",
    "across_families",
    "claims_sentence",
    "family_sentence",
    "clustered_mean_se",
    "holm",
    "paired_difference",
    "pairwise",
    "replicated_claims",
    "split_seeds",
]

#: Family-wise error rate of every ranking (the conventional 5 %).
ALPHA = 0.05
#: Columns that identify one paired sample (present ones are used).
PAIR_KEYS = ("scene", "seed", "illumination.klux")


def clustered_mean_se(values: np.ndarray, clusters: np.ndarray) -> tuple[float, float, int, int]:
    """Mean, cluster-robust standard error, number of values and number of clusters of the finite
    ``values`` (one cluster label per value).

    ``SE² = G/(G−1) · Σ_g (Σ_{i∈g}(y_i − ȳ))² / N²`` (the CR1 sandwich of a mean). With one value
    per cluster it is the ordinary ``s/√N``; with equal cluster sizes, ``s(cluster means)/√G``.
    NaN standard error with fewer than two clusters; ``(nan, nan, 0, 0)`` without finite values.
    """
    y = np.asarray(values, dtype=np.float64).ravel()
    c = np.asarray(clusters).ravel()
    if y.shape != c.shape:
        raise ValueError(f"values {y.shape} and clusters {c.shape} differ in shape")
    keep = np.isfinite(y)
    y, c = y[keep], c[keep]
    n = int(y.size)
    if n == 0:
        return np.nan, np.nan, 0, 0
    mean = float(y.mean())
    _, inverse = np.unique(c, return_inverse=True)
    g = int(inverse.max()) + 1
    if g < 2:
        return mean, np.nan, n, g
    sums = np.bincount(inverse, weights=y - mean, minlength=g)
    var = g / (g - 1) * float(np.sum(sums**2)) / n**2
    return mean, float(np.sqrt(var)), n, g


def cell_summary(frame: pd.DataFrame, value: str, cluster: str = "seed", prefix: str | None = None) -> dict[str, float]:
    """``{p_mean, p_se, p_n, p_clusters}`` of column ``value`` over the rows of one table cell,
    the standard error clustered by column ``cluster`` (each row its own cluster when the frame
    has no such column). ``prefix`` defaults to ``value``."""
    p = value if prefix is None else prefix
    y = frame[value].to_numpy(dtype=np.float64)
    c = frame[cluster].to_numpy() if cluster in frame.columns else np.arange(len(frame))
    mean, se, n, g = clustered_mean_se(y, c)
    return {f"{p}_mean": mean, f"{p}_se": se, f"{p}_n": n, f"{p}_clusters": g}


def _t_p(diff: float, se: float, clusters: int) -> tuple[float, float]:
    if not (np.isfinite(diff) and np.isfinite(se)) or clusters < 2:
        return np.nan, np.nan
    if se == 0:
        return (np.inf if diff != 0 else 0.0), (0.0 if diff != 0 else 1.0)
    t = diff / se
    return float(t), float(2 * _st.t.sf(abs(t), clusters - 1))


def _wide(frame: pd.DataFrame, value: str, by: str, pair_keys: Sequence[str]) -> pd.DataFrame:
    keys = [k for k in pair_keys if k in frame.columns]
    if not keys:
        raise ValueError(f"paired comparison needs at least one of the columns {list(pair_keys)}")
    # pivot_table(index=keys, columns=by, values=value, aggfunc="mean") as its steps: the mean of
    # each (keys, by) group, groups whose mean is NaN dropped, unstacked, all-NaN columns dropped,
    # columns sorted.
    # The same frame (pivot_table would also cast integer means back to integers; the differences
    # are taken as float64 either way) at about half the cost: Figure 9's rankings called it 176
    # times, 3.9 s of the paper sweep's table build under cProfile (issue 42 item 6)
    means = frame.groupby([*keys, by], sort=True)[value].mean().dropna()
    return means.unstack(by).dropna(how="all", axis=1).sort_index(axis=1)


def _diff_from_wide(wide: pd.DataFrame, a: object, b: object, cluster: str) -> dict[str, float]:
    if a not in wide.columns or b not in wide.columns:
        return {"diff": np.nan, "se": np.nan, "n": 0, "clusters": 0, "t": np.nan, "p": np.nan}
    d = (wide[a] - wide[b]).to_numpy(dtype=np.float64)
    names = list(wide.index.names)
    labels = wide.index.get_level_values(cluster).to_numpy() if cluster in names else np.arange(len(wide))
    diff, se, n, g = clustered_mean_se(d, labels)
    t, p = _t_p(diff, se, g)
    return {"diff": diff, "se": se, "n": n, "clusters": g, "t": t, "p": p}


def paired_difference(
    frame: pd.DataFrame,
    value: str,
    a: object,
    b: object,
    by: str = "scan",
    pair_keys: Sequence[str] = PAIR_KEYS,
    cluster: str = "seed",
) -> dict[str, float]:
    """Mean of ``value(a) − value(b)`` over the pairs both have (rows matched on ``pair_keys``,
    ``a`` and ``b`` levels of column ``by``), its standard error clustered by ``cluster``, the
    number of pairs ``n`` and clusters, the t statistic and its two-sided p-value (``G − 1``
    degrees of freedom). NaN where fewer than two clusters have a pair."""
    return _diff_from_wide(_wide(frame, value, by, pair_keys), a, b, cluster)


def holm(p: Sequence[float] | np.ndarray) -> np.ndarray:
    """Holm's step-down adjusted p-values (same order as ``p``). NaN entries stay NaN and do not
    count towards the family size."""
    p = np.asarray(p, dtype=np.float64)
    out = np.full(p.shape, np.nan)
    ok = np.flatnonzero(np.isfinite(p))
    m = ok.size
    if m == 0:
        return out
    order = ok[np.argsort(p[ok], kind="stable")]
    adj = np.minimum(1.0, np.maximum.accumulate((m - np.arange(m)) * p[order]))
    out[order] = adj
    return out


def pairwise(
    frame: pd.DataFrame,
    value: str,
    levels: Sequence[object],
    by: str = "scan",
    pair_keys: Sequence[str] = PAIR_KEYS,
    cluster: str = "seed",
) -> pd.DataFrame:
    """Every pair ``(a, b)`` of ``levels`` (``a`` before ``b``): :func:`paired_difference` of
    ``a − b`` with Holm-adjusted p-values over the family (``p_holm``)."""
    wide = _wide(frame, value, by, pair_keys)
    rows = []
    for i, a in enumerate(levels):
        for b in levels[i + 1 :]:
            rows.append({"a": a, "b": b, **_diff_from_wide(wide, a, b, cluster)})
    out = pd.DataFrame(rows, columns=["a", "b", "diff", "se", "n", "clusters", "t", "p"])
    out["p_holm"] = holm(out["p"].to_numpy()) if len(out) else []
    return out


def split_seeds(seeds: Sequence[int] | np.ndarray) -> tuple[list, list]:
    """The sorted distinct seeds cut into a first and a second half (disjoint; the first half gets
    the smaller half when the count is odd)."""
    s = sorted(pd.unique(pd.Series(list(seeds)).dropna()))
    h = len(s) // 2
    return s[:h], s[h:]


def replicated_claims(
    frame: pd.DataFrame,
    value: str,
    levels: Sequence[object],
    higher_is_better: bool,
    alpha: float = ALPHA,
    by: str = "scan",
    pair_keys: Sequence[str] = PAIR_KEYS,
    cluster: str = "seed",
) -> pd.DataFrame:
    """The pairwise comparisons of ``levels`` on all seeds, on each half of the seeds
    (:func:`split_seeds`) with their own Holm correction, and the claim each supports.

    Columns: ``a, b, diff, se, n, clusters, p, p_holm`` (all seeds), ``diff_1, p_1, p_holm_1``
    and ``diff_2, p_2, p_holm_2`` (the halves), ``higher_is_better``, and ``claim``: ``"a"`` or
    ``"b"`` (the better one) when ``p_holm < alpha`` in *both* halves with the same sign, else
    ``""``. A frame without the ``cluster`` column, or with fewer than four distinct seeds,
    supports no claim.
    """
    full = pairwise(frame, value, levels, by, pair_keys, cluster)
    full["claim"] = ""
    full["higher_is_better"] = bool(higher_is_better)
    for k in (1, 2):
        full[f"diff_{k}"] = np.nan
        full[f"p_{k}"] = np.nan
        full[f"p_holm_{k}"] = np.nan
    if cluster not in frame.columns or frame[cluster].nunique() < 4 or full.empty:
        return full
    halves = split_seeds(frame[cluster])
    for k, seeds in enumerate(halves, start=1):
        part = pairwise(frame[frame[cluster].isin(seeds)], value, levels, by, pair_keys, cluster)
        full[f"diff_{k}"] = part["diff"].to_numpy()
        full[f"p_{k}"] = part["p"].to_numpy()
        full[f"p_holm_{k}"] = part["p_holm"].to_numpy()
    sig = (full["p_holm_1"] < alpha) & (full["p_holm_2"] < alpha)
    same = np.sign(full["diff_1"]) == np.sign(full["diff_2"])
    a_better = (full["diff_1"] > 0) == higher_is_better
    full["claim"] = np.where(sig & same, np.where(a_better, full["a"], full["b"]), "")
    return full


def across_families(claims: pd.DataFrame, alpha: float = ALPHA) -> pd.DataFrame:
    """``claims`` (rows of :func:`replicated_claims` from any number of families, concatenated)
    with Holm over *all* its pairs at once: ``p_holm_all`` (all seeds), ``p_holm_all_1`` and
    ``p_holm_all_2`` (each seed half), and ``claim_all``: the better scan where both halves'
    all-pair Holm p are below ``alpha`` with the same sign, else ``""``. A copy; the per-family
    columns are kept."""
    out = claims.copy()
    if out.empty:
        for c in ("p_holm_all", "p_holm_all_1", "p_holm_all_2", "claim_all"):
            out[c] = pd.Series(dtype=object if c == "claim_all" else float)
        return out
    out["p_holm_all"] = holm(out["p"].to_numpy(dtype=np.float64))
    for k in (1, 2):
        col = f"p_{k}"
        raw = out[col].to_numpy(dtype=np.float64) if col in out else np.full(len(out), np.nan)
        out[f"p_holm_all_{k}"] = holm(raw)
    sig = (out["p_holm_all_1"] < alpha) & (out["p_holm_all_2"] < alpha)
    same = np.sign(out["diff_1"]) == np.sign(out["diff_2"])
    hib = out["higher_is_better"].astype(bool) if "higher_is_better" in out else pd.Series(True, index=out.index)
    a_better = (out["diff_1"] > 0) == hib
    out["claim_all"] = np.where(sig & same, np.where(a_better, out["a"], out["b"]), "")
    return out


def family_sentence(claims: pd.DataFrame, family_size: int = 6, alpha: float = ALPHA) -> str:
    """One sentence on what is controlled across the families of ``claims`` (the output of
    :func:`across_families`): the number of families and pairs, the replication rule's bound on
    expected false claims (``F·α²``), and the all-pair Holm result (smallest all-seed p, claims)."""
    if claims.empty or "p_holm_all" not in claims:
        return "No pairwise comparison."
    pairs = len(claims)
    families = max(1, round(pairs / family_size))
    smallest = float(np.nanmin(claims["p_holm_all"])) if claims["p_holm_all"].notna().any() else np.nan
    n_all = int((claims["claim_all"] != "").sum())
    return (
        f"Holm controls each family of {family_size} pairs at {alpha:g}; this table has {families} families "
        f"({pairs} pairs). Across them, a claim needs both disjoint seed halves, so with no true difference at most "
        f"{families} × {alpha:g}² = {families * alpha**2:.2g} false claims are expected; Holm over all {pairs} pairs "
        f"at once (`p_holm_all` in the rankings CSV): smallest all-seed p {smallest:.3g}, "
        f"{n_all} claim{'s' if n_all != 1 else ''} holding in both halves."
    )


def claims_sentence(claims: pd.DataFrame, label: dict | None = None) -> str:
    """The replicated claims of :func:`replicated_claims` as one sentence (``"none"`` when there
    are none), e.g. ``"Spiral better than Basic (+5.1 ± 1.2)"``, with the all-seed difference
    ``a − b`` of the pair as compared and its clustered standard error."""
    label = label or {}
    parts = []
    for r in claims.itertuples():
        if not r.claim:
            continue
        win, lose = (r.a, r.b) if r.claim == r.a else (r.b, r.a)
        parts.append(
            f"{label.get(win, win)} better than {label.get(lose, lose)} "
            f"({label.get(r.a, r.a)} − {label.get(r.b, r.b)} = {r.diff:+.3g} ± {r.se:.2g})"
        )
    return "; ".join(parts) if parts else "none"
