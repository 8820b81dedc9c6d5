"""Arms with another intrinsic reward (RND, ICM, Disagreement) against SAC and against SAC-MC, with verdicts that
keep their error rate (the rules of :mod:`mcrl.analysis.claims`).

Each arm X whose ``intrinsic`` is not ``mc`` (at ``intrinsic_alpha > 0``) is compared on the final success rate with:

- every SAC arm Y (mcrl's, and any reference SAC): "X reaches a higher final success rate than SAC" is the claim an
  exploration bonus makes, so it is tested one-sided (exact rank-sum): **better than SAC** when significant;
  **short of SAC + d** when X falling short of Y + d is, where d is the thesis' gain of SAC-MC over SAC on this task
  (a gain as large as MC's is excluded); else **not decidable**;
- every SAC-MC arm Z: no direction is declared, so the test is two-sided: **better than** or **worse than SAC-MC**
  when significant, else **not decidable**.

Holm's correction runs over the family of each baseline arm (every claim against it: :mod:`mcrl.analysis.families`),
so within each baseline the chance of any false verdict stays at most 5%. With fewer than ``MIN_SEEDS_FOR_VERDICT``
seeds per arm there is no verdict. P(X > Y) and the mean difference with bootstrap intervals are the effect sizes,
and each comparison states the power its seeds had to detect a difference of d.
"""

from __future__ import annotations

from mcrl.analysis.cells import (interval, is_scheduled, num, other_intrinsic, pvalue, reference_sac, sac_and_mc, steps,
                                 too_few)
from mcrl.analysis.claims import LEVEL, NOT_DECIDABLE, NOT_REPRODUCED, REPRODUCED
from mcrl.analysis.experiment import Experiment
from mcrl.analysis.families import ClaimResult, ReportClaims
from mcrl.analysis.markdown import Block, Bullets, Heading, Paragraph, Table
from mcrl.analysis.stats import MIN_SEEDS_FOR_VERDICT
from mcrl.analysis.thesis import env_ids, thesis_experiment, thesis_gain
from mcrl.analysis.verdicts import power_cell


def effect_of_interest(exp: Experiment) -> float | None:
    """The thesis' gain of SAC-MC 0.2 over SAC on this task (FetchPush: +0.23); None for other tasks."""
    return thesis_gain(thesis_experiment(exp.preset, env_ids(exp.runs)))


def _words(r: ClaimResult) -> str:
    """The verdict as this section words it: better than SAC, short of SAC +0.23, worse than SAC-MC, ..."""
    v = r.verdict.verdict
    if r.note:
        return f"{NOT_DECIDABLE}: {r.note}"
    if r.kind == "differs":
        return NOT_DECIDABLE if v != REPRODUCED else f"{'better' if r.test.x_above else 'worse'} than SAC-MC"
    if v == REPRODUCED:
        return "better than SAC"
    return f"short of SAC {r.by:+.2f}" if v == NOT_REPRODUCED and r.by is not None else NOT_DECIDABLE


def _row(r: ClaimResult) -> list[str]:
    assert r.x_group is not None and r.y_group is not None
    few = too_few(r.x.size, r.y.size)
    base = f"`{r.y_group.key}`" + (" (reference)" if r.y_group.peer else "")
    test = "two-sided" if r.kind == "differs" else "one-sided X > Y"
    if few:
        return [f"`{r.x_group.key}`", base, f"{r.x.size} / {r.y.size}", test, "-", "-", f"{NOT_DECIDABLE}: {few}",
                "-", "-", "-"]

    def ps(p: float, adj: float | None) -> str:
        return "-" if p != p else f"{pvalue(p)} ({'unadjusted' if adj is None else pvalue(adj)})"

    (p, lo, hi), (m, mlo, mhi) = r.effects
    return [f"`{r.x_group.key}`", base, f"{r.x.size} / {r.y.size}", test, ps(r.test.p, r.verdict.p_adj),
            ps(r.test.p_refute, r.verdict.p_refute_adj), f"**{_words(r)}**",
            f"{p:.3f} {interval((lo, hi), 3)}", f"{m:+.3f} [{mlo:+.3f}, {mhi:+.3f}]", power_cell(r)]


