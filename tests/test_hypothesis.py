"""mcrl.analysis.hypothesis: the exact rank-sum test against full enumeration, Holm, exact intervals; and
mcrl.analysis.divergence: the soft-Q bound on synthetic critics."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import scipy.stats

from mcrl.analysis import hypothesis as h
from mcrl.analysis.divergence import check_critics, lag_steps, lagged_bound, reward_max, soft_q_bound


def test_rank_sum_test_equals_full_enumeration_with_ties() -> None:
    rng = np.random.default_rng(0)
    for _ in range(60):
        nx, ny = (int(v) for v in rng.integers(1, 6, size=2))
        x, y = rng.integers(0, 4, nx) / 4, rng.integers(0, 4, ny) / 4  # many ties
        ranks = h.midranks(np.concatenate([x, y]))
        sums = np.array([ranks[list(c)].sum() for c in itertools.combinations(range(nx + ny), nx)])
        observed = ranks[:nx].sum()
        assert h.rank_sum_test(x, y, "greater") == pytest.approx((sums >= observed - 1e-9).mean(), abs=1e-12)
        assert h.rank_sum_test(x, y, "less") == pytest.approx((sums <= observed + 1e-9).mean(), abs=1e-12)


def test_rank_sum_test_matches_scipy_without_ties() -> None:
    rng = np.random.default_rng(1)
    x, y = rng.normal(size=7), rng.normal(0.8, size=9)
    for alt in ("greater", "less", "two-sided"):
        ref = scipy.stats.mannwhitneyu(x, y, alternative=alt, method="exact").pvalue
        assert h.rank_sum_test(x, y, alt) == pytest.approx(ref, rel=1e-9)
    assert h.rank_sum_test([0.9, 0.8, 0.7], [0.1, 0.2, 0.3]) == pytest.approx(1 / 20)
    with pytest.raises(ValueError):
        h.rank_sum_test([], [1.0])


def test_midranks_and_the_grid() -> None:
    rng = np.random.default_rng(3)
    for _ in range(50):
        v = rng.integers(0, 5, int(rng.integers(1, 15))) / 4
        np.testing.assert_array_equal(h.midranks(v), scipy.stats.rankdata(v))
    assert 0.28 - (0.75 - 0.52) != 0.05 and h.on_grid([0.28 - (0.75 - 0.52), np.nan]).tolist() == [0.05]
    # a shift is the same test as shifting by hand on the grid
    x, y = [0.28, 0.38, 0.7, 0.1], [0.05, 0.15, 0.2, 0.9]
    assert h.rank_sum_test(x, y, "less", shift=0.75 - 0.52) == h.rank_sum_test([0.05, 0.15, 0.47, -0.13], y, "less")


def test_tost_power() -> None:
    assert h.tost_power(12, 12, 0.115, 0.05, 0.05, 0.05) > 0.9  # no difference, tight scores: shown
    assert h.tost_power(6, 6, 0.115, 0.28, 0.28, 0.01) == 0.0  # FetchPush's spread at Holm's 0.05 / 5: never
    assert h.tost_power(12, 12, 0.115, 0.05, 0.05, 0.05, difference=0.115) <= 0.05 + 0.005  # at the margin: the level
    assert math.isnan(h.tost_power(6, 6, 0.1, 0.0, 0.1))


def test_holm() -> None:
    assert h.holm([0.01, 0.04, 0.03]) == pytest.approx([0.03, 0.06, 0.06])
    assert h.holm([0.5, 0.01]) == pytest.approx([0.5, 0.02])
    assert h.holm([0.3, 0.9]) == pytest.approx([0.6, 0.9])
    assert h.holm([0.04, 0.03]) == pytest.approx([0.06, 0.06])  # monotone: never below an earlier step
    assert h.holm([]) == []


def test_exact_rate_intervals() -> None:
    lo, hi = h.clopper_pearson(2, 6)
    ref = scipy.stats.binomtest(2, 6).proportion_ci(method="exact")
    assert (lo, hi) == pytest.approx((ref.low, ref.high))
    assert h.clopper_pearson(0, 12)[0] == 0.0 and h.clopper_pearson(12, 12)[1] == 1.0
    assert h.fisher_exact(4, 6, 0, 6) == pytest.approx(scipy.stats.fisher_exact([[4, 2], [0, 6]])[1])


def test_power_grows_with_seeds_and_effect() -> None:
    p6, p12 = (h.rank_sum_power(n, n, 0.23, 0.25, 0.25, 0.05) for n in (6, 12))
    assert 0.2 < p6 < p12 < 0.9
    assert h.rank_sum_power(12, 12, 0.0, 0.25, 0.25, 0.05) <= 0.05 + 0.005  # no effect: the level
    assert math.isnan(h.rank_sum_power(6, 6, 0.2, 0.0, 0.2))


# ------------------------------------------------------------------ the soft-Q bound


FETCH = {"env_id": "FetchPush-v4", "gamma": 0.99, "tau": 0.005, "intrinsic_alpha": 0.0}


def test_the_bound_from_theory() -> None:
    # FetchPush: 4-d actions, rewards <= 0: Q <= c * 4 log 2 * 0.99 / 0.01
    assert soft_q_bound(1.0, 4, 0.99, 0.0) == pytest.approx(4 * math.log(2) * 99)
    assert lag_steps(0.99, 0.005) == 20_000
    assert reward_max(FETCH) == 0.0 and reward_max({"env_id": "Pendulum-v1"}) is None
    assert reward_max({"env_id": "AntMaze_UMazeDense-v5", "intrinsic_alpha": 0.2, "intrinsic_reward_high": 1.0}) == pytest.approx(1.0)
    # the coefficient falls from 1 to 0.01 by step 10k: the lagged bound keeps 1's until 20k steps later
    steps = np.arange(1000, 60_001, 1000)
    coef = np.where(steps <= 10_000, 1.0, 0.01)
    b = lagged_bound(steps, coef, 4, 0.99, 0.005, 0.0)
    assert b[steps == 30_000][0] == pytest.approx(soft_q_bound(1.0, 4, 0.99, 0.0))
    assert b[steps == 31_000][0] == pytest.approx(soft_q_bound(0.01, 4, 0.99, 0.0))


def test_check_critics_flags_a_critic_above_the_bound_and_not_an_early_overshoot() -> None:
    steps = np.arange(1000, 100_001, 1000, dtype=float)
    coef = np.where(steps <= 10_000, 0.5, 0.01)
    q = np.where(steps <= 15_000, 25.0, -5.0)  # overshoots while the coefficient falls: within the lag
    settled = check_critics({"step": steps, "q_mean": q, "ent_coef": coef}, FETCH)
    assert settled is not None and not settled.left and settled.rows == 100
    q_div = np.where(steps >= 60_000, 2.0 ** ((steps - 60_000) / 4000), q)  # grows past 2.74 = bound at c 0.01
    div = check_critics({"step": steps, "q_mean": q_div, "ent_coef": coef}, FETCH)
    first = steps[(steps >= 60_000) & (q_div > soft_q_bound(0.01, 4, 0.99, 0.0))][0]
    assert div.left and div.first_outside == first and div.outside_at_end and div.max_excess > 0
    assert check_critics({"step": steps, "q_mean": q, "ent_coef": coef}, {"env_id": "Pendulum-v1"}) is None
