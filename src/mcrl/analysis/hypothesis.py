"""Hypothesis tests with a known false-positive rate, for verdicts on differences between configurations.

A verdict ("X beats Y") comes from an exact test, never from whether a bootstrap interval happens to exclude a
value: with 3-6 seeds per arm percentile-bootstrap intervals are too narrow, and a rule built on them fires more
often than its nominal level under the null (about 10% at 3 vs 3 seeds for "the CI of P(X > Y) lies above 0.5").

- :func:`rank_sum_test`: the Mann-Whitney / Wilcoxon rank-sum test, exact: its p-value is the share of all
  C(n_x + n_y, n_x) ways of splitting the pooled values into the two arms whose rank sum is at least as extreme
  as the observed one, ties handled with mid-ranks (the permutation distribution of U, not a normal
  approximation). Its statistic U / (n_x n_y) is the probability of improvement P(X > Y) the report shows.
- :func:`holm`: Holm's step-down adjustment, so several claims that share an arm keep a family-wise error rate.
- :func:`rank_sum_power`, :func:`tost_power`: the probability that the test detects a given shift, or that two
  one-sided tests show equivalence within a margin, by simulation.

Shifted comparisons (X - d against Y) are ranked on a grid of ``GRID_DECIMALS`` decimals: scores are recorded with a
few decimals (a success rate is k / episodes), so ``0.75 - 0.52 = 0.22999999999999998`` must still make
0.50 - 0.23 tie with 0.27, as it does in exact arithmetic.
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
GRID_DECIMALS = 9  # values closer than 1e-9 are one value: far below any recorded score's resolution


def on_grid(values: Any) -> np.ndarray:
    """Finite values of ``values`` rounded to ``GRID_DECIMALS`` decimals, so floating-point residue of a shift
    does not break a tie that exact arithmetic has."""
    a = np.asarray(values, dtype=float).ravel()
    return np.round(a[np.isfinite(a)], GRID_DECIMALS)


def midranks(values: Any) -> np.ndarray:
    """Ranks 1..n of ``values``, ties sharing the mean of their ranks (scipy's "average", in plain numpy: the
    null simulations call it thousands of times)."""
    _, inverse, counts = np.unique(np.asarray(values, dtype=float).ravel(), return_inverse=True, return_counts=True)
    first = np.cumsum(counts) - counts + 1  # the rank of each distinct value's first copy
    return (first + (counts - 1) / 2.0)[inverse]


def _subset_sum_counts(doubled_ranks: np.ndarray, k: int) -> np.ndarray:
    """counts[s] = the number of k-element subsets of ``doubled_ranks`` (non-negative ints) summing to s."""
    total = int(doubled_ranks.sum())
    counts = np.zeros((k + 1, total + 1))
    counts[0, 0] = 1.0
    reach = 0  # the largest sum any subset so far can have: columns beyond it are zero
    for v in doubled_ranks.astype(int):
        reach += v
        # add this element to every subset of size j-1 (from a copy, so no element is used twice)
        counts[1:, v:reach + 1] += counts[:-1, : reach + 1 - v].copy()
    return counts[k]


@lru_cache(maxsize=8192)
def _null_counts(tie_sizes: tuple[int, ...], k: int) -> np.ndarray:
    """counts[s] of the k-element subsets of pooled values whose sorted tie groups have these sizes: the null
    distribution of X's doubled mid-rank sum depends on nothing else, so simulations with repeating tie patterns
    count it once."""
    c = np.asarray(tie_sizes)
    doubled = np.repeat(2 * (np.cumsum(c) - c + 1) + c - 1, c)  # 2 x mid-rank: an integer
    return _subset_sum_counts(doubled, k)


@lru_cache(maxsize=64)
def _null_distribution_no_ties(n_x: int, n_y: int) -> tuple[np.ndarray, np.ndarray]:
    """(doubled rank sums of X, their probabilities) under the null, for data without ties."""
    counts = _null_counts((1,) * (n_x + n_y), n_x)
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


def rank_sum_test(x: Any, y: Any, alternative: Alternative = "greater", shift: float = 0.0) -> float:
    """Exact p-value of the rank-sum test of "X - shift tends to be larger than Y" (``greater``), smaller
    (``less``) or either (``two-sided``: twice the smaller tail, at most 1).

    Exact for any sample sizes and with ties: the null distribution of X's mid-rank sum over all splits of the
    pooled values is counted, not approximated. Under the null (both samples from one distribution, or any
    exchangeable arrangement), ``P(p <= a) <= a`` for every level a. NaN values are dropped. ``shift`` tests a
    location shift (X - shift against Y), computed on the grid of :func:`on_grid` so ties stay ties.
    """
    a = on_grid(np.asarray(x, dtype=float).ravel() - shift)
    b = on_grid(y)
    if a.size == 0 or b.size == 0:
        raise ValueError(f"rank_sum_test needs at least one value in each sample, got {a.size} and {b.size}")
    if alternative not in ("greater", "less", "two-sided"):
        raise ValueError(f"alternative must be 'greater', 'less' or 'two-sided', not {alternative!r}")
    _, inverse, sizes = np.unique(np.concatenate([a, b]), return_inverse=True, return_counts=True)
    doubled = (2 * (np.cumsum(sizes) - sizes + 1) + sizes - 1)[inverse.ravel()]  # 2 x mid-rank: an integer
    return _p_from_counts(_null_counts(tuple(sizes.tolist()), a.size), int(doubled[: a.size].sum()), alternative)


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


def _rejects(s: np.ndarray, n_x: int, n_y: int, level: float, alternative: Alternative) -> np.ndarray:
    """Which doubled rank sums ``s`` of X (data without ties) the exact test rejects at ``level``."""
    support, prob = _null_distribution_no_ties(n_x, n_y)

    def tail(a: float, upper: bool) -> np.ndarray:
        p = np.cumsum(prob[::-1])[::-1] if upper else np.cumsum(prob)  # P(S >= s) or P(S <= s) at each s
        ok = support[p <= a * (1 + 1e-9)]  # rank sums at least as extreme as a level-a test needs
        if ok.size == 0:
            return np.zeros(s.shape, bool)
        return s >= ok.min() if upper else s <= ok.max()

    if alternative == "greater":
        return tail(level, True)
    if alternative == "less":
        return tail(level, False)
    return tail(level / 2, True) | tail(level / 2, False)  # twice the smaller tail <= level


def _doubled_rank_sums(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """2 x X's rank sum per row of (sims, n) draws without ties."""
    ranks = np.argsort(np.argsort(np.concatenate([x, y], axis=1), axis=1), axis=1) + 1
    return 2 * ranks[:, :x.shape[1]].sum(axis=1)


