"""The sections of ``mcrl report`` that apply to any experiment: tables, figures and readings, as typed blocks
(:mod:`mcrl.analysis.markdown`). The claims and their verdicts are :mod:`mcrl.analysis.verdicts`, the thesis'
comparison :mod:`mcrl.analysis.comparison`, how the report was made :mod:`mcrl.analysis.provenance`;
:mod:`mcrl.analysis.report` puts them in order.

Every reading of a result (a difference between configurations) is drawn only when each configuration it compares
has at least ``MIN_SEEDS_FOR_VERDICT`` finished seeds, and comes from an exact test
(:mod:`mcrl.analysis.hypothesis`) with Holm's correction over the report's comparisons; otherwise the report says
there are too few seeds.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence

import numpy as np

from mcrl.analysis.cells import (CONF, SEED, mean_cell, mean_ci, name, num, other_intrinsic, pvalue,
                                 sac_and_mc, sample_var, steps, too_few)
from mcrl.analysis.divergence import CriticCheck, Rate, check_critics, lag_steps
from mcrl.analysis.claims import LEVEL
from mcrl.analysis.comparison import thesis_arms, thesis_at_budget
from mcrl.analysis.experiment import ConfigGroup, Experiment
from mcrl.analysis.families import ReportClaims
from mcrl.analysis.hypothesis import fisher_exact, holm, rank_sum_test
from mcrl.analysis.markdown import Block, Bullets, Figure, Heading, Paragraph, Table
from mcrl.analysis.plots import arm_colors, curves_by_config, figure_to_png, has_data, panel_grid, plot_curves_with_band
from mcrl.analysis.reward_curves import reward_section
from mcrl.analysis.runs import Run
from mcrl.analysis.verdicts import level
from mcrl.analysis.stats import (
    MIN_SEEDS_FOR_VERDICT,
    minimum_detectable_difference,
    probability_of_improvement,
    seeds_to_detect,
    stratified_iqm_ci,
)

ALPHA, POWER = 0.05, 0.8  # of the minimum detectable difference; ALPHA is also the level of the readings


def _source(runs: Sequence[Run]) -> str:
    """Where the final numbers of these runs come from, e.g. 'final_eval.json, 100 episodes (3)'."""
    counts = Counter(r.final_source for r in runs if r.final_source is not None)
    parts = [f"{'final_eval.json' if src == 'final_eval.json' else 'last eval.csv row'}, "
             f"{'?' if n is None else n} episodes" + (f" ({c})" if len(counts) > 1 else "")
             for (src, n), c in sorted(counts.items(), key=lambda kv: -kv[1])]
    return "; ".join(parts) or "-"


def _comparisons(exp: Experiment) -> list[tuple[ConfigGroup, ConfigGroup]]:
    """(X, Y) pairs compared: each SAC-MC configuration with each SAC one, each configuration with another
    intrinsic reward with each SAC and each SAC-MC one, and mcrl's SAC with each finished reference arm."""
    sac, mc = sac_and_mc(exp)
    others = other_intrinsic(exp)
    peers = [g for g in exp.configs if g.peer and g.finished]
    return ([(x, y) for x in mc for y in sac] + [(x, y) for x in others for y in [*sac, *mc]]
            + [(y, p) for y in sac for p in peers])


# ---------------------------------------------------------------------------------- sections


def summary(exp: Experiment) -> list[Block]:
    """The report's title and what it is made of, in a few lines; how it was made comes last (:func:`mcrl.analysis.provenance.provenance`)."""
    n_done = sum(r.status == "finished" for r in exp.runs)
    envs = sorted({str(r.config["env_id"]) for r in exp.runs if "env_id" in r.config})
    budgets = sorted({r.total_steps for r in exp.runs if r.total_steps is not None})
    return [Heading(1, f"mcrl report: {exp.dir.name}"), Bullets([
        f"preset: `{exp.preset or '?'}`; environment: {', '.join(f'`{e}`' for e in envs) or '?'}; training budget "
        f"(total_steps): {', '.join(steps(b) for b in budgets) or '?'}",
        f"runs finished: {n_done} of {len(exp.runs)}"
        + ("" if n_done == len(exp.runs) else " (see [Missing and unfinished runs](#missing-and-unfinished-runs))"),
        f"configurations: {', '.join(f'`{g.key}`' for g in exp.configs)}",
        "provenance (commits, machines, commands) and method: [at the end](#provenance-and-method)",
    ])]


