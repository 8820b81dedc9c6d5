"""The comparison with the thesis: its table beside ours, a verdict on each of its claims (decided in the claims'
families, :mod:`mcrl.analysis.families`), and its alpha curve (:mod:`mcrl.analysis.alpha_curve`).

Each claim against SAC is tested against every SAC baseline of the report (mcrl's SAC and any reference SAC, e.g.
stable-baselines3's), and the report says whether the verdict depends on which one is the baseline.
"""

from __future__ import annotations

import math
from typing import Any

from mcrl.algo.intrinsic import THESIS_REWARD
from mcrl.analysis.alpha_curve import alpha_curve_blocks
from mcrl.analysis.cells import (interval, is_code_variant, mcrl_groups, mean_cell, mean_ci, num, reference_sac,
                                 sac_and_mc, sample_var, steps, too_few)
from mcrl.analysis.claims import LEVEL, NOT_DECIDABLE
from mcrl.analysis.experiment import ConfigGroup, Experiment
from mcrl.analysis.families import CODE_VARIANT, ClaimResult, ReportClaims
from mcrl.analysis.markdown import Block, Bullets, Heading, Paragraph, Table
from mcrl.analysis.stats import MIN_SEEDS_FOR_VERDICT
from mcrl.analysis.thesis import THESIS_RESULTS, env_ids, thesis_experiment, thesis_gain
from mcrl.analysis.verdicts import power_sentence, tests_sentence


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


def thesis_arms(exp: Experiment, t: dict[str, Any]) -> list[tuple[str, dict[str, Any], list[ConfigGroup]]]:
    """Each row of the thesis' table (its label, its numbers) with the configurations of ``exp`` it is held against:
    mcrl's and the reference arms at its alpha, SAC-MC's only with the thesis' reward (RND & co. at 0.2 are not the
    thesis' SAC-MC)."""
    ours_all = [*mcrl_groups(exp), *(g for g in exp.configs if g.peer)]
    return [("SAC" if alpha == 0 else f"SAC-MC alpha={alpha:g}", th,
             [g for g in ours_all if g.intrinsic_alpha is not None and math.isclose(g.intrinsic_alpha, alpha)
              and (alpha == 0 or g.intrinsic == THESIS_REWARD)])
            for alpha, th in t["by_alpha"].items()]


def _budgets(exp: Experiment) -> list[int]:
    """The training budgets (total_steps) of mcrl's runs in ``exp``, ascending; a run never started has none."""
    return sorted({r.total_steps for g in mcrl_groups(exp) for r in g.runs if r.total_steps is not None})


def thesis_at_budget(exp: Experiment) -> tuple[str, dict[str, Any]] | None:
    """The thesis' table (its name, its entry in THESIS_RESULTS) when every mcrl run of ``exp`` trains for the
    thesis' own budget, so that its final numbers can stand at the end of our curves; else None."""
    name = thesis_experiment(exp.preset, env_ids(exp.runs))
    if name is None:
        return None
    return (name, THESIS_RESULTS[name]) if _budgets(exp) == [THESIS_RESULTS[name]["total_steps"]] else None


def _table(exp: Experiment, t: dict[str, Any]) -> tuple[list[list[str]], list[str]]:
    rows, lines = [], []
    for label, th, ours in thesis_arms(exp, t):
        if not ours:
            rows.append([label, f"{th['success_mean']:.2f}", "not in this sweep", f"{th['success_var']:.2f}", "",
                         f"{th['mean_reward']:.1f}", "not in this sweep"])
        for g in ours:
            s, m = g.finals()
            (ms, cs), (mm, cm) = mean_ci(s), mean_ci(m)
            row_label = f"{label}, reference" if g.peer else label
            row_label += ", the thesis' code's variant" if label != "SAC" and is_code_variant(g) else ""
            rows.append([f"{row_label} (`{g.key}`)", f"{th['success_mean']:.2f}", mean_cell(ms, cs, s.size, 3),
                         f"{th['success_var']:.2f}", num(sample_var(s), 4), f"{th['mean_reward']:.1f}",
                         mean_cell(mm, cm, m.size, 2)])
            lines.append(_thesis_verdict(f"{row_label} (`{g.key}`) success rate", th["success_mean"], ms, cs, s.size, 2))
            lines.append(_thesis_verdict(f"{row_label} (`{g.key}`) mean return", th["mean_reward"], mm, cm, m.size, 1))
    return rows, lines


