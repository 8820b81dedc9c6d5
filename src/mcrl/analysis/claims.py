"""The thesis' claims, tested: its table beside ours, and a verdict on each directional claim.

A directional claim, "X reaches a higher final success rate than Y", is decided by a test with a known error rate,
declared in advance:

- **reproduced** when the one-sided exact rank-sum test of X > Y (:func:`mcrl.analysis.hypothesis.rank_sum_test`)
  has a Holm-adjusted p-value at most :data:`LEVEL` (0.05); Holm's adjustment runs over the claims of the report
  that share a baseline arm, so the chance that any of them is called reproduced when no arm differs is at most
  0.05;
- **not reproduced** when instead the one-sided test that X falls short of Y + the claimed difference (X shifted
  down by it, against Y) is significant the same way: an improvement as large as the thesis reports is excluded;
- **not decidable with this many seeds** otherwise, or with fewer than ``MIN_SEEDS_FOR_VERDICT`` seeds per arm.

P(X > Y) and the mean difference, with their bootstrap intervals, are reported beside it as effect sizes, with the
power the seeds had to detect the thesis' own difference. Each claim is tested against every SAC baseline of the
report (mcrl's SAC and any reference SAC, e.g. stable-baselines3's), and the report says whether the verdict
depends on which one is the baseline.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from mcrl.analysis.cells import (CONF, SEED, interval, is_code_variant, mcrl_groups, mean_cell, mean_ci, num, pvalue,
                                 reference_sac, sac_and_mc, sample_var, steps, too_few)
from mcrl.analysis.experiment import ConfigGroup, Experiment
from mcrl.analysis.hypothesis import holm, rank_sum_power, rank_sum_test
from mcrl.analysis.markdown import Block, Bullets, Heading, Paragraph, Table
from mcrl.analysis.stats import MIN_SEEDS_FOR_VERDICT, mean_difference_ci, probability_of_improvement
from mcrl.analysis.thesis import THESIS_RESULTS, thesis_experiment

LEVEL = 0.05  # the family-wise false-positive rate of "reproduced" among claims that share a baseline
REPRODUCED, NOT_REPRODUCED, NOT_DECIDABLE = "reproduced", "not reproduced", "not decidable with this many seeds"
CODE_VARIANT = "the thesis' code's variant of SAC-MC alpha=0.2 (one batch-mean KL, the whole observation)"


@dataclass(frozen=True)
class ClaimTest:
    """The two one-sided exact rank-sum tests of a claim "X beats Y by about ``claimed``" on final scores."""

    n_x: int
    n_y: int
    p_better: float  # H1: X > Y
    p_short: float  # H1: X - claimed < Y (the claimed improvement is too large)


def claim_test(x: Any, y: Any, claimed: float) -> ClaimTest:
    a, b = np.asarray(x, dtype=float).ravel(), np.asarray(y, dtype=float).ravel()
    a, b = a[np.isfinite(a)], b[np.isfinite(b)]
    if a.size == 0 or b.size == 0:
        return ClaimTest(a.size, b.size, math.nan, math.nan)
    return ClaimTest(a.size, b.size, rank_sum_test(a, b, "greater"), rank_sum_test(a - claimed, b, "less"))


@dataclass(frozen=True)
class Verdict:
    verdict: str
    p_better_adj: float | None  # Holm-adjusted; None when too few seeds
    p_short_adj: float | None
    family: int  # claims in its Holm family (those with enough seeds)


def decide(tests: Sequence[ClaimTest], level: float = LEVEL, min_seeds: int = MIN_SEEDS_FOR_VERDICT) -> list[Verdict]:
    """Verdicts on claims that share a baseline arm, Holm-adjusted within the family of those with enough seeds."""
    ok = [i for i, t in enumerate(tests) if min(t.n_x, t.n_y) >= min_seeds]
    better = dict(zip(ok, holm([tests[i].p_better for i in ok])))
    short = dict(zip(ok, holm([tests[i].p_short for i in ok])))
    out = []
    for i in range(len(tests)):
        if i not in better:
            out.append(Verdict(NOT_DECIDABLE, None, None, len(ok)))
        elif better[i] <= level:
            out.append(Verdict(REPRODUCED, better[i], short[i], len(ok)))
        elif short[i] <= level:
            out.append(Verdict(NOT_REPRODUCED, better[i], short[i], len(ok)))
        else:
            out.append(Verdict(NOT_DECIDABLE, better[i], short[i], len(ok)))
    return out


# ---------------------------------------------------------------------------------- the report's section


def _thesis_verdict(what: str, thesis: float, ours: float, ci: tuple[float, float] | None, n: int, digits: int) -> str:
    """Is the thesis' number inside our interval? (A description, not a test.)"""
    few = too_few(n)
    if few or ci is None:
        return f"{what}: {few or 'no confidence interval'} (thesis {thesis:.{digits}f}, ours {num(ours, digits)})."
    where = ("inside" if ci[0] <= thesis <= ci[1] else "above" if thesis > ci[1] else "below")
    text = f"{what}: the thesis' {thesis:.{digits}f} lies {where} our 95% CI {interval(ci, digits)} (our mean {ours:.{digits}f})"
    if where == "inside":
        return text + ": consistent with the thesis."
    return text + (": our runs do worse than the thesis reports." if where == "above"
                   else ": our runs do better than the thesis reports.")