def _curve_source(r: Run, col: str) -> dict[str, np.ndarray]:
    """The columns a curve of `col` comes from: metrics.csv for the intrinsic weight, eval.csv for the rest."""
    return r.metrics if col == "intrinsic_alpha" else r.eval if r.has_eval else {}


def _learning_curves(exp: Experiment) -> list[Block]:
    # the intrinsic weight beside success where a run's schedule moves it (metrics.csv's intrinsic_alpha)
    moving = any(r.config.get("intrinsic_schedule", "constant") != "constant" for r in exp.runs)
    panels = [("success_rate", "eval success rate", "success rate"), ("mean_return", "eval mean return", "return")]
    if moving:
        panels.insert(1, ("intrinsic_alpha", "intrinsic weight alpha in force", "alpha"))
    fig, axes = panel_grid(len(panels), ncols=len(panels))
    colors = arm_colors([g.key for g in exp.configs])
    thesis = thesis_at_budget(exp)
    for ax, (col, title, ylabel) in zip(axes, panels):
        _plot_arms(ax, exp, col, lambda r, c=col: _curve_source(r, c), title, ylabel, colors)
        if thesis is not None and col in _THESIS_FINAL:
            _thesis_stars(ax, exp, thesis[1], col, colors)
    partial = sum(r.status == "partial" and r.has_eval for r in exp.runs)
    return [
        Heading(2, "Learning curves"),
        Figure("learning_curves.png", figure_to_png(fig),
         "Deterministic evaluation during training: mean over seeds, shaded 95% bootstrap band over seeds "
         f"where at least {MIN_SEEDS_FOR_VERDICT} seeds have the point; where fewer do, thin lines are the seeds' own curves."
         + (" Dashed: reference arms (not trained by mcrl)." if any(g.peer for g in exp.configs) else "")
         + (" Middle: the intrinsic weight in force at each log row, as each run's schedule set it." if moving else "")
         + (f" Stars at {steps(thesis[1]['total_steps'])} env steps: the thesis' final success rate and mean "
            f"reward ({thesis[1]['tables']}), in the colour of the configuration held against them."
            if thesis is not None else "")
         + (f" {partial} unfinished run(s) are included up to their last evaluation." if partial else "")),
    ]


_THESIS_FINAL = {"success_rate": "success_mean", "mean_return": "mean_reward"}  # our curve: the thesis' number


def _plot_arms(ax, exp: Experiment, col: str, source, title: str, ylabel: str, colors: dict[str, str],
               logy: bool = False) -> None:
    """Each configuration's curve of ``col`` (from ``source(run)``), mcrl's arms solid, reference arms dashed."""
    for peers, style in ((False, "-"), (True, "--")):
        series = [(g.key, source(r)) for g in exp.configs if bool(g.peer) == peers
                  for r in g.runs if has_data(source(r), col)]
        if series or not peers:
            grid, by_cfg = curves_by_config(series, col)
            plot_curves_with_band(ax, grid, by_cfg, title=title, ylabel=ylabel, colors=colors, seed=SEED,
                                  linestyle=style, logy=logy)


def _thesis_stars(ax, exp: Experiment, t: dict, col: str, colors: dict[str, str]) -> None:
    """The thesis' final number of ``col`` for each row of its table, a star at its budget in the colour of the
    first configuration held against that row (none where no configuration is)."""
    for label, th, ours in thesis_arms(exp, t):
        if ours:
            ax.plot([t["total_steps"]], [th[_THESIS_FINAL[col]]], linestyle="none", marker="*", markersize=12,
                    color=colors[ours[0].key], markeredgecolor="black", markeredgewidth=0.5, label=f"thesis: {label}")
    ax.legend(fontsize=7, loc="best")