def _sds_ok(*sds: float) -> bool:
    return all(sd > 0 and math.isfinite(sd) for sd in sds)


def rank_sum_power(n_x: int, n_y: int, shift: float, sd_x: float, sd_y: float, level: float = 0.05,
                   alternative: Alternative = "greater", sims: int = 20_000, seed: int = 0) -> float:
    """The probability that :func:`rank_sum_test` at ``level`` detects a true shift of ``shift`` between the
    means, when each seed's score is normal with the given standard deviations (simulated, ``sims`` draws).

    NaN when a standard deviation is not positive and finite. With few seeds the exact test cannot reach small
    levels at all (at 3 vs 3 the smallest one-sided p-value is 1/20), which this shows as zero power.
    """
    if not _sds_ok(sd_x, sd_y):
        return float("nan")
    rng = np.random.default_rng(seed)
    x = rng.normal(shift, sd_x, size=(sims, n_x))
    y = rng.normal(0.0, sd_y, size=(sims, n_y))
    return float(_rejects(_doubled_rank_sums(x, y), n_x, n_y, level, alternative).mean())


def tost_power(n_x: int, n_y: int, margin: float, sd_x: float, sd_y: float, level: float = 0.05,
               difference: float = 0.0, sims: int = 20_000, seed: int = 0) -> float:
    """The probability that two one-sided exact rank-sum tests at ``level`` (X + margin > Y and X - margin < Y)
    both reject, i.e. show X and Y equivalent within ``margin``, when the true difference of means is
    ``difference`` (default 0) and scores are normal with the given standard deviations (simulated).

    NaN when a standard deviation is not positive and finite. Each test runs at the full ``level``: the claim
    needs both, so no adjustment between them is due (an intersection-union test).
    """
    if not _sds_ok(sd_x, sd_y):
        return float("nan")
    rng = np.random.default_rng(seed)
    x = rng.normal(difference, sd_x, size=(sims, n_x))
    y = rng.normal(0.0, sd_y, size=(sims, n_y))
    above = _rejects(_doubled_rank_sums(x + margin, y), n_x, n_y, level, "greater")
    below = _rejects(_doubled_rank_sums(x - margin, y), n_x, n_y, level, "less")
    return float((above & below).mean())


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