def _table(exp: Experiment, t: dict[str, Any]) -> tuple[list[list[str]], list[str]]:
    rows, lines = [], []
    ours_all = [*mcrl_groups(exp), *(g for g in exp.configs if g.peer)]
    for alpha, th in t["by_alpha"].items():
        label = "SAC" if alpha == 0 else f"SAC-MC alpha={alpha:g}"
        ours = [g for g in ours_all if g.mc_alpha is not None and math.isclose(g.mc_alpha, alpha)
                and (alpha == 0 or g.intrinsic == "mc")]  # RND & co. at 0.2 are not the thesis' SAC-MC
        if not ours:
            rows.append([label, f"{th['success_mean']:.2f}", "not in this sweep", f"{th['success_var']:.2f}", "",
                         f"{th['mean_reward']:.1f}", "not in this sweep"])
        for g in ours:
            s, m = g.finals()
            (ms, cs), (mm, cm) = mean_ci(s), mean_ci(m)
            row_label = f"{label}, reference" if g.peer else label
            row_label += ", the thesis' code's variant" if alpha > 0 and is_code_variant(g) else ""
            rows.append([f"{row_label} (`{g.key}`)", f"{th['success_mean']:.2f}", mean_cell(ms, cs, s.size, 3),
                         f"{th['success_var']:.2f}", num(sample_var(s), 4), f"{th['mean_reward']:.1f}",
                         mean_cell(mm, cm, m.size, 2)])
            lines.append(_thesis_verdict(f"{row_label} (`{g.key}`) success rate", th["success_mean"], ms, cs, s.size, 2))
            lines.append(_thesis_verdict(f"{row_label} (`{g.key}`) mean return", th["mean_reward"], mm, cm, m.size, 1))
    return rows, lines


def _claim_lines(exp: Experiment, by_alpha: dict[float, dict[str, float]]) -> list[str]:
    """A verdict on each claim "SAC-MC alpha=0.2 beats SAC" against each SAC baseline (one Holm family per
    baseline), then whether the verdict depends on the baseline. A claim without finished runs says so."""
    if 0.2 not in by_alpha or 0 not in by_alpha:
        return []
    claimed = by_alpha[0.2]["success_mean"] - by_alpha[0]["success_mean"]
    sac, mc = sac_and_mc(exp)
    baselines = [*sac, *reference_sac(exp)]
    out: list[str] = []
    claims: list[tuple[str, ConfigGroup]] = []
    for what, variant in (("SAC-MC alpha=0.2", False), (CODE_VARIANT, True)):
        xs = [g for g in mc if math.isclose(g.mc_alpha or 0.0, 0.2) and is_code_variant(g) == variant]
        if not xs or not baselines:
            side = "SAC (mc_alpha = 0)" if not baselines else what
            hint = " (add its experiment with `--with DIR`)" if baselines and variant else ""
            out.append(f"**{NOT_DECIDABLE.capitalize()}**: {_claim_text(what, claimed)}: this report has no finished "
                       f"run of {side}, 0 seeds{hint}.")
        claims += [(what, x) for x in xs]
    results: dict[str, list[str]] = {}
    for y in baselines:
        tests = [claim_test(x.finals()[0], y.finals()[0], claimed) for _, x in claims]
        base = f"{'reference ' if y.peer else 'mcrl '}SAC `{y.key}`"
        for (what, x), t, v in zip(claims, tests, decide(tests)):
            out.append(_claim_line(_claim_text(what, claimed), x, y, base, t, v, claimed))
            results.setdefault(f"{what} (`{x.key}`)", []).append(
                f"{v.verdict} against {base} ({t.n_x} vs {t.n_y} seeds)")
    for what, res in results.items():
        if len(res) > 1:
            same = len({r.split(" against ")[0] for r in res}) == 1
            out.append(f"Does the verdict on {what} depend on which SAC is the baseline? "
                       f"{'No' if same else 'Yes'}: {'; '.join(res)}.")
    return out


