"""experiments/shapes/anchor_bound.py (issue 44): the bound on the chamfer targets that four iToF
spots allow. Its arithmetic against brute force, and one real chamfer curve at 16²."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from conftest import load_script

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bound():
    yield from load_script(ROOT / "experiments" / "shapes" / "anchor_bound.py", "shapes_anchor_bound")


@settings(max_examples=80, deadline=None)
@given(st.lists(st.tuples(st.floats(-9.0, 9.0), st.floats(0.0, 4.0)), min_size=1, max_size=4), st.floats(0.1, 1.0))
def test_set_length_never_underestimates_a_union_of_intervals(bound, intervals, step):
    """The length read off the grid bounds the true length of the sampled set from above, for sets
    whose every piece is at least a step wide (a piece between two grid points is not seen: the
    script's docstring states this assumption)."""
    intervals = [(a, w + step) for a, w in intervals]
    grid = np.arange(-10.0, 16.0 + step / 2, step)
    inside = np.zeros(len(grid), dtype=bool)
    for a, w in intervals:
        inside |= (grid >= a) & (grid <= a + w)
    lo = np.array(sorted(intervals))
    true_length = 0.0  # the union's length
    end = -np.inf
    for a, w in lo:
        b = a + w
        if b > end:
            true_length += b - max(a, end)
            end = b
    assert bound.set_length(inside, step) >= true_length - 1e-9
    assert bound.set_length(inside, step) <= inside.sum() * step + len(intervals) * step + 1e-9


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.floats(-20.0, 20.0), st.floats(0.0, 5.0)), min_size=1, max_size=3), st.floats(0.5, 8.0))
def test_no_set_of_a_length_holds_more_gaussian_mass_than_the_centred_interval(bound, intervals, sigma):
    """Anderson's lemma, the step the bound rests on, checked on unions of up to three intervals."""
    pts = sorted((a, a + w) for a, w in intervals)
    merged: list[list[float]] = []
    for a, b in pts:
        if merged and a <= merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], b)
        else:
            merged.append([a, b])
    mass = sum(stats.norm.cdf(b, scale=sigma) - stats.norm.cdf(a, scale=sigma) for a, b in merged)
    length = sum(b - a for a, b in merged)
    assert mass <= bound.success_probability(length, sigma) + 1e-12


def test_target_bound_is_both_conditions(bound):
    assert bound.target_bound(1.0, 1.0, 10) == pytest.approx(1.0)
    assert bound.target_bound(0.0, 1.0, 10) == 0.0  # no seed within 2 mm: the median cannot be
    assert bound.target_bound(1.0, 0.5, 10) == pytest.approx(0.5**10)
    # at least 5 of 10 seeds within 2 mm, each with probability 0.3
    assert bound.target_bound(0.3, 1.0, 10) == pytest.approx(float(stats.binom.sf(4, 10, 0.3)))


def test_the_iToF_default_is_four_spots_at_one_centimetre(bound):
    sigma, spots = bound.itof_sigma_m([])
    assert spots == 4 and sigma == pytest.approx(0.01)
    assert bound.itof_sigma_m(["itof.averaging_s=8"])[0] == pytest.approx(0.0025)


def test_a_real_curve_at_16(bound, tmp_path):
    """The exact sphere scores its floor at δ = 0, and worse the farther it is moved."""
    from nirspi_pipe.types import Camera

    model = bound.targets.metric_floor.scene_model("sphere", tmp_path)
    c = bound.chamfer_curve(model, Camera(16), np.array([0.0, 0.002, 0.006, -0.006]))
    floor = bound.targets.metric_floor.scores(model, Camera(16))["chamfer_mm"]
    assert c[0] == pytest.approx(floor)
    assert c[0] < c[1] < c[2] and c[0] < c[3]
