"""The report of a sequential experiment (``mcrl report EXP`` where ``EXP/plan.yaml`` exists): the confirmatory
verdict first, then the plan, each look's z against its bounds, and the usual results on the looked-at runs only.

No report shows a batch's results before its look: runs whose seeds no look has used yet are left out, even when
they have finished (their small files are committed as they finish). :func:`answer_markdown` is the verdict as the
README's answer block quotes it (``mcrl report EXP --readme README.md`` writes it there; a test compares them).
"""
from __future__ import annotations

import textwrap
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from mcrl.analysis.markdown import Block, Bullets, Figure, Heading, Paragraph, Table
from mcrl.decide.look import CONTINUE
from mcrl.decide.plan import Plan, load_plan
from mcrl.decide.runner import boundary_table, read_looks

PLAN = "plan.yaml"
ANSWER_START, ANSWER_END = "<!-- confirmatory:start -->", "<!-- confirmatory:end -->"


def is_sequential(experiment_dir: str | Path) -> bool:
    return (Path(experiment_dir) / PLAN).is_file()


def _claim_words(plan: Plan, name: str) -> str:
    c = next(c for c in plan.claims if c.name == name)
    return f"{c.better} ends higher than {c.than}"


def _interval(c: dict) -> str:
    """A claim's repeated confidence interval of the shift at one look, with its coverage; "-" while none."""
    rci = c.get("shift_rci")
    return f"[{rci[0]:+.2f}, {rci[1]:+.2f}] ({1 - 2 * c['level']:.0%})" if rci else "-"


def _decision_text(plan: Plan, look: dict, name: str) -> str:
    c = look["claims"][name]
    words = _claim_words(plan, name)
    if c["decision"] == CONTINUE:
        return (f"{words}: not decided yet (look {look['look']}, {c['n_x']} v {c['n_y']} seeds: z {c['z']:+.2f}, "
                f"continuing between {c['lower']:+.2f} and {c['upper']:.2f})" if c.get("lower") is not None else
                f"{words}: not decided yet (look {look['look']}: z {c['z']:+.2f}, efficacy bound {c['upper']:.2f})")
    interval = f"; repeated confidence interval of the shift {_interval(c)}" if c.get("shift_rci") else ""
    return (f"{words}: **{c['decision']}** at look {c['decided_at']} ({c['n_x']} v {c['n_y']} seeds; mean final "
            f"success {c['mean_x']:.2f} v {c['mean_y']:.2f}, difference {c['difference']:+.2f}{interval}; "
            f"{c['reason']}; level {c['level']:g} in force)")


def answer_markdown(experiment_dir: str | Path) -> str:
    """The confirmatory verdict in a few lines: what the README leads with. Depends only on the plan and its looks."""
    plan = load_plan(Path(experiment_dir) / PLAN)
    looks = read_looks(plan)
    p = plan.primary
    head = (f"Confirmatory experiment, preregistered before its runs: {len(plan.arms)} arms at "
            f"`{plan.preset}` on fresh seeds ({plan.seeds[0]}-{plan.seeds[-1]}), looks every {plan.batch} seeds an "
            f"arm up to {plan.max_seeds}, family-wise one-sided error at most {plan.level:g} "
            f"({plan.multiplicity}; primary {p.level:g}, {p.spending}-type spending, non-binding futility).")
    if not looks:
        return _wrap(head + f" **Not decided yet: no look taken.** Look 1 needs {plan.batch} finished seeds of every "
                     f"arm ({plan.batch * len(plan.arms)} runs). Primary claim: {_claim_words(plan, p.name)}.")
    last = looks[-1]
    lines = [_wrap(head), ""]
    lines.append(_wrap(f"- Primary: {_decision_text(plan, last, p.name)}.", "  "))
    for c in plan.claims:
        if not c.primary:
            lines.append(_wrap(f"- Secondary: {_decision_text(plan, last, c.name)}.", "  "))
    state = "decided" if last["done"] else f"continuing with {', '.join(last['continue_arms'])}"
    lines.append(f"- {len(looks)} look(s) taken; {state}.")
    return "\n".join(lines)


def _wrap(text: str, indent: str = "") -> str:
    return textwrap.fill(text, width=115, subsequent_indent=indent, break_long_words=False, break_on_hyphens=False)