def _critic_curves(exp: Experiment) -> list[Block]:
    """The critics' mean Q and the entropy coefficient over training, per configuration: what the bound's table
    summarises, and the two quantities a reader checks first when a SAC run stalls or diverges."""
    panels = [("q_mean", "mean Q (replay batches)", "Q", False),
              ("ent_coef", "entropy coefficient", "alpha (entropy)", True)]
    if not any(has_data(r.metrics, col) for r in exp.runs for col, *_ in panels):
        return []
    fig, axes = panel_grid(len(panels), ncols=len(panels))
    colors = arm_colors([g.key for g in exp.configs])
    for ax, (col, title, ylabel, logy) in zip(axes, panels):
        _plot_arms(ax, exp, col, lambda r: r.metrics, title, ylabel, colors, logy=logy)
    axes[0].set_yscale("symlog", linthresh=1.0)  # a diverging arm's Q (1e4 and up) would flatten the others' to 0
    return [
        Paragraph("The critics' mean Q over the replay batches (symmetric log scale: linear within +-1) and SAC's "
                  "entropy coefficient (log scale) during "
                  f"training, from metrics.csv: mean over seeds, 95% bootstrap band where >= {MIN_SEEDS_FOR_VERDICT} "
                  "seeds have the point, unfinished runs up to their last log row."),
        Figure("critics_entropy.png", figure_to_png(fig), "Mean Q and entropy coefficient from metrics.csv."),
    ]


def _final_table(exp: Experiment) -> list[Block]:
    rows = []
    for g in exp.configs:
        s, m = g.finals()
        ms, cs = mean_ci(s)
        mm, cm = mean_ci(m)
        budgets = sorted({r.total_steps for r in g.finished if r.total_steps is not None})
        rows.append([name(g), num(g.intrinsic_alpha, 2), f"{s.size} / {len(g.runs)}",
                     ", ".join(map(steps, budgets)) or steps(g.total_steps),  # none finished: the configured budget
                     mean_cell(ms, cs, s.size, 3), num(sample_var(s), 4), mean_cell(mm, cm, m.size, 2),
                     _source(g.finished)])
    return [
        Heading(2, "Final performance per configuration"),
        Paragraph("Final evaluation of each finished run across seeds: mean with 95% bootstrap CI, and sample variance "
              "(ddof=1) of the success rate, as in the thesis' tables. A run's final numbers come from its "
              "final_eval.json (the evaluation at the end of training, with final_eval_episodes episodes) when it "
              "has one, else from the last row of its eval.csv; the last column says which, and over how many "
              "episodes."),
        Table(["configuration", "intrinsic_alpha", "seeds finished", "total_steps", "mean success [95% CI]",
                   "variance of success", "mean final return [95% CI]", "final numbers from"], rows),
    ]


def _per_seed_table(exp: Experiment) -> list[Block]:
    rows = []
    for g in exp.configs:
        for r in g.runs:
            fin, src = r.final, r.final_source
            status = {"missing": "missing", "partial": "unfinished"}.get(r.status, "no evaluation")
            rows.append([name(g), "?" if r.seed is None else str(r.seed), f"`{r.name}`",
                         num(fin[0], 3) if fin else status, num(fin[1], 2) if fin else "-",
                         f"{'final_eval.json' if src[0] == 'final_eval.json' else 'last eval.csv row'}, "
                         f"{'?' if src[1] is None else src[1]} episodes" if src else "-"])
    return [
        Heading(2, "Final performance per seed"),
        Paragraph("The final evaluation of every run, by configuration and seed."),
        Table(["configuration", "seed", "run", "final success", "final return", "from"], rows),
    ]


def _reading(p_adj: float, nx: int, ny: int, y: str, x_wins: bool) -> str:
    """A two-sided exact test's reading of X against Y, from its Holm-adjusted p-value."""
    few = too_few(nx, ny)
    if few:
        return few
    if p_adj <= ALPHA:
        return f"{'better' if x_wins else 'worse'} than {y} (adjusted p = {pvalue(p_adj)})"
    return f"no clear difference (adjusted p = {pvalue(p_adj)})"


def _two_sided(pairs: list[tuple[np.ndarray, np.ndarray]]) -> list[float]:
    """Holm-adjusted two-sided exact rank-sum p-values of the pairs with enough seeds (NaN for the others)."""
    ok = [i for i, (a, b) in enumerate(pairs) if min(a.size, b.size) >= MIN_SEEDS_FOR_VERDICT]
    adj = dict(zip(ok, holm([rank_sum_test(*pairs[i], "two-sided") for i in ok])))
    return [adj.get(i, math.nan) for i in range(len(pairs))]


