"""The thesis' alpha curve beside mcrl's (issue 50): final success and return per intrinsic_alpha with intervals, a plot
against alpha with the thesis' numbers marked where it gives them (its words where it does not), and a verdict on
each of its claims about alpha > 0.2 (0.4 and 0.6 about the same as SAC, 0.8 and 1.0 worse), decided in the family
of mcrl's SAC arm (:mod:`mcrl.analysis.families`)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from mcrl.analysis.cells import is_code_variant, mean_cell, mean_ci, reference_sac, sac_and_mc
from mcrl.analysis.claims import LEVEL
from mcrl.analysis.experiment import ConfigGroup, Experiment
from mcrl.analysis.families import ClaimResult, ReportClaims
from mcrl.analysis.markdown import Block, Bullets, Figure, Heading, Paragraph, Table
from mcrl.analysis.plots import figure_to_png, panel_grid
from mcrl.analysis.thesis import equivalence_margin
from mcrl.analysis.verdicts import power_sentence, tests_sentence, verdict_cell

THESIS_WORDS = {"same": "about the same as SAC", "worse": "below SAC"}


def curve_groups(exp: Experiment) -> dict[float, ConfigGroup]:
    """mcrl's SAC and plain SAC-MC arms (the thesis' MC reward), by intrinsic_alpha; the first arm of each alpha."""
    sac, mc = sac_and_mc(exp)
    out: dict[float, ConfigGroup] = {}
    for g in [*sac, *mc]:
        if not is_code_variant(g):
            out.setdefault(round(float(g.intrinsic_alpha or 0.0), 6), g)
    return dict(sorted(out.items()))


def _thesis_cells(alpha: float, t: dict[str, Any]) -> tuple[str, str, float | None, float | None]:
    """(thesis success, thesis mean reward) as the table shows them, and as numbers where the thesis gives them."""
    if alpha in t["by_alpha"]:
        th = t["by_alpha"][alpha]
        return f"{th['success_mean']:.2f}", f"{th['mean_reward']:.1f}", th["success_mean"], th["mean_reward"]
    c = t["alpha_curve"].get(alpha)
    if c is None:
        return "-", "-", None, None
    words = "comparable to SAC ('becomes comparable')" if c["claim"] == "same" else "'relatively low'"
    reward = (f"about {c['mean_reward']:.1f} ('a mean reward of {abs(c['mean_reward'])}')" if "mean_reward" in c
              else "'decrease'")
    return words, reward, None, c.get("mean_reward")


def _plot(groups: dict[float, ConfigGroup], refs: list[ConfigGroup], t: dict[str, Any], margin: float | None) -> bytes:
    fig, axes = panel_grid(2)
    sac_th = t["by_alpha"][0.0]
    for ax, col, ylabel, th_key in ((axes[0], 0, "final success rate", "success_mean"),
                                    (axes[1], 1, "final return", "mean_reward")):
        xs, ms, lo, hi = [], [], [], []
        for a, g in groups.items():
            v = g.finals()[col]
            m, ci = mean_ci(v)
            if math.isfinite(m):
                xs.append(a), ms.append(m), lo.append(m - (ci[0] if ci else m)), hi.append((ci[1] if ci else m) - m)
        ax.errorbar(xs, ms, yerr=[lo, hi], fmt="o-", color="C0", capsize=3, label="mcrl (mean, 95% CI)")
        for i, g in enumerate(refs):
            m, ci = mean_ci(g.finals()[col])
            if math.isfinite(m):
                ax.errorbar([0.02 * (i + 1)], [m], yerr=[[m - (ci[0] if ci else m)], [(ci[1] if ci else m) - m]],
                            fmt="s", color="0.5", capsize=3, label=f"{g.key} (reference)")
        pts = [(a, v[th_key]) for a, v in t["by_alpha"].items()]
        pts += [(a, c["mean_reward"]) for a, c in t["alpha_curve"].items() if th_key == "mean_reward" and "mean_reward" in c]
        ax.plot(*zip(*sorted(pts)), "x", color="C3", ms=9, mew=2, label="thesis (its numbers)")
        same = [a for a, c in t["alpha_curve"].items() if c["claim"] == "same" and th_key == "success_mean"]
        if same and margin:
            ax.errorbar(same, [sac_th[th_key]] * len(same), yerr=margin, fmt="o", mfc="none", color="C3", capsize=3,
                        label=f"thesis: about SAC's (words; +/-{margin:.3g})")
        worse = [a for a, c in t["alpha_curve"].items() if c["claim"] == "worse"]
        ax.plot(worse, [sac_th[th_key]] * len(worse), "v", mfc="none", color="C3", ms=9,
                label="thesis: below SAC's (words)")
        ax.set_xticks(sorted({*groups, *t["by_alpha"], *t["alpha_curve"]}))
        ax.set_xlabel("intrinsic_alpha (share of the MC reward)")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    return figure_to_png(fig)


def _line(a: float, claim: str, r: ClaimResult | None, g: ConfigGroup | None) -> str:
    text = f"the thesis' claim that SAC-MC alpha={a:.1f} is {THESIS_WORDS[claim]}"
    if r is None:
        why = "this report has no finished run of it, 0 seeds (add its experiment with `--with DIR`)" if g is None \
            else "this report has no SAC arm (intrinsic_alpha = 0) to test it against"
        return f"**Not decidable with this many seeds**: {text}: {why}."
    cell = verdict_cell(r)
    head = f"{cell[:2]}{cell[2:3].upper()}{cell[3:]}: {text}, X = `{g.key if g else r.x_name}`, Y = {r.y_name}, {r.test.n_x} vs {r.test.n_y} seeds"
    if r.note or r.verdict.p_adj is None:
        return head + "."
    (p, plo, phi), (d, dlo, dhi) = r.effects
    return (f"{head}: {tests_sentence(r)}; level {LEVEL}. Effect sizes: P(X > Y) = {p:.3f} [{plo:.3f}, {phi:.3f}], "
            f"mean difference {d:+.3f} [{dlo:+.3f}, {dhi:+.3f}]. {power_sentence(r)}")


def alpha_curve_blocks(exp: Experiment, claims: ReportClaims, t: dict[str, Any]) -> list[Block]:
    """The subsection on the thesis' alpha curve; nothing for an experiment whose thesis has none."""
    curve = t.get("alpha_curve")
    if not curve:
        return []
    groups = curve_groups(exp)
    sac = groups.get(0.0)
    margin = next((r.by for r in claims.results if r.kind == "same"), None) or equivalence_margin("FetchPush")
    rows, lines = [], []
    for a in sorted({*t["by_alpha"], *curve, *groups}):
        g = groups.get(a)
        th_s, th_r, _, _ = _thesis_cells(a, t)
        s, m = g.finals() if g else (np.empty(0), np.empty(0))
        (ms, cs), (mm, cm) = mean_ci(s), mean_ci(m)
        r = None
        if a in curve and g is not None and sac is not None:
            r = claims.find(g, sac, curve[a]["claim"])
        rows.append([f"{a:.1f}", th_s, mean_cell(ms, cs, s.size, 3) if s.size else "not in this report",
                     th_r, mean_cell(mm, cm, m.size, 2) if m.size else "not in this report", str(s.size),
                     THESIS_WORDS[curve[a]["claim"]] if a in curve else "-",
                     verdict_cell(r) if r else "-"])
        if a in curve:
            lines.append(_line(a, curve[a]["claim"], r, g))
    refs = reference_sac(exp)
    return [
        Heading(3, "The thesis' alpha curve"),
        Paragraph("Final success and return per intrinsic_alpha, mcrl's arms (95% bootstrap CIs) beside the thesis' section "
                  "4.1.3, which gives numbers for 0 and 0.2 (Tables 4.2-4.3) and two mean rewards, and words for the "
                  "rest: at 0.4 and 0.6 'the success rate ... becomes comparable to that of the baseline SAC' and the "
                  "average reward 'converges with that of the baseline SAC with a mean reward of 28.81 and 28.96' "
                  "(printed without their sign; FetchPush's returns lie in [-50, 0]); at 0.8 and 1.0 'the Success "
                  "rate and the average rewards decrease' and the success rates 'are relatively low'. 'About the "
                  f"same' is tested with a margin of {margin:.3g}, half the thesis' SAC-MC 0.2 lead, by two one-sided "
                  "exact rank-sum tests (TOST); 'below SAC' as a one-sided test of X < Y, refuted when a deficit as "
                  "large as that lead is excluded. Both are tested against mcrl's SAC in its family."),
        Table(["intrinsic_alpha", "thesis success", "ours success [95% CI]", "thesis mean reward",
               "ours final return [95% CI]", "seeds", "thesis' claim", "verdict"], rows),
        Figure("alpha_curve.png", _plot(groups, refs, t, margin),
               "Final success and return against intrinsic_alpha: mcrl's arms (mean, 95% bootstrap CI; grey squares: "
               "reference SAC arms at alpha 0), the thesis' numbers (x), its 'about the same as SAC' (hollow circle "
               "at its SAC value, bar: the margin) and its 'below SAC' (hollow triangle at its SAC value)."),
        Bullets(lines),
    ]