def looked_seeds(plan: Plan, looks: Sequence[dict]) -> set[str]:
    """Names of the runs some look has used."""
    if not looks:
        return set()
    return {plan.run_name(arm, s) for arm, seeds in looks[-1]["seeds"].items() for s in seeds}


def _z_plot(plan: Plan, looks: Sequence[dict]) -> bytes:
    from mcrl.analysis.plots import COLORS, figure_to_png, panel_grid

    fig, axes = panel_grid(len(plan.claims))
    planned = boundary_table(plan)
    for ax, c, color in zip(axes, plan.claims, COLORS):
        rows = [r for r in planned if r["claim"] == c.name and r["level"] == c.level]
        n = [r["seeds_per_arm"] for r in rows]
        ax.plot(n, [r["upper"] for r in rows], "--", color="0.5", label=f"efficacy bound at {c.level:g} (planned)")
        ax.plot(n, [r["lower"] if r["lower"] is not None else np.nan for r in rows], ":", color="0.5",
                label="futility bound (planned)")
        pts = [(lk["claims"][c.name]["n_x"], lk["claims"][c.name]["z"], lk["claims"][c.name].get("upper"),
                lk["claims"][c.name].get("lower")) for lk in looks
               if lk["claims"][c.name].get("decided_at", lk["look"]) >= lk["look"]]
        if pts:
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", color=color, label="z at each look")
            ax.plot([p[0] for p in pts], [p[2] if p[2] is not None else np.nan for p in pts], "v", color="k",
                    label="bound in force")
        ax.axhline(0, color="0.8", lw=0.8)
        ax.set_title(f"{c.name}{' (primary)' if c.primary else ''}")
        ax.set_xlabel("seeds an arm")
        ax.set_ylabel("rank-sum z")
        ax.legend(fontsize=7)
    return figure_to_png(fig)


def sequential_section(experiment_dir: str | Path) -> list[Block]:
    d = Path(experiment_dir)
    plan = load_plan(d / PLAN)
    looks = read_looks(plan)
    blocks: list[Block] = [Heading(2, "Confirmatory verdict (preregistered sequential plan)"),
                           Paragraph(answer_markdown(d))]
    claim_rows = []
    for lk in looks:
        for name, c in lk["claims"].items():
            if c.get("decided_at", lk["look"]) < lk["look"]:
                continue  # decided earlier: its row is that look's
            claim_rows.append([str(lk["look"]), name, f"{c['n_x']} v {c['n_y']}", f"{c['z']:+.3f}",
                               "-" if c.get("lower") is None else f"{c['lower']:+.3f}",
                               "-" if c.get("upper") is None else f"{c['upper']:.3f}",
                               f"{c['level']:g}", f"{c['alpha_spent']:.4f}", f"{c['difference']:+.3f}",
                               _interval(c),
                               f"{c['p_fixed_sample']:.4f}" if "p_fixed_sample" in c else "-", c["decision"]])
    if claim_rows:
        blocks += [Heading(3, "Looks"), Table(["look", "claim", "seeds", "z", "futility bound", "efficacy bound",
                                                "level in force", "alpha spent", "difference of means",
                                                "repeated confidence interval of the shift",
                                                "fixed-sample p (naive)", "decision"], claim_rows),
                   Paragraph("The fixed-sample p ignores the looks and is shown for orientation only: the decision is "
                             "z against the bounds. The repeated confidence interval of the shift (coverage 1 - 2 x "
                             "the level in force, by inverting the rank-sum test at the look's efficacy bound) holds "
                             "at every look at once, so it stays valid whenever the experiment stops.")]
    blocks.append(Figure("sequential_z.png", _z_plot(plan, looks),
                         "z of each claim at each look against its bounds (dashed: planned at the claim's own level)"))
    blocks += [Heading(3, "The plan"), Bullets([
        f"file `{plan.path.name}`, hash `{plan.hash}`; runs at commit `{plan.commit or 'not pinned'}`",
        "arms: " + "; ".join(f"`{a}` = `{plan.preset}` + {ov or '{}'}" for a, ov in plan.arms.items()),
        f"seeds {plan.seeds[0]}-{plan.seeds[-1]} in order, {plan.batch} an arm per look, at most {plan.max_seeds} "
        f"({plan.max_looks} looks)",
        f"test: one-sided rank-sum on {plan.metric}, tie-corrected; family level {plan.level:g}, "
        f"multiplicity {plan.multiplicity}",
        *[f"claim `{c.name}`{' (primary)' if c.primary else ''}: {c.better} > {c.than}, level {c.level:g}, "
          f"{c.spending}-type spending" + (f", futility beta {c.futility.beta:g} ({c.futility.spending}) under "
                                          f"P(X > Y) = {c.futility.effect:g}" if c.futility else ", no futility rule")
          for c in plan.claims]])]
    return blocks