def claim_line(claim: str, r: ClaimResult) -> str:
    """One thesis claim's verdict with its tests, family, effect sizes and power."""
    assert r.x_group is not None and r.y_group is not None
    base = f"{'reference ' if r.y_group.peer else 'mcrl '}SAC `{r.y_group.key}`"
    head = (f"**{r.verdict.verdict.capitalize()}**: {claim}, X = `{r.x_group.key}`, Y = {base}, "
            f"{r.test.n_x} vs {r.test.n_y} seeds")
    if r.note:
        return f"{head}: {r.note}; {tests_sentence(r)}."
    if r.verdict.p_adj is None:
        return f"{head}: fewer than the {MIN_SEEDS_FOR_VERDICT} seeds per arm a verdict needs."
    (p, p_lo, p_hi), (d, d_lo, d_hi) = r.effects
    return (f"{head}: {tests_sentence(r)}; level {LEVEL}. Effect sizes: P(X > Y) = {p:.3f} [{p_lo:.3f}, "
            f"{p_hi:.3f}], mean difference {d:+.3f} [{d_lo:+.3f}, {d_hi:+.3f}]. {power_sentence(r)}")


def _claim_text(what: str, claimed: float) -> str:
    return f"the thesis' claim that {what} reaches a higher final success rate than SAC (thesis: {claimed:+.2f})"


def depends_on_baseline(results: list[ClaimResult]) -> list[str]:
    """For each X tested against more than one SAC: does its verdict depend on which SAC is the baseline?"""
    out, by_x = [], {}
    for r in results:
        by_x.setdefault(id(r.x_group), []).append(r)
    for res in by_x.values():
        if len(res) > 1:
            same = len({r.verdict.verdict for r in res}) == 1
            x = res[0]
            out.append(f"Does the verdict on {x.what} (`{x.x_group.key}`) depend on which SAC is the baseline? "  # type: ignore[union-attr]
                       f"{'No' if same else 'Yes'}: " + "; ".join(
                           f"{r.verdict.verdict} against {'reference' if r.y_group.peer else 'mcrl'} SAC "  # type: ignore[union-attr]
                           f"`{r.y_group.key}` ({r.test.n_x} vs {r.test.n_y} seeds)" for r in res) + ".")  # type: ignore[union-attr]
    return out


def _claim_lines(exp: Experiment, claims: ReportClaims, claimed: float) -> list[str]:
    """A verdict on each claim "SAC-MC alpha=0.2 beats SAC" against each SAC baseline, then whether the verdict
    depends on the baseline. A claim without finished runs says so."""
    out: list[str] = []
    mine = [r for r in claims.results if r.kind == "better" and r.source.startswith("thesis")
            and r.x_group is not None and r.y_group is not None and r.what in ("SAC-MC alpha=0.2", CODE_VARIANT)]
    baselines = list(dict.fromkeys(id(r.y_group) for r in mine))
    for what in ("SAC-MC alpha=0.2", CODE_VARIANT):
        if not any(r.what == what for r in mine):
            have_sac = bool(sac_and_mc(exp)[0] or reference_sac(exp))
            side = "SAC (intrinsic_alpha = 0)" if not have_sac else what
            hint = " (add its experiment with `--with DIR`)" if have_sac and what == CODE_VARIANT else ""
            out.append(f"**{NOT_DECIDABLE.capitalize()}**: {_claim_text(what, claimed)}: this report has no finished "
                       f"run of {side}, 0 seeds{hint}.")
    order = {"SAC-MC alpha=0.2": 0, CODE_VARIANT: 1}
    mine.sort(key=lambda r: (baselines.index(id(r.y_group)), order[r.what]))
    out += [claim_line(_claim_text(r.what, claimed), r) for r in mine]
    return out + depends_on_baseline(mine)


def thesis_section(exp: Experiment, claims: ReportClaims) -> list[Block]:
    """The comparison with the thesis' table and its claims, for presets that reproduce a thesis experiment."""
    name = thesis_experiment(exp.preset, env_ids(exp.runs))
    if name is None:
        return []
    t = THESIS_RESULTS[name]
    ours_all = mcrl_groups(exp)
    budgets = _budgets(exp)
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
    gain = thesis_gain(name)
    claim_lines = _claim_lines(exp, claims, gain) if gain is not None else []
    return [
        Heading(2, f"Comparison with the thesis ({name})"),
        Table(["algorithm", "thesis success", "ours success [95% CI]", "thesis variance", "our variance",
               "thesis mean reward", "our mean final return [95% CI]"], rows),
        Bullets(lines or ["No configuration of this sweep has the thesis' intrinsic_alpha (0 or 0.2) with finished runs."]),
        Heading(3, "The thesis' claims"),
        Paragraph(f"Each directional claim is decided by a one-sided exact rank-sum (Mann-Whitney) test on the final "
                  f"success rate at level {LEVEL}, declared before looking, with Holm's correction over the claims that "
                  "share a baseline arm (its family; see [Verdicts](#verdicts)): 'reproduced' when X > Y is "
                  "significant, 'not reproduced' when X falling short of Y plus the thesis' difference is, else 'not "
                  f"decidable'. Under the null this rule calls a claim reproduced at most {LEVEL:.0%} of the time at "
                  "any number of seeds (tests/test_claims.py simulates it). P(X > Y) and the mean difference are "
                  "effect sizes with 95% bootstrap intervals."),
        Bullets(claim_lines),
        *alpha_curve_blocks(exp, claims, t),
        Paragraph("**Caveats:**"),
        Bullets(notes),
    ]