def _robust_stats(exp: Experiment) -> list[Block]:
    out: list[Block] = [Heading(2, "IQM and probability of improvement")]
    groups = [g for g in exp.configs if g.finished]
    succ = stratified_iqm_ci({g.key: g.finals()[0] for g in groups}, conf=CONF, seed=SEED)
    ret = stratified_iqm_ci({g.key: g.finals()[1] for g in groups}, conf=CONF, seed=SEED)
    out += [
        Paragraph("Interquartile mean (25% trimmed mean) of the final evaluation over finished seeds, with "
              "stratified-bootstrap 95% CIs (rliable's method; the overview names the implementation that ran). "
              "With fewer than 4 seeds the IQM is the plain mean."),
        Table(["configuration", "seeds", "IQM success [95% CI]", "IQM final return [95% CI]"],
         [[name(g), str(len(g.finished)), mean_cell(succ[g.key][0], succ[g.key][1:], len(g.finished), 3),
           mean_cell(ret[g.key][0], ret[g.key][1:], len(g.finished), 2)] for g in groups]),
    ]
    sac, mc = sac_and_mc(exp)
    if not sac or not mc:
        missing = "no finished SAC configuration (intrinsic_alpha = 0)" if not sac else "no finished SAC-MC configuration (intrinsic_alpha > 0)"
        out.append(Paragraph(f"Probability of improvement of SAC-MC over SAC: not computed, the sweep has {missing}."))
    pairs = _comparisons(exp)
    if not pairs:
        return out
    finals = [(x.finals(), y.finals()) for x, y in pairs]
    p_succ = _two_sided([(fx[0], fy[0]) for fx, fy in finals])
    p_ret = _two_sided([(fx[1], fy[1]) for fx, fy in finals])
    rows = []
    for (x, y), ((sx, mx), (sy, my)), p_s, p_m in zip(pairs, finals, p_succ, p_ret):
        ps = probability_of_improvement(sx, sy, conf=CONF, seed=SEED)
        pm = probability_of_improvement(mx, my, conf=CONF, seed=SEED)
        yname = "SAC" if any(y is g for g in sac) else f"`{y.key}`"
        n_s, n_m = min(sx.size, sy.size), min(mx.size, my.size)
        rows.append([f"`{x.key}` > `{y.key}`", f"{sx.size} / {sy.size}", mean_cell(ps[0], ps[1:], n_s, 3),
                     _reading(p_s, sx.size, sy.size, yname, ps[0] > 0.5), mean_cell(pm[0], pm[1:], n_m, 3),
                     _reading(p_m, mx.size, my.size, yname, pm[0] > 0.5)])
    return out + [
        Paragraph("Probability of improvement P(X > Y): the chance that a random finished seed of configuration X "
                  "ends above a random seed of configuration Y (ties count half; 0.5 = no difference), with "
                  "stratified-bootstrap 95% CIs (rliable's method; the overview names the implementation that ran), "
                  "an effect size. X is each SAC-MC configuration against mcrl's SAC, each configuration with another "
                  "intrinsic reward against SAC and SAC-MC, and mcrl's SAC against each reference arm. The reading "
                  f"comes from a two-sided exact rank-sum (Mann-Whitney) test at level {ALPHA}, Holm-adjusted over "
                  f"the {len(pairs)} comparisons of each column, so the chance of "
                  f"reading any difference where there is none stays at most {ALPHA:.0%}."),
        Table(["comparison", "seeds X / Y", "P(X > Y), success [95% CI]", "reading (success)",
                   "P(X > Y), final return [95% CI]", "reading (return)"], rows),
    ]