def intrinsic_section(exp: Experiment, claims: ReportClaims) -> list[Block]:
    """The report's section on arms with another intrinsic reward; nothing when the report has none."""
    arms = other_intrinsic(exp)
    if not arms:
        return []
    sac, mc = sac_and_mc(exp)
    sacs = [*sac, *reference_sac(exp)]
    d = effect_of_interest(exp)
    moving = any(is_scheduled(g) for g in arms)  # the words for schedules only where a report has one
    out: list[Block] = [Heading(2, "Other intrinsic rewards " + ("and schedules " if moving else "")
                                + "against SAC and SAC-MC")]
    missing = [what for what, have in (("SAC (intrinsic_alpha = 0)", sacs), ("SAC-MC (intrinsic=mc)", mc)) if not have]
    d_text = (f"d = {d:+.2f}, the thesis' gain of SAC-MC over SAC on this task" if d is not None
              else "no effect of interest is known for this task, so no 'short of' verdict and no power")
    out.append(Paragraph(
        "Each arm with another intrinsic reward than MC"
        + (", or whose weight moves during training (`intrinsic_schedule`)," if moving else "")
        + " is compared on the final success rate with every SAC arm and every SAC-MC arm"
        + (" (at a constant weight)" if moving else "") + ". Against SAC the claim an exploration bonus makes is "
        "tested one-sided (exact "
        "rank-sum): 'better than SAC' when significant, 'short of SAC + d' when the arm falling short of SAC plus "
        f"d is ({d_text}), else 'not decidable'. Against SAC-MC no direction is declared: a two-sided exact "
        f"rank-sum test. Level {LEVEL}, Holm-adjusted over the family of the baseline (every claim against it; "
        f"see [Verdicts](#verdicts) for its members and size); fewer than {MIN_SEEDS_FOR_VERDICT} seeds per arm give "
        "no verdict. P(X > Y) and the mean difference (95% bootstrap intervals) are effect sizes; the last column is "
        "the power the seeds had to detect a difference of d (normal scores with the observed SDs), at the level "
        "given: the first Holm level of the baseline's family."))
    if missing:
        out.append(Paragraph(f"This report has no finished run of {' or '.join(missing)}: add its experiment with "
                             "`mcrl report EXP --with DIR`."))
    comps = [r for y in sacs for x in arms if (r := claims.find(x, y, "better"))]
    comps += [r for z in mc for x in arms if (r := claims.find(x, z, "differs"))]
    if comps:
        out.append(Table(["X", "Y", "seeds X / Y", "test", "p (Holm-adjusted)",
                          "p of X short of Y + d (Holm-adjusted)", "verdict", "P(X > Y) [95% CI]",
                          "mean difference X - Y [95% CI]", f"power for {num(d, 2) if d is not None else 'd'}"],
                         [_row(r) for r in comps]))
    if len(sacs) > 1:
        lines = []
        for x in arms:
            res = [r for r in comps if r.x_group is x and r.kind == "better"]
            same = len({_words(r) for r in res}) == 1
            lines.append(f"Does the verdict on `{x.key}` depend on which SAC is the baseline? "
                         f"{'No' if same else 'Yes'}: " + "; ".join(
                             f"{_words(r)} against `{r.y_group.key}` ({r.x.size} vs {r.y.size} "  # type: ignore[union-attr]
                             "seeds)" for r in res) + ".")
        out.append(Bullets(lines))
    budgets = sorted({r.total_steps for g in arms for r in g.finished if r.total_steps is not None})
    others = sorted({r.total_steps for g in [*sac, *mc] for r in g.finished if r.total_steps is not None})
    if others and budgets != others:
        out.append(Paragraph(f"**Not like-for-like:** the intrinsic arms trained for {', '.join(map(steps, budgets))} "
                             f"steps, the baselines for {', '.join(map(steps, others))}."))
    return out
