"""Arms with another intrinsic reward (RND, ICM, Disagreement) against SAC and against SAC-MC, with verdicts that
keep their error rate (the rules of :mod:`mcrl.analysis.claims`).

Each arm X whose ``intrinsic`` is not ``mc`` (at ``mc_alpha > 0``) is compared on the final success rate with:

- every SAC arm Y (mcrl's, and any reference SAC): "X reaches a higher final success rate than SAC" is the claim an
  exploration bonus makes, so it is tested one-sided (exact rank-sum): **better than SAC** when significant;
  **short of SAC + d** when X falling short of Y + d is, where d is the thesis' gain of SAC-MC over SAC on this task
  (a gain as large as MC's is excluded); else **not decidable**;
- every SAC-MC arm Z: no direction is declared, so the test is two-sided: **better than** or **worse than SAC-MC**
  when significant, else **not decidable**.

Holm's correction runs over the arms compared with one baseline arm, so within each baseline the chance of any
false verdict stays at most 5%. With fewer than ``MIN_SEEDS_FOR_VERDICT`` seeds per arm there is no verdict.
P(X > Y) and the mean difference with bootstrap intervals are the effect sizes, and each comparison states the
power its seeds had to detect a difference of d.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mcrl.analysis.cells import (CONF, SEED, interval, num, other_intrinsic, pvalue, reference_sac, sac_and_mc,
                                 sample_var, steps, too_few)
from mcrl.analysis.claims import LEVEL, NOT_DECIDABLE, NOT_REPRODUCED, REPRODUCED, claim_test, decide
from mcrl.analysis.experiment import ConfigGroup, Experiment
from mcrl.analysis.hypothesis import holm, rank_sum_power, rank_sum_test
from mcrl.analysis.markdown import Block, Bullets, Heading, Paragraph, Table
from mcrl.analysis.stats import (MIN_SEEDS_FOR_VERDICT, improvement_point, mean_difference_ci,
                                 probability_of_improvement)
from mcrl.analysis.thesis import THESIS_RESULTS, thesis_experiment


@dataclass(frozen=True)
class Comparison:
    """One arm against one baseline: the test, its Holm-adjusted p-value within the baseline's family, verdict."""

    x: ConfigGroup
    y: ConfigGroup
    test: str  # "one-sided X > Y" | "two-sided"
    p: float | None  # None with too few seeds
    p_adj: float | None
    p_short: float | None  # one-sided tests only: of X falling short of Y + d
    p_short_adj: float | None
    verdict: str
    power: float  # to detect a shift of the effect of interest (NaN when unknown)


def effect_of_interest(exp: Experiment) -> float | None:
    """The thesis' gain of SAC-MC 0.2 over SAC on this task (FetchPush: +0.23); None for other tasks."""
    t = THESIS_RESULTS.get(thesis_experiment(exp.preset) or "")
    return None if t is None else t["by_alpha"][0.2]["success_mean"] - t["by_alpha"][0.0]["success_mean"]


def _power(x: np.ndarray, y: np.ndarray, d: float | None, level: float, alternative: str) -> float:
    if d is None or x.size == 0 or y.size == 0:
        return math.nan
    sd_x, sd_y = math.sqrt(sample_var(x)), math.sqrt(sample_var(y))
    return rank_sum_power(x.size, y.size, d, sd_x, sd_y, level, alternative)  # type: ignore[arg-type]


def against_sac(arms: list[ConfigGroup], sac: ConfigGroup, d: float | None) -> list[Comparison]:
    """Each arm's one-sided claim "better than SAC", Holm over the arms (one family per SAC arm)."""
    y = sac.finals()[0]
    tests = [claim_test(x.finals()[0], y, d if d is not None else 0.0) for x in arms]
    words = {REPRODUCED: "better than SAC", NOT_REPRODUCED: f"short of SAC {d:+.2f}" if d is not None else NOT_DECIDABLE,
             NOT_DECIDABLE: NOT_DECIDABLE}
    out = []
    for x, t, v in zip(arms, tests, decide(tests)):
        level = LEVEL / max(v.family, 1)  # Holm's first step: a lower bound on its power
        tested = v.p_better_adj is not None
        out.append(Comparison(x, sac, "one-sided X > Y", t.p_better if tested else None, v.p_better_adj,
                              t.p_short if tested and d is not None else None, v.p_short_adj if d is not None else None,
                              words[v.verdict], _power(x.finals()[0], y, d, level, "greater")))
    return out


def against_mc(arms: list[ConfigGroup], mc: ConfigGroup, d: float | None) -> list[Comparison]:
    """Each arm against SAC-MC, two-sided, Holm over the arms (one family per SAC-MC arm)."""
    z = mc.finals()[0]
    ok = [i for i, x in enumerate(arms) if min(x.finals()[0].size, z.size) >= MIN_SEEDS_FOR_VERDICT]
    raw = {i: rank_sum_test(arms[i].finals()[0], z, "two-sided") for i in ok}
    adj = dict(zip(ok, holm([raw[i] for i in ok])))
    out = []
    for i, x in enumerate(arms):
        sx = x.finals()[0]
        verdict = NOT_DECIDABLE
        if i in adj and adj[i] <= LEVEL:
            verdict = "better than SAC-MC" if improvement_point(sx, z) > 0.5 else "worse than SAC-MC"  # U's side
        out.append(Comparison(x, mc, "two-sided", raw.get(i), adj.get(i), None, None, verdict,
                              _power(sx, z, d, LEVEL / max(len(ok), 1), "two-sided")))
    return out