def _test_level(claims: ReportClaims | None, x: ConfigGroup, y: ConfigGroup) -> tuple[float, str, str, str]:
    """(level, sides, in words, the claim's kind or "") of the test the verdicts run on X against Y: that of its
    declared claim, at its family's first Holm level (as its power), one-sided for better / worse, two-sided for
    differs and same (whose refutation, a difference beyond the margin, is two-sided); two-sided at ALPHA where
    no claim is declared."""
    r = next((r for r in claims.results if r.x_group is x and r.y_group is y and not r.exploratory),
             None) if claims else None
    if r is None:
        return ALPHA, "two-sided", f"two-sided, {ALPHA} (no claim)", ""
    sides = "one-sided" if r.kind in ("better", "worse") else "two-sided"
    m = r.family.with_seeds
    side = {"better": " X > Y", "worse": " X < Y", "same": " (of 'about the same')"}.get(r.kind, "")
    words = f"{sides}{side}, {level(r.level)}" + (f" = {LEVEL} / {m}" if m > 1 else "")
    return r.level, sides, words, r.kind


def _detectable(exp: Experiment, claims: ReportClaims | None = None) -> list[Block]:
    """How large a difference in mean final success these seeds can detect, per comparison, at the test and level
    the verdicts use for it."""
    out: list[Block] = [Heading(2, "How large a difference can these seeds detect")]
    pairs = _comparisons(exp)
    if not pairs:
        return out + [Paragraph("Not computed: no finished SAC configuration (intrinsic_alpha = 0) and another finished "
                            "configuration to compare it with.")]
    rows = []
    for x, y in pairs:
        sx, sy = x.finals()[0], y.finals()[0]
        sx, sy = sx[np.isfinite(sx)], sy[np.isfinite(sy)]
        few = too_few(sx.size, sy.size)
        diff = float(sx.mean() - sy.mean()) if sx.size and sy.size else math.nan
        a, sides, test, kind = _test_level(claims, x, y)
        mde = minimum_detectable_difference(sx, sy, a, POWER, sides)
        other_side = (kind == "better" and diff < 0) or (kind == "worse" and diff > 0)
        need = None if other_side else seeds_to_detect(sx, sy, diff, a, POWER, sides)
        rows.append([f"`{x.key}` vs `{y.key}`", f"{sx.size} / {sy.size}",
                     f"{num(math.sqrt(sample_var(sx)), 3)} / {num(math.sqrt(sample_var(sy)), 3)}", num(diff, 3),
                     test, few or num(mde, 3),
                     few or ("n/a (the other side)" if other_side else "n/a" if need is None else str(need))])
    return out + [
        Paragraph("The minimum detectable difference (MDE) is the smallest true difference in mean final success "
                  f"that a two-sample test finds with probability {POWER}, at the test and level the verdicts use "
                  "for the comparison (column 'test, level'): one-sided for a claim that X lies above or below Y, "
                  "two-sided for one that they differ or are about the same (whose refutation, a difference beyond "
                  "the margin, is two-sided), at "
                  f"the first Holm level of the claim's family ({LEVEL} / m, where its power is computed); "
                  f"two-sided at {ALPHA} where no claim is declared. It is computed from the seed counts and the "
                  "standard deviations of final success observed here (Welch/normal approximation: MDE = "
                  "(z_(1-a) + z_0.8) * sqrt(s_X^2/n_X + s_Y^2/n_Y) one-sided at level a, z_(1-a/2) two-sided). A "
                  "true difference smaller than the MDE is likely to go unnoticed with these seeds. The last column "
                  "is the number of seeds per configuration at which the MDE, at the same test and level, would "
                  "shrink to the observed difference (same spread assumed); none where the observed difference lies "
                  "on the other side of a one-sided claim."),
        Table(["comparison", "seeds X / Y", "sd of final success X / Y", "observed difference X - Y",
               "test, level", "minimum detectable difference", "seeds each to detect the observed difference"],
              rows),
    ]


def _missing_section(exp: Experiment) -> list[Block]:
    out: list[Block] = [Heading(2, "Missing and unfinished runs")]
    bad = [(g, r) for g in exp.configs for r in g.runs if r.status != "finished" or r.final is None]
    if not bad:
        return out + [Paragraph(f"None: all {len(exp.runs)} runs finished.")]
    rows = []
    for g, r in sorted(bad, key=lambda gr: exp.runs.index(gr[1])):
        status = {"missing": "missing (no run directory)", "partial": "unfinished (no `done` file)",
                  "finished": "finished, but eval.csv has no rows"}[r.status]
        rows.append([f"`{r.name}`", f"`{g.key}`", str(r.seed), status,
                     f"{steps(r.last_step) if r.last_step is not None else '-'} / {steps(r.total_steps or g.total_steps)}"])
    return out + [
        Paragraph(f"{len(bad)} of {len(exp.runs)} runs are left out of the final-performance statistics "
              "(unfinished runs still appear in the learning curves up to their last evaluation). Re-run or "
              "resume them, then write the report again."),
        Table(["run", "configuration", "seed", "status", "last logged step / total_steps"], rows),
    ]