def _learn_rates(exp, plan: Plan) -> list[Block]:
    """Exploratory: how often a seed of each looked-at arm learns (final >= 0.2), beside reference arms."""
    from mcrl.analysis.hypothesis import fisher_exact

    rows, groups = [], [g for g in exp.configs if g.finished]
    base = next((g for g in groups if g.peer is None and (g.intrinsic_alpha or 0) == 0), None)
    if base is None:
        return []
    b = base.finals()[0]
    for g in groups:
        s = g.finals()[0]
        k = int(np.sum(s >= 0.2))
        p = "" if g is base else f"{fisher_exact(k, len(s), int(np.sum(b >= 0.2)), len(b)):.3f}"
        rows.append([g.key + (f" ({g.peer})" if g.peer else ""), f"{k} of {len(s)}", p])
    return [Heading(3, "Exploratory: how often a seed learns"),
            Paragraph(f"Seeds ending at 0.2 or more, and Fisher's exact test (two-sided) against `{base.key}`: "
                      "exploratory, not part of the plan; the plan's verdict is the one above."),
            Table(["arm", "seeds with final >= 0.2", "Fisher p against fresh SAC"], rows)]


def sequential_report(experiment_dir: str | Path, extra_runs: Sequence[str | Path] = ()) -> list[Block]:
    """The whole report of a sequential experiment."""
    from mcrl.analysis.experiment import group_runs, load_experiment
    from mcrl.analysis.provenance import provenance
    from mcrl.analysis.sections import results

    d = Path(experiment_dir)
    plan = load_plan(d / PLAN)
    looks = read_looks(plan)
    blocks: list[Block] = [Heading(1, f"mcrl report: {d.name} (confirmatory)")] + sequential_section(d)
    if not looks:
        return blocks + [Paragraph("No look has been taken: the runs' results stay out of this report until the "
                                   "look that uses them.")]
    exp = load_experiment(d, extra_runs)
    keep = looked_seeds(plan, looks)
    here = d.resolve()
    runs = [r for r in exp.runs if r.name in keep or (r.source is not None and Path(r.source).resolve() != here)]
    exp = replace(exp, runs=runs, configs=group_runs(runs))
    return blocks + _learn_rates(exp, plan) + results(exp) + provenance(exp, None)


def write_answer(experiment_dir: str | Path, readme: str | Path) -> bool:
    """Put :func:`answer_markdown` between the README's confirmatory markers; True if it changed."""
    path = Path(readme)
    readme_answer(path)
    text = path.read_text()
    head, rest = text.split(ANSWER_START, 1)
    _, tail = rest.split(ANSWER_END, 1)
    new = f"{head}{ANSWER_START}\n{answer_markdown(experiment_dir)}\n{ANSWER_END}{tail}"
    if new != text:
        path.write_text(new)
    return new != text


def readme_answer(readme: str | Path) -> str:
    """The text between the README's confirmatory markers; MCRLError when it has none."""
    from mcrl.errors import MCRLError

    text = Path(readme).read_text()
    if ANSWER_START not in text or ANSWER_END not in text.split(ANSWER_START, 1)[-1]:
        raise MCRLError(f"{readme} has no {ANSWER_START} ... {ANSWER_END} block: add the two markers where the "
                        "confirmatory verdict goes")
    return text.split(ANSWER_START, 1)[1].split(ANSWER_END, 1)[0].strip("\n")


__all__ = ["answer_markdown", "is_sequential", "readme_answer", "sequential_report", "sequential_section",
           "write_answer"]