def _row(c: Comparison) -> list[str]:
    sx, sy = c.x.finals()[0], c.y.finals()[0]
    few = too_few(sx.size, sy.size)
    base = f"`{c.y.key}`" + (" (reference)" if c.y.peer else "")
    if few:
        return [f"`{c.x.key}`", base, f"{sx.size} / {sy.size}", c.test, "-", "-", f"{NOT_DECIDABLE}: {few}",
                "-", "-", "-"]

    def ps(p: float | None, adj: float | None) -> str:
        return "-" if p is None or adj is None else f"{pvalue(p)} ({pvalue(adj)})"

    p, lo, hi = probability_of_improvement(sx, sy, conf=CONF, seed=SEED)
    m, mlo, mhi = mean_difference_ci(sx, sy, conf=CONF, seed=SEED)
    return [f"`{c.x.key}`", base, f"{sx.size} / {sy.size}", c.test, ps(c.p, c.p_adj), ps(c.p_short, c.p_short_adj),
            f"**{c.verdict}**",
            f"{p:.3f} {interval((lo, hi), 3)}", f"{m:+.3f} [{mlo:+.3f}, {mhi:+.3f}]", num(c.power, 2)]


def intrinsic_section(exp: Experiment) -> list[Block]:
    """The report's section on arms with another intrinsic reward; nothing when the report has none."""
    arms = other_intrinsic(exp)
    if not arms:
        return []
    sac, mc = sac_and_mc(exp)
    sacs = [*sac, *reference_sac(exp)]
    d = effect_of_interest(exp)
    out: list[Block] = [Heading(2, "Other intrinsic rewards against SAC and SAC-MC")]
    missing = [what for what, have in (("SAC (mc_alpha = 0)", sacs), ("SAC-MC (intrinsic=mc)", mc)) if not have]
    d_text = (f"d = {d:+.2f}, the thesis' gain of SAC-MC over SAC on this task" if d is not None
              else "no effect of interest is known for this task, so no 'short of' verdict and no power")
    out.append(Paragraph(
        "Each arm with another intrinsic reward than MC is compared on the final success rate with every SAC arm "
        "and every SAC-MC arm. Against SAC the claim an exploration bonus makes is tested one-sided (exact "
        "rank-sum): 'better than SAC' when significant, 'short of SAC + d' when the arm falling short of SAC plus "
        f"d is ({d_text}), else 'not decidable'. Against SAC-MC no direction is declared: a two-sided exact "
        f"rank-sum test. Level {LEVEL}, Holm-adjusted over the arms compared with the same baseline; fewer than "
        f"{MIN_SEEDS_FOR_VERDICT} seeds per arm give no verdict. P(X > Y) and the mean difference (95% bootstrap "
        "intervals) are effect sizes; the last column is the power the seeds had to detect a difference of d "
        "(normal scores with the observed SDs)."))
    if missing:
        out.append(Paragraph(f"This report has no finished run of {' or '.join(missing)}: add its experiment with "
                             "`mcrl report EXP --with DIR`."))
    comps = [c for y in sacs for c in against_sac(arms, y, d)] + [c for z in mc for c in against_mc(arms, z, d)]
    if comps:
        out.append(Table(["X", "Y", "seeds X / Y", "test", "p (Holm-adjusted)",
                          "p of X short of Y + d (Holm-adjusted)", "verdict", "P(X > Y) [95% CI]",
                          "mean difference X - Y [95% CI]", f"power for {num(d, 2) if d is not None else 'd'}"],
                         [_row(c) for c in comps]))
    if len(sacs) > 1:
        lines = []
        for x in arms:
            res = [c for c in comps if c.x is x and any(c.y is y for y in sacs)]
            same = len({c.verdict for c in res}) == 1
            lines.append(f"Does the verdict on `{x.key}` depend on which SAC is the baseline? "
                         f"{'No' if same else 'Yes'}: " + "; ".join(
                             f"{c.verdict} against `{c.y.key}` ({c.x.finals()[0].size} vs {c.y.finals()[0].size} "
                             "seeds)" for c in res) + ".")
        out.append(Bullets(lines))
    budgets = sorted({r.total_steps for g in arms for r in g.finished if r.total_steps is not None})
    others = sorted({r.total_steps for g in [*sac, *mc] for r in g.finished if r.total_steps is not None})
    if others and budgets != others:
        out.append(Paragraph(f"**Not like-for-like:** the intrinsic arms trained for {', '.join(map(steps, budgets))} "
                             f"steps, the baselines for {', '.join(map(steps, others))}."))
    return out
