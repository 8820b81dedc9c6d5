"""Claims about final scores and the exact tests that decide them, with a known error rate.

A claim compares an arm X with a baseline arm Y on the final success rate, in one of four kinds:

- ``better`` (by d): X > Y. Its own test is the one-sided exact rank-sum test of X > Y; it is refuted when X
  falling short of Y + d is shown instead (X shifted down by d, against Y): an improvement as large as claimed is
  excluded.
- ``worse`` (by d): X < Y, refuted when X + d > Y is shown: a deficit as large as d is excluded.
- ``same`` (margin m): |X - Y| < m, shown by two one-sided tests (TOST: X + m > Y and X - m < Y, each at the full
  level, as equivalence needs both; its p-value is the larger one); refuted when X beyond Y + m or below Y - m is
  shown (the smaller of those two p-values, doubled: either side refutes).
- ``differs``: X != Y, two-sided; no refutation, as no size is claimed.

Claims that share a baseline arm form a family (:mod:`mcrl.analysis.registry` declares them), and :func:`decide`
runs Holm's correction over the family's claims with enough seeds, separately for the claims' own tests and for
their refutations, so the chance that any claim of a family is called reproduced (or refuted) wrongly stays at most
:data:`LEVEL`. Shifted values are compared on the exact grid of :func:`mcrl.analysis.hypothesis.on_grid`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from mcrl.analysis.hypothesis import holm, rank_sum_power, rank_sum_test, tost_power
from mcrl.analysis.stats import MIN_SEEDS_FOR_VERDICT, improvement_point

LEVEL = 0.05  # the family-wise false-positive rate of a verdict among claims that share a baseline
REPRODUCED, NOT_REPRODUCED, NOT_DECIDABLE = "reproduced", "not reproduced", "not decidable with this many seeds"
Kind = Literal["better", "worse", "same", "differs"]
KINDS: tuple[str, ...] = ("better", "worse", "same", "differs")


@dataclass(frozen=True)
class ClaimTest:
    """The exact tests of one claim on final scores (NaN where a test does not apply)."""

    n_x: int
    n_y: int
    p: float  # the claim's own test
    p_refute: float  # the test of its opposite (NaN for 'differs', or when no size is claimed)
    parts: tuple[float, ...] = field(default=())  # 'same': the p-values of X + m > Y and X - m < Y
    x_above: bool = False  # P(X > Y) > 1/2: the side of a 'differs' verdict


def _finite(v: Any) -> np.ndarray:
    a = np.asarray(v, dtype=float).ravel()
    return a[np.isfinite(a)]


def claim_test(x: Any, y: Any, by: float | None, kind: Kind = "better") -> ClaimTest:
    """The tests of "X is ``kind`` than Y" (by ``by``; the margin of a ``same`` claim) on final scores."""
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {', '.join(KINDS)}, not {kind!r}")
    a, b = _finite(x), _finite(y)
    if a.size == 0 or b.size == 0:
        return ClaimTest(a.size, b.size, math.nan, math.nan)
    nan = math.nan
    above = improvement_point(a, b) > 0.5
    if kind == "better":
        return ClaimTest(a.size, b.size, rank_sum_test(a, b, "greater"),
                         nan if by is None else rank_sum_test(a, b, "less", shift=by), x_above=above)
    if kind == "worse":
        return ClaimTest(a.size, b.size, rank_sum_test(a, b, "less"),
                         nan if by is None else rank_sum_test(a, b, "greater", shift=-by), x_above=above)
    if kind == "differs":
        return ClaimTest(a.size, b.size, rank_sum_test(a, b, "two-sided"), nan, x_above=above)
    if by is None or not by > 0:
        raise ValueError(f"a 'same' claim needs a positive margin, got {by!r}")
    lo, hi = rank_sum_test(a, b, "greater", shift=-by), rank_sum_test(a, b, "less", shift=by)
    beyond = min(rank_sum_test(a, b, "greater", shift=by), rank_sum_test(a, b, "less", shift=-by))
    return ClaimTest(a.size, b.size, max(lo, hi), min(1.0, 2.0 * beyond), (lo, hi), above)


@dataclass(frozen=True)
class Verdict:
    verdict: str
    p_adj: float | None  # Holm-adjusted within the family; None when too few seeds (or the family is not tested)
    p_refute_adj: float | None  # None also where the claim has no refutation
    family: int  # claims in its Holm family (those with enough seeds)


def decide(tests: Sequence[ClaimTest], level: float = LEVEL, min_seeds: int = MIN_SEEDS_FOR_VERDICT) -> list[Verdict]:
    """Verdicts on the claims of one family, Holm-adjusted over those with enough seeds: the claims' own tests in
    one Holm run, their refutations in another (a claim without one counts there as p = 1)."""
    ok = [i for i, t in enumerate(tests) if min(t.n_x, t.n_y) >= min_seeds]
    own = dict(zip(ok, holm([tests[i].p for i in ok])))
    refute = dict(zip(ok, holm([1.0 if math.isnan(tests[i].p_refute) else tests[i].p_refute for i in ok])))
    out = []
    for i, t in enumerate(tests):
        if i not in own:
            out.append(Verdict(NOT_DECIDABLE, None, None, len(ok)))
            continue
        r = None if math.isnan(t.p_refute) else refute[i]
        verdict = (REPRODUCED if own[i] <= level else NOT_REPRODUCED if r is not None and r <= level
                   else NOT_DECIDABLE)
        out.append(Verdict(verdict, own[i], r, len(ok)))
    return out


def claim_power(kind: Kind, by: float | None, x: Any, y: Any, level: float) -> float:
    """The chance that these seeds reproduce the claim at ``level`` if it holds as stated: a true difference of
    ``by`` for better / worse / differs, a true difference of 0 for 'same' (normal scores with the observed
    standard deviations). NaN without a size or with fewer than 2 seeds an arm."""
    a, b = _finite(x), _finite(y)
    if by is None or a.size < 2 or b.size < 2:
        return math.nan
    sd_x, sd_y = float(np.std(a, ddof=1)), float(np.std(b, ddof=1))
    if kind == "same":
        return tost_power(a.size, b.size, by, sd_x, sd_y, level)
    if kind == "worse":
        return rank_sum_power(a.size, b.size, -by, sd_x, sd_y, level, "less")
    return rank_sum_power(a.size, b.size, by, sd_x, sd_y, level, "two-sided" if kind == "differs" else "greater")


def outcome(kind: str, verdict: str, by: float | None, x_above: bool) -> str:
    """What a verdict says about the scores, in words: 'better', 'short of +0.23', 'about the same', ..."""
    if verdict == NOT_DECIDABLE:
        return "not decidable"
    size = "" if by is None else f"{by:+.3g}" if kind != "same" else f"{by:.3g}"
    words = {("better", REPRODUCED): "better", ("better", NOT_REPRODUCED): f"short of {size}",
             ("worse", REPRODUCED): "worse", ("worse", NOT_REPRODUCED): f"not worse by {size.lstrip('+')}",
             ("same", REPRODUCED): "about the same",
             ("same", NOT_REPRODUCED): f"differs by more than {size}",
             ("differs", REPRODUCED): "better" if x_above else "worse"}
    return words.get((kind, verdict), verdict)


def statement(kind: str, x: str, y: str, by: float | None) -> str:
    """The claim in symbols, so a table of claims never reads as a verdict: 'X > Y (claimed +0.23)', ..."""
    if kind == "same":
        return f"{x} about the same as {y} (within {by:.3g})"
    if kind == "differs":
        return f"{x} differs from {y}"
    size = "" if by is None else f" (claimed {'+' if kind == 'better' else '-'}{abs(by):.3g})"
    return f"{x} {'>' if kind == 'better' else '<'} {y}{size}"