def _critic_section(exp: Experiment) -> list[Block]:
    """Per run: did its critics leave the soft-Q bound (mcrl.analysis.divergence), when, by how much; per arm: the
    rate with an exact interval, and Fisher's test against mcrl's SAC arm."""
    out: list[Block] = [Heading(2, "Critics against the soft-Q bound")]
    checks: dict[str, list[tuple[Run, CriticCheck]]] = {}
    for g in exp.configs:
        for r in g.finished:
            c = check_critics(r.metrics, r.config)
            if c is not None:
                checks.setdefault(g.key, []).append((r, c))
    if not checks:
        return out + [Paragraph("Not computed: no finished run logs `q_mean` and `ent_coef` on an environment whose "
                                "reward bound is known (mcrl.envs.FAMILIES).")] + _critic_curves(exp)
    cfg = next(r.config for runs in checks.values() for r, _ in runs)
    lag = lag_steps(float(cfg.get("gamma", 0.99)), float(cfg.get("tau", 0.005)))
    rows = [[f"`{key}`", f"`{r.name}`", "yes" if c.left else "no", steps(c.first_outside) if c.left else "-",
             f"{c.rows_outside} / {c.rows}", "yes" if c.outside_at_end else "no", f"{c.peak_q:.1f} at {steps(c.peak_step)}",
             f"{c.max_excess:+.2f} at {steps(c.max_excess_step)}"] for key, runs in checks.items() for r, c in runs]
    rates = {key: Rate(sum(c.left for _, c in runs), len(runs)) for key, runs in checks.items()}
    sac = [g.key for g in sac_and_mc(exp)[0] if g.key in rates]
    rate_rows = []
    for key, rate in rates.items():
        vs = "-" if not sac or key == sac[0] else (
            f"p = {pvalue(fisher_exact(rate.k, rate.n, rates[sac[0]].k, rates[sac[0]].n))} vs `{sac[0]}`")
        rate_rows.append([f"`{key}`", str(rate), vs])
    return out + [
        Paragraph("A soft Q-value cannot exceed r_max / (1 - gamma) + c gamma d log 2 / (1 - gamma): rewards are at "
                  "most r_max (FetchPush: 0) and a tanh-squashed policy on [-1, 1]^d has at most d log 2 nats of "
                  "entropy, weighted by the entropy coefficient c. The critics lag behind a falling c, so the bound at "
                  f"a step uses the largest c logged in the preceding {lag:,} gradient steps, 1 / (tau (1 - gamma)), "
                  "the critics' time constant. A run whose logged mean Q is above it has left the bound: its critics "
                  "hold a value no policy could earn (details: mcrl.analysis.divergence). The bound is generous, so "
                  "a run inside it may still overestimate."),
        Table(["configuration", "run", "left the bound", "first step outside", "rows outside", "outside at the end",
               "peak mean Q", "largest mean Q - bound"], rows),
        Paragraph("Rate of runs whose critics left the bound, with an exact (Clopper-Pearson) 95% interval, and "
                  "Fisher's exact test (two-sided) against mcrl's SAC arm."),
        Table(["configuration", "left the bound", "vs SAC"], rate_rows),
        *_critic_curves(exp),
    ]


def results(exp: Experiment, claims: ReportClaims | None = None) -> list[Block]:
    """The sections after the verdicts and the thesis' comparison: final numbers, curves, effect sizes, what the
    seeds can detect, critics, the MC reward, every seed, and what is missing."""
    return (_final_table(exp) + _learning_curves(exp) + _robust_stats(exp) + _detectable(exp, claims)
            + _critic_section(exp) + reward_section(exp) + _per_seed_table(exp) + _missing_section(exp))
