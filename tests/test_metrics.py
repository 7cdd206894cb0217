"""Metric definitions (torcsrl.metrics) on hand-made tables with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from torcsrl import metrics as M


# ------------------------------------------------------------------------------- scalars
def test_normalized_return_scalar_array_and_undefined_scale():
    assert M.normalized_return(60.0, 10.0, 110.0) == pytest.approx(0.5)
    assert M.normalized_return(110.0, 10.0, 110.0) == pytest.approx(1.0)
    assert M.normalized_return(0.0, 10.0, 110.0) == pytest.approx(-0.1)  # worse than random
    np.testing.assert_allclose(M.normalized_return(np.array([10.0, 60.0]), 10.0, 110.0), [0.0, 0.5])
    assert math.isnan(M.normalized_return(5.0, 10.0, 10.0))  # clean no better than random
    assert math.isnan(M.normalized_return(5.0, 10.0, 8.0))


def test_lap_completion_rate_and_mrr():
    assert M.lap_completion_rate([True, False, True, True]) == 0.75
    assert math.isnan(M.lap_completion_rate([]))
    assert M.mean_resilience_rate({"a": {0: 1.0, 1: 0.8, 2: 0.6}, "b": {1: 1.0, 2: float("nan")}}) == pytest.approx(0.8)
    assert M.mean_resilience_rate(np.array([[0.5, 1.0], [0.0, 0.5]])) == pytest.approx(0.5)


def test_corruption_error_plain_relative_and_zero_denominators():
    assert M.corruption_error([0.2, 0.4], [0.4, 0.8]) == pytest.approx(0.5)
    # relative: subtract each policy's clean DE first
    assert M.corruption_error([0.3, 0.5], [0.4, 0.8], de_clean=0.1, de_ref_clean=0.2) == pytest.approx((0.2 + 0.4) / (0.2 + 0.6))
    assert M.corruption_error([0.0, 0.0], [0.0, 0.0]) == 1.0  # neither ever fails: as robust as the reference
    assert M.corruption_error([0.0, 0.5], [0.0, 0.0]) == math.inf
    assert M.mce([0.5, 1.5, float("nan")]) == pytest.approx(1.0)
    with pytest.raises(ValueError):
        M.corruption_error([0.1], [0.1, 0.2])


def test_ausc_breaking_severity_worst_case():
    assert M.ausc([0, 1, 2], [1.0, 0.7, 0.4]) == pytest.approx(0.7)
    assert M.ausc([0, 5], [1.0, 1.0]) == pytest.approx(1.0)
    assert M.ausc([0, 1, 3, 5], [1.0, 1.2, -0.3, 0.0]) == pytest.approx(((1 + 1) / 2 + 2 * (1 + 0) / 2 + 2 * 0) / 5)  # clipped
    assert math.isnan(M.ausc([0, 1], [1.0, float("nan")]))
    with pytest.raises(ValueError):
        M.ausc([1, 2], [0.5, 0.4])
    assert M.breaking_severity([0, 1, 2, 3], [1.0, 0.5, 0.4, 0.0]) == 2  # 0.5 is not below 0.5
    assert M.breaking_severity([0, 1], [1.0, 0.9]) is None
    assert M.breaking_severity([0, 1], [0.0, 0.0]) == 0
    assert M.worst_case({"a": 0.4, "b": 0.2, "c": float("nan")}) == ("b", 0.2)
    assert M.worst_case({"a": float("nan")})[0] is None


def test_bootstrap_ci_contains_the_mean_and_is_seeded():
    x = np.random.default_rng(3).normal(5.0, 2.0, size=40)
    lo, hi = M.bootstrap_ci(x, n_boot=500, seed=1)
    assert lo < x.mean() < hi
    assert (lo, hi) == M.bootstrap_ci(x, n_boot=500, seed=1)
    assert (lo, hi) != M.bootstrap_ci(x, n_boot=500, seed=2)
    assert M.bootstrap_ci([2.0], seed=0) == (2.0, 2.0)
    assert all(math.isnan(v) for v in M.bootstrap_ci([float("nan")]))
    # the paired form agrees with the plain one for the mean
    assert M.bootstrap(lambda idx: float(x[idx].mean()), len(x), n_boot=500, seed=1) == pytest.approx((lo, hi))


def test_steering_off_track_and_lap_stats():
    mean_abs, per_km = M.steering_oscillation([0.1, -0.1, 0.1, 0.0, 0.1], distance_m=2000.0)
    assert mean_abs == pytest.approx(0.15)
    assert per_km == pytest.approx(1.0)  # 2 flips (the 0.0 is inside the dead band) over 2 km
    assert M.off_track_events([0.0, 1.2, 1.3, 0.5, -1.1]) == 2
    assert M.off_track_events([]) == 0
    assert M.lap_time_stats([60.0, 50.0, 52.0]) == {"fastest_lap": 50.0, "mean_lap": 51.0}
    assert M.lap_time_stats([61.0]) == {"fastest_lap": 61.0, "mean_lap": 61.0}
    assert all(math.isnan(v) for v in M.lap_time_stats([]).values())


# ------------------------------------------------------------------------------- a grid
def _rows():
    """Two policies (A = reference, B) + random, one track, two episodes, corruptions c1, c2 at s = 1, 2.

    R_random = 0; R_clean(A) = 100, R_clean(B) = 200, so NR = R / R_clean.
    """
    rows = []

    def add(p, c, s, rets, succ):
        for e, (r, ok) in enumerate(zip(rets, succ)):
            rows.append({"policy": p, "track": "t1", "surface": "asphalt", "corruption": c, "severity": s, "episode": e,
                         "return": r, "success": ok})

    add("random", M.CLEAN, 0, [0.0, 0.0], [False, False])
    add("A", M.CLEAN, 0, [100.0, 100.0], [True, True])
    add("A", "c1", 1, [80.0, 60.0], [True, False])
    add("A", "c1", 2, [50.0, 30.0], [False, False])
    add("A", "c2", 1, [100.0, 100.0], [True, True])
    add("A", "c2", 2, [90.0, 70.0], [True, False])
    add("B", M.CLEAN, 0, [200.0, 200.0], [True, False])
    add("B", "c1", 1, [200.0, 200.0], [True, True])
    add("B", "c1", 2, [100.0, 100.0], [True, False])
    add("B", "c2", 1, [200.0, 100.0], [True, False])
    add("B", "c2", 2, [0.0, 0.0], [False, False])
    return rows


def test_robustness_summary_known_answers():
    s = M.robustness_summary(_rows(), policies=["A", "B"], reference="A", n_boot=200, seed=0)
    a, b = s["policies"]["A"], s["policies"]["B"]
    assert s["severities"] == [0, 1, 2] and s["corruptions"] == ["c1", "c2"] and s["units"] == 2
    # NR per cell and mRR
    assert a["corruptions"]["c1"]["severities"]["1"]["nr"] == pytest.approx(0.7)
    assert a["corruptions"]["c1"]["severities"]["0"]["nr"] == pytest.approx(1.0)
    assert b["corruptions"]["c2"]["severities"]["1"]["nr"] == pytest.approx(0.75)
    assert a["mrr"] == pytest.approx((0.7 + 0.4 + 1.0 + 0.8) / 4)
    assert b["mrr"] == pytest.approx((1.0 + 0.5 + 0.75 + 0.0) / 4)
    # CE against A: B's DE sums c1 0.5 vs A's 1.5, c2 1.5 vs 0.5
    assert a["mce"] == pytest.approx(1.0)
    assert b["corruptions"]["c1"]["ce"] == pytest.approx(1 / 3)
    assert b["corruptions"]["c2"]["ce"] == pytest.approx(3.0)
    assert b["mce"] == pytest.approx((1 / 3 + 3.0) / 2)
    # relative: B's clean DE is 0.5, A's 0
    assert b["corruptions"]["c1"]["relative_ce"] == pytest.approx(-0.5 / 1.5)
    assert b["corruptions"]["c2"]["relative_ce"] == pytest.approx(0.5 / 0.5)
    assert b["relative_mce"] == pytest.approx((-1 / 3 + 1.0) / 2)
    # AUSC, breaking severity, worst case
    assert a["corruptions"]["c1"]["ausc"] == pytest.approx(0.7)
    assert b["corruptions"]["c2"]["ausc"] == pytest.approx(0.625)
    assert a["corruptions"]["c1"]["breaking_severity"] == 2
    assert a["corruptions"]["c2"]["breaking_severity"] is None
    assert b["corruptions"]["c1"]["breaking_severity"] is None
    assert b["corruptions"]["c2"]["breaking_severity"] == 2
    assert a["worst_case"] == {"corruption": "c1", "nr": pytest.approx(0.55)}
    assert b["worst_case"] == {"corruption": "c2", "nr": pytest.approx(0.375)}
    assert a["first_break"] == {"corruption": "c1", "severity": 2}
    # LCR with its interval; intervals contain the point estimate
    cell = a["corruptions"]["c1"]["severities"]["1"]
    assert cell["lcr"] == 0.5 and cell["lcr_ci"][0] <= 0.5 <= cell["lcr_ci"][1] and cell["n"] == 2
    assert a["mrr_ci"][0] <= a["mrr"] <= a["mrr_ci"][1]
    assert b["mce_ci"][0] <= b["mce"] <= b["mce_ci"][1]
    assert s["r_random"] == {"t1/asphalt": 0.0}
    # seeded: the same call gives the same intervals
    s2 = M.robustness_summary(_rows(), policies=["A", "B"], reference="A", n_boot=200, seed=0)
    assert s2["policies"]["B"]["mrr_ci"] == b["mrr_ci"]


def test_robustness_summary_without_random_rows_has_undefined_nr_and_a_note():
    rows = [r for r in _rows() if r["policy"] != "random"]
    s = M.robustness_summary(rows, reference="A", n_boot=10)
    assert s["policies"]["A"]["mrr"] is None
    assert any("NR is undefined" in n for n in s["notes"])
    # LCR-based metrics do not need R_random
    assert s["policies"]["B"]["mce"] == pytest.approx((1 / 3 + 3.0) / 2)
