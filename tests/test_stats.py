"""mcrl.analysis.stats against hand-computed values and known distributions."""

from __future__ import annotations

import numpy as np
import pytest

from mcrl.analysis import stats


@pytest.fixture(params=["numpy", "rliable"])
def backend(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Run a test with mcrl's numpy stratified bootstrap and, where it imports, rliable's."""
    if request.param == "numpy":
        monkeypatch.setattr(stats, "_rliable_library", lambda: None)
    elif stats._rliable_library() is None:
        pytest.skip("rliable.library does not import here (arch vs pandas 3)")
    return request.param


def test_iqm_hand_computed() -> None:
    assert stats.iqm(np.arange(1, 9)) == pytest.approx(4.5)  # mean of 3, 4, 5, 6
    assert stats.iqm([1, 1, 0, 100, -100, 0, 1, 1]) == pytest.approx(0.75)  # middle four: 0, 1, 1, 1
    assert stats.iqm([2.0, 4.0, 9.0]) == pytest.approx(5.0)  # n < 4: nothing trimmed
    np.testing.assert_allclose(stats.iqm(np.array([np.arange(1, 9), np.arange(11, 19)]), axis=1), [4.5, 14.5])


def test_bootstrap_ci_coverage_on_normal_data() -> None:
    """Over many N(0, 1) datasets the 95% percentile CI of the mean covers 0 about 95% of the time."""
    rng = np.random.default_rng(123)
    trials, covered = 400, 0
    for _ in range(trials):
        lo, hi = stats.bootstrap_ci(rng.normal(size=30), np.mean, n_boot=1000, rng=rng)
        covered += lo <= 0.0 <= hi
    assert 0.88 <= covered / trials <= 0.99


def test_bootstrap_ci_deterministic_and_any_statistic() -> None:
    x = np.array([0.1, 0.4, 0.35, 0.8, 0.5])
    assert stats.bootstrap_ci(x, np.mean, rng=7) == stats.bootstrap_ci(x, np.mean, rng=7)
    lo, hi = stats.bootstrap_ci(x, lambda s: float(np.max(s) - np.min(s)), n_boot=200, rng=0)  # no axis kwarg
    assert 0.0 <= lo <= hi <= 0.7 + 1e-12
    assert stats.bootstrap_ci(np.full(5, 3.0), stats.iqm, rng=0) == (3.0, 3.0)


def test_mean_ci_band() -> None:
    one = np.linspace(0, 1, 11)
    m, lo, hi = stats.mean_ci_band(one[None])
    np.testing.assert_allclose(m, one)
    np.testing.assert_allclose(lo, one)
    np.testing.assert_allclose(hi, one)

    curves = np.array([[0.0, 1.0, 2.0], [2.0, 3.0, np.nan]])  # second seed stopped early
    m, lo, hi = stats.mean_ci_band(curves, rng=0)
    np.testing.assert_allclose(m, [1.0, 2.0, 2.0])
    assert lo[0] == pytest.approx(0.0) and hi[0] == pytest.approx(2.0)  # resamples: both, either seed
    assert lo[2] == hi[2] == pytest.approx(2.0)  # only one seed there
    assert np.all(lo <= m) and np.all(m <= hi)

    a, b = stats.mean_ci_band(np.random.default_rng(0).normal(size=(6, 50)), rng=3), \
        stats.mean_ci_band(np.random.default_rng(0).normal(size=(6, 50)), rng=3)
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


def test_align_curves_interpolates_inside_each_run_only() -> None:
    grid, curves = stats.align_curves([([0, 10, 20], [0.0, 1.0, 2.0]), ([0, 5, 10], [1.0, 2.0, np.nan])])
    np.testing.assert_array_equal(grid, [0, 5, 10, 20])
    np.testing.assert_allclose(curves[0], [0.0, 0.5, 1.0, 2.0])
    np.testing.assert_allclose(curves[1], [1.0, 2.0, np.nan, np.nan])


def test_probability_of_improvement_constructed_cases(backend: str) -> None:
    assert stats.probability_of_improvement([4, 5, 6], [1, 2, 3], n_boot=300) == (1.0, 1.0, 1.0)
    assert stats.probability_of_improvement([1, 2, 3], [4, 5, 6], n_boot=300) == (0.0, 0.0, 0.0)
    p, lo, hi = stats.probability_of_improvement([1, 2, 3, 4], [1, 2, 3, 4], n_boot=500)
    assert p == 0.5 and lo < 0.5 < hi
    # x = 0.6, 0.8, 1.0 vs y = 0.2, 0.4, 0.6: 8 wins and one tie out of 9 pairs.
    p, lo, hi = stats.probability_of_improvement([0.6, 0.8, 1.0], [0.2, 0.4, 0.6], n_boot=500)
    assert p == pytest.approx(8.5 / 9)
    assert lo <= p <= hi <= 1.0
    # Unequal run counts and several tasks: mean over tasks of per-task probabilities (1 and 0).
    x, y = np.array([[5.0, 0.0], [6.0, 1.0]]), np.array([[1.0, 7.0], [2.0, 8.0], [3.0, 9.0]])
    assert stats.probability_of_improvement(x, y, n_boot=200)[0] == pytest.approx(0.5)


def test_probability_of_improvement_deterministic(backend: str) -> None:
    x, y = np.random.default_rng(1).normal(0.3, 1, 8), np.random.default_rng(2).normal(0, 1, 6)
    assert stats.probability_of_improvement(x, y, n_boot=400, seed=5) == \
        stats.probability_of_improvement(x, y, n_boot=400, seed=5)


def test_stratified_iqm_ci(backend: str) -> None:
    scores = {"a": np.arange(1.0, 9.0), "const": np.full(4, 0.5), "tasks": np.arange(12.0).reshape(6, 2)}
    out = stats.stratified_iqm_ci(scores, n_boot=500, seed=0)
    assert out["a"][0] == pytest.approx(4.5)
    assert 1.0 <= out["a"][1] < 4.5 < out["a"][2] <= 8.0
    assert out["const"] == (0.5, 0.5, 0.5)
    assert out["tasks"][0] == pytest.approx(stats.iqm(np.arange(12.0)))
    assert stats.stratified_iqm_ci(scores, n_boot=500, seed=0) == out


def test_stratified_iqm_ci_entries_are_independent(backend: str) -> None:
    """An entry's interval is the same whatever other entries share the call (a report's arms finish one by one)."""
    rng = np.random.default_rng(3)
    x, other = rng.uniform(size=12), rng.uniform(size=3)
    alone = stats.stratified_iqm_ci({"x": x}, n_boot=300, seed=0)["x"]
    assert stats.stratified_iqm_ci({"other": other, "x": x}, n_boot=300, seed=0)["x"] == alone
    assert stats.stratified_iqm_ci({"other": np.append(other, 0.9), "x": x}, n_boot=300, seed=0)["x"] == alone


def test_stratified_ci_coverage(backend: str) -> None:
    """The stratified-bootstrap CI of the IQM of N(0, 1) covers 0 in most of 60 datasets (sanity check)."""
    rng = np.random.default_rng(0)
    covered = sum(lo <= 0.0 <= hi for _, lo, hi in
                  (stats.stratified_iqm_ci({"x": rng.normal(size=20)}, n_boot=300, seed=i)["x"] for i in range(60)))
    assert covered >= 50


def test_minimum_detectable_difference_hand_computed() -> None:
    z = 1.959964 + 0.841621  # z_0.975 + z_0.8
    x, y = [0.2, 0.4, 0.6], [0.6, 0.8, 1.0]  # sample variances 0.04 each
    assert stats.minimum_detectable_difference(x, y) == pytest.approx(z * np.sqrt(0.04 / 3 + 0.04 / 3), rel=1e-5)
    # unequal sizes and spreads (Welch): sqrt(s1^2/n1 + s2^2/n2)
    a, b = np.array([1.0, 2.0, 3.0, 4.0]), np.array([0.0, 0.0, 6.0])
    expected = z * np.sqrt(a.var(ddof=1) / 4 + b.var(ddof=1) / 3)
    assert stats.minimum_detectable_difference(a, b) == pytest.approx(expected, rel=1e-5)
    # other alpha and power
    assert stats.minimum_detectable_difference(x, y, alpha=0.01, power=0.9) == pytest.approx(
        (2.575829 + 1.281552) * np.sqrt(0.08 / 3), rel=1e-5)
    assert np.isnan(stats.minimum_detectable_difference([0.5], [0.1, 0.2]))  # no variance from one seed
    assert stats.minimum_detectable_difference([1.0, 1.0], [0.0, 0.0]) == 0.0


def test_seeds_to_detect() -> None:
    x, y = [0.2, 0.4, 0.6], [0.6, 0.8, 1.0]
    # n = z^2 (0.04 + 0.04) / 0.4^2 = 3.92 -> 4, and the MDE with 4 seeds each is just below 0.4
    assert stats.seeds_to_detect(x, y, 0.4) == 4
    z = 1.959964 + 0.841621
    assert z * np.sqrt(0.08 / 4) < 0.4 < z * np.sqrt(0.08 / 3)
    assert stats.seeds_to_detect(x, y, -0.4) == 4  # the sign does not matter
    assert stats.seeds_to_detect(x, y, 0.0) is None
    assert stats.seeds_to_detect([1.0, 1.0], [0.0, 0.0], 0.5) == 2  # no spread: the minimum
    assert stats.seeds_to_detect([1.0], [0.0, 0.5], 0.5) is None


def test_detectable_difference_and_seeds_at_a_one_sided_adjusted_level() -> None:
    """One-sided at a Holm level, as the verdicts test 'better' claims: z_{1-alpha}, not z_{1-alpha/2}."""
    x, y = [0.2, 0.4, 0.6], [0.6, 0.8, 1.0]
    z = 2.539185 + 0.841621  # z_{1 - 0.05/9} + z_0.8
    assert stats.minimum_detectable_difference(x, y, 0.05 / 9, 0.8, "one-sided") == pytest.approx(
        z * np.sqrt(0.08 / 3), rel=1e-5)
    # n = z^2 (0.04 + 0.04) / 0.4^2 = 5.71 -> 6 (4 two-sided at 0.05)
    assert stats.seeds_to_detect(x, y, 0.4, 0.05 / 9, 0.8, "one-sided") == 6
    assert stats.seeds_to_detect(x, y, 0.4, 0.05, 0.8, "two-sided") == stats.seeds_to_detect(x, y, 0.4) == 4
    with pytest.raises(ValueError, match="one-sided"):
        stats.minimum_detectable_difference(x, y, sides="greater")


def test_mean_difference_ci_contains_the_difference_and_narrows_with_seeds():
    rng = np.random.default_rng(1)
    small = stats.mean_difference_ci(rng.normal(1, 1, 5), rng.normal(0, 1, 5))
    large = stats.mean_difference_ci(rng.normal(1, 1, 500), rng.normal(0, 1, 500))
    for d, lo, hi in (small, large):
        assert lo <= d <= hi
    assert large[2] - large[1] < (small[2] - small[1]) / 4 and large[1] < 1.0 < large[2]
