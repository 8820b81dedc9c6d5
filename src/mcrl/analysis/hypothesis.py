"""Hypothesis tests with a known false-positive rate, for verdicts on differences between configurations.

A verdict ("X beats Y") comes from an exact test, never from whether a bootstrap interval happens to exclude a
value: with 3-6 seeds per arm percentile-bootstrap intervals are too narrow, and a rule built on them fires more
often than its nominal level under the null (about 10% at 3 vs 3 seeds for "the CI of P(X > Y) lies above 0.5").

- :func:`rank_sum_test`: the Mann-Whitney / Wilcoxon rank-sum test, exact: its p-value is the share of all
  C(n_x + n_y, n_x) ways of splitting the pooled values into the two arms whose rank sum is at least as extreme
  as the observed one, ties handled with mid-ranks (the permutation distribution of U, not a normal
  approximation). Its statistic U / (n_x n_y) is the probability of improvement P(X > Y) the report shows.
- :func:`holm`: Holm's step-down adjustment, so several claims that share an arm keep a family-wise error rate.
- :func:`rank_sum_power`: the probability that the test detects a given shift, by simulation.
- :func:`clopper_pearson`, :func:`fisher_exact`: exact intervals and tests for rates (e.g. of diverged critics).

Pure numpy/scipy, deterministic given a seed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import lru_cache
from typing import Any, Literal

import numpy as np
import scipy.stats

Alternative = Literal["greater", "less", "two-sided"]


def midranks(values: Any) -> np.ndarray:
    """Ranks 1..n of ``values``, ties sharing the mean of their ranks."""
    return scipy.stats.rankdata(np.asarray(values, dtype=float), method="average")


def _subset_sum_counts(doubled_ranks: np.ndarray, k: int) -> np.ndarray:
    """counts[s] = the number of k-element subsets of ``doubled_ranks`` (non-negative ints) summing to s."""
    total = int(doubled_ranks.sum())
    counts = np.zeros((k + 1, total + 1))
    counts[0, 0] = 1.0
    for v in doubled_ranks.astype(int):
        # add this element to every subset of size j-1 (a copy, so no element is used twice)
        shifted = np.zeros_like(counts)
        shifted[1:, v:] = counts[:-1, : total + 1 - v]
        counts += shifted
    return counts[k]


@lru_cache(maxsize=64)
def _null_distribution_no_ties(n_x: int, n_y: int) -> tuple[np.ndarray, np.ndarray]:
    """(doubled rank sums of X, their probabilities) under the null, for data without ties."""
    counts = _subset_sum_counts(2 * np.arange(1, n_x + n_y + 1), n_x)
    support = np.flatnonzero(counts)
    return support, counts[support] / counts.sum()


def _p_from_counts(counts: np.ndarray, observed: int, alternative: Alternative) -> float:
    total = counts.sum()
    upper = counts[observed:].sum() / total  # P(S >= s_obs)
    lower = counts[: observed + 1].sum() / total  # P(S <= s_obs)
    if alternative == "greater":
        return float(upper)
    if alternative == "less":
        return float(lower)
    return float(min(1.0, 2.0 * min(upper, lower)))


def rank_sum_test(x: Any, y: Any, alternative: Alternative = "greater") -> float:
    """Exact p-value of the rank-sum test of "X tends to be larger than Y" (``greater``), smaller (``less``) or
    either (``two-sided``: twice the smaller tail, at most 1).

    Exact for any sample sizes and with ties: the null distribution of X's mid-rank sum over all splits of the
    pooled values is counted, not approximated. Under the null (both samples from one distribution, or any
    exchangeable arrangement), ``P(p <= a) <= a`` for every level a. NaN values are dropped.
    """
    a = np.asarray(x, dtype=float).ravel()
    b = np.asarray(y, dtype=float).ravel()
    a, b = a[np.isfinite(a)], b[np.isfinite(b)]
    if a.size == 0 or b.size == 0:
        raise ValueError(f"rank_sum_test needs at least one value in each sample, got {a.size} and {b.size}")
    if alternative not in ("greater", "less", "two-sided"):
        raise ValueError(f"alternative must be 'greater', 'less' or 'two-sided', not {alternative!r}")
    doubled = np.rint(2 * midranks(np.concatenate([a, b]))).astype(int)  # mid-ranks are multiples of 1/2
    counts = _subset_sum_counts(doubled, a.size)
    return _p_from_counts(counts, int(doubled[: a.size].sum()), alternative)


def holm(pvalues: Sequence[float]) -> list[float]:
    """Holm's step-down adjusted p-values (same order as given): a claim is accepted at family-wise level a when
    its adjusted p is at most a. Controls the chance of any false claim in the family at a, whatever the
    dependence between the tests (e.g. claims that share their baseline arm)."""
    p = np.asarray(pvalues, dtype=float)
    m = p.size
    order = np.argsort(p, kind="stable")
    adjusted = np.empty(m)
    running = 0.0
    for i, j in enumerate(order):
        running = max(running, min(1.0, (m - i) * p[j]))
        adjusted[j] = running
    return adjusted.tolist()


def rank_sum_power(n_x: int, n_y: int, shift: float, sd_x: float, sd_y: float, level: float = 0.05,
                   alternative: Alternative = "greater", sims: int = 20_000, seed: int = 0) -> float:
    """The probability that :func:`rank_sum_test` at ``level`` detects a true shift of ``shift`` between the
    means, when each seed's score is normal with the given standard deviations (simulated, ``sims`` draws).

    NaN when a standard deviation is not positive and finite. With few seeds the exact test cannot reach small
    levels at all (at 3 vs 3 the smallest one-sided p-value is 1/20), which this shows as zero power.
    """
    if not (sd_x > 0 and sd_y > 0 and math.isfinite(sd_x) and math.isfinite(sd_y)):
        return float("nan")
    support, prob = _null_distribution_no_ties(n_x, n_y)
    upper_tail = np.cumsum(prob[::-1])[::-1]  # P(S >= s) at each support point s
    lower_tail = np.cumsum(prob)  # P(S <= s)

    def rejects(s: np.ndarray, tail: np.ndarray, a: float, upper: bool) -> np.ndarray:
        ok = support[tail <= a * (1 + 1e-9)]  # rank sums at least as extreme as a level-a test needs
        if ok.size == 0:
            return np.zeros(s.shape, bool)
        return s >= ok.min() if upper else s <= ok.max()

    rng = np.random.default_rng(seed)
    x = rng.normal(shift, sd_x, size=(sims, n_x))
    y = rng.normal(0.0, sd_y, size=(sims, n_y))
    ranks = np.argsort(np.argsort(np.concatenate([x, y], axis=1), axis=1), axis=1) + 1  # continuous: no ties
    s = 2 * ranks[:, :n_x].sum(axis=1)
    if alternative == "greater":
        hit = rejects(s, upper_tail, level, True)
    elif alternative == "less":
        hit = rejects(s, lower_tail, level, False)
    else:  # twice the smaller tail <= level: either tail at level / 2
        hit = rejects(s, upper_tail, level / 2, True) | rejects(s, lower_tail, level / 2, False)
    return float(hit.mean())


def clopper_pearson(k: int, n: int, conf: float = 0.95) -> tuple[float, float]:
    """Exact (Clopper-Pearson) ``conf`` interval of a rate from k successes in n trials."""
    if n <= 0:
        return float("nan"), float("nan")
    a = (1 - conf) / 2
    lo = 0.0 if k == 0 else float(scipy.stats.beta.ppf(a, k, n - k + 1))
    hi = 1.0 if k == n else float(scipy.stats.beta.ppf(1 - a, k + 1, n - k))
    return lo, hi


def fisher_exact(k1: int, n1: int, k2: int, n2: int) -> float:
    """Two-sided p-value of Fisher's exact test that two rates, k1/n1 and k2/n2, are equal."""
    return float(scipy.stats.fisher_exact([[k1, n1 - k1], [k2, n2 - k2]], alternative="two-sided")[1])