def _claim_text(what: str, claimed: float) -> str:
    return f"the thesis' claim that {what} reaches a higher final success rate than SAC (thesis: {claimed:+.2f})"


def _claim_line(claim: str, x: ConfigGroup, y: ConfigGroup, base: str, t: ClaimTest, v: Verdict,
                claimed: float) -> str:
    sx, sy = x.finals()[0], y.finals()[0]
    head = f"**{v.verdict.capitalize()}**: {claim}, X = `{x.key}`, Y = {base}, {t.n_x} vs {t.n_y} seeds"
    if v.p_better_adj is None:
        return f"{head}: fewer than the {MIN_SEEDS_FOR_VERDICT} seeds per arm a verdict needs."
    family = (f"Holm-adjusted over the {v.family} claims against this baseline" if v.family > 1
              else "the only claim against this baseline, so unadjusted")
    tests = (f"one-sided exact rank-sum test of X > Y: p = {pvalue(t.p_better)} ({family}: {pvalue(v.p_better_adj)}); "
             f"of X falling short of Y {claimed:+.2f}: p = {pvalue(t.p_short)} (adjusted {pvalue(v.p_short_adj)})")
    p, p_lo, p_hi = probability_of_improvement(sx, sy, conf=CONF, seed=SEED)
    d, d_lo, d_hi = mean_difference_ci(sx, sy, conf=CONF, seed=SEED)
    level = LEVEL / v.family  # Holm's first step: a lower bound on its power
    power = rank_sum_power(t.n_x, t.n_y, claimed, float(np.std(sx, ddof=1)), float(np.std(sy, ddof=1)), level)
    return (f"{head}: {tests}; level {LEVEL}. Effect sizes: P(X > Y) = {p:.3f} [{p_lo:.3f}, {p_hi:.3f}], mean "
            f"difference {d:+.3f} [{d_lo:+.3f}, {d_hi:+.3f}]. Power of these seeds to detect the thesis' "
            f"{claimed:+.2f}: {num(power, 2)} (rank-sum test at level {level:.3g}, normal scores with the observed "
            "SDs).")


def thesis_section(exp: Experiment) -> list[Block]:
    """The comparison with the thesis' table and its claims, for presets that reproduce a thesis experiment."""
    name = thesis_experiment(exp.preset)
    if name is None:
        return []
    t = THESIS_RESULTS[name]
    ours_all = mcrl_groups(exp)
    budgets = sorted({r.total_steps for g in ours_all for r in g.runs if r.total_steps is not None})
    notes = []
    if budgets != [t["total_steps"]]:
        notes.append(f"**Not like-for-like:** our runs trained for {', '.join(map(steps, budgets)) or 'an unknown number of'} "
                     f"env steps, the thesis' for {steps(t['total_steps'])}; final numbers after a different "
                     "budget are not expected to match.")
    notes.append(f"The thesis used {t['seeds']} seeds per configuration ({t['tables']}); it does not say how its "
                 "'variance of success rate' was computed, ours is the sample variance of the final success rate "
                 "across seeds. Its 'mean reward' is compared with our mean final evaluation return.")
    notes.append(t["caveat"])
    if min((len(g.finished) for g in ours_all if g.finished), default=0) < 5:
        notes.append("With fewer than 5 seeds a percentile-bootstrap CI is too narrow (it covers the true mean "
                     "less than 95% of the time), so an 'outside our CI' reading is weaker than it reads.")
    rows, lines = _table(exp, t)
    claims = _claim_lines(exp, t["by_alpha"])
    return [
        Heading(2, f"Comparison with the thesis ({name})"),
        Table(["algorithm", "thesis success", "ours success [95% CI]", "thesis variance", "our variance",
               "thesis mean reward", "our mean final return [95% CI]"], rows),
        Bullets(lines or ["No configuration of this sweep has the thesis' mc_alpha (0 or 0.2) with finished runs."]),
        Heading(3, "The thesis' claims"),
        Paragraph(f"Each directional claim is decided by a one-sided exact rank-sum (Mann-Whitney) test on the final "
                  f"success rate at level {LEVEL}, declared before looking, with Holm's correction over the claims that "
                  "share a baseline arm: 'reproduced' when X > Y is significant, 'not reproduced' when X falling "
                  "short of Y plus the thesis' difference is, else 'not decidable'. Under the null this rule calls a "
                  f"claim reproduced at most {LEVEL:.0%} of the time at any number of seeds (tests/test_claims.py "
                  "simulates it). P(X > Y) and the mean difference are effect sizes with 95% bootstrap intervals."),
        Bullets(claims),
        Paragraph("**Caveats:**"),
        Bullets(notes),
    ]
