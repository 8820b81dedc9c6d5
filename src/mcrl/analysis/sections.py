"""The sections of ``mcrl report``: tables, figures and verdicts, as blocks (:mod:`mcrl.analysis.markdown`).

Every reading of a result (a difference between configurations, a thesis claim borne out or not)
is drawn only when each configuration it compares has at least ``MIN_SEEDS_FOR_VERDICT`` finished
seeds; otherwise the report says there are too few seeds.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Sequence

import numpy as np

from mcrl.analysis.experiment import ConfigGroup, Experiment, Run
from mcrl.analysis.markdown import Block
from mcrl.analysis.plots import COLORS, figure_to_png, has_data, panel_grid, plot_curves_with_band
from mcrl.analysis.stats import (
    MIN_SEEDS_FOR_VERDICT,
    NOT_DECIDABLE,
    Interval,
    align_curves,
    bootstrap_backend,
    bootstrap_ci,
    claim_verdict,
    minimum_detectable_difference,
    probability_of_improvement,
    seeds_to_detect,
    stratified_iqm_ci,
)
from mcrl.analysis.thesis import THESIS_RESULTS, thesis_experiment

CONF = 0.95
SEED = 0  # every bootstrap in a report uses it: the same runs give the same report
ALPHA, POWER = 0.05, 0.8  # of the minimum detectable difference


# ------------------------------------------------------------------------------- formatting


def _f(x: float | None, digits: int) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def _ci(iv: tuple[float, float] | None, digits: int) -> str:
    return "n/a" if iv is None else f"[{_f(iv[0], digits)}, {_f(iv[1], digits)}]"


def _steps(n: float | int | None) -> str:
    return "?" if n is None else f"{int(n):,}"


def _code(s: str) -> str:
    return f"`{s}`" if "`" not in s else s


def _name(g: ConfigGroup) -> str:
    """A group's table cell: its label, marked when it is a reference arm."""
    return f"`{g.key}` (reference)" if g.peer else f"`{g.key}`"


def _mean_ci(x: np.ndarray) -> tuple[float, tuple[float, float] | None]:
    """Mean and 95% percentile-bootstrap CI over seeds; no CI from fewer than 2 seeds."""
    if x.size == 0:
        return math.nan, None
    return float(x.mean()), (bootstrap_ci(x, np.mean, conf=CONF, rng=SEED) if x.size >= 2 else None)


def _var(x: np.ndarray) -> float:
    """Sample variance across seeds (ddof=1); NaN for fewer than 2 seeds."""
    return float(x.var(ddof=1)) if x.size >= 2 else math.nan


def too_few(*ns: int) -> str | None:
    """The report's text for a reading from too few seeds, or None when every n is enough."""
    if min(ns) >= MIN_SEEDS_FOR_VERDICT:
        return None
    return f"too few seeds for a verdict (n={' vs '.join(map(str, ns))}, need >= {MIN_SEEDS_FOR_VERDICT})"


def _source(runs: Sequence[Run]) -> str:
    """Where the final numbers of these runs come from, e.g. 'final_eval.json, 100 episodes (3)'."""
    counts = Counter(r.final_source for r in runs if r.final_source is not None)
    parts = [f"{'final_eval.json' if src == 'final_eval.json' else 'last eval.csv row'}, "
             f"{'?' if n is None else n} episodes" + (f" ({c})" if len(counts) > 1 else "")
             for (src, n), c in sorted(counts.items(), key=lambda kv: -kv[1])]
    return "; ".join(parts) or "-"


def _mcrl(exp: Experiment) -> list[ConfigGroup]:
    return [g for g in exp.configs if g.peer is None]


def _sac_and_mc(exp: Experiment) -> tuple[list[ConfigGroup], list[ConfigGroup]]:
    """mcrl's finished SAC (mc_alpha 0) and SAC-MC (mc_alpha > 0) configurations."""
    with_data = [g for g in _mcrl(exp) if g.finished and g.mc_alpha is not None]
    return [g for g in with_data if g.mc_alpha == 0.0], [g for g in with_data if g.mc_alpha > 0.0]


def _is_code_variant(g: ConfigGroup) -> bool:
    """Runs with the thesis' code's MC reward: one batch-mean KL for all transitions, the whole observation."""
    started = [r for r in g.runs if r.config]  # a run not started yet has no config.json to tell
    return bool(started) and all(r.config.get("mc_reduction") == "batch" and r.config.get("mc_state") == "full"
                                 for r in started)


def _comparisons(exp: Experiment) -> list[tuple[ConfigGroup, ConfigGroup]]:
    """(X, Y) pairs compared: each SAC-MC configuration with each SAC one, and mcrl's SAC with each
    finished reference arm."""
    sac, mc = _sac_and_mc(exp)
    peers = [g for g in exp.configs if g.peer and g.finished]
    return [(x, y) for x in mc for y in sac] + [(y, p) for y in sac for p in peers]


# ---------------------------------------------------------------------------------- sections


def _overview(exp: Experiment) -> list[Block]:
    n_done = sum(r.status == "finished" for r in exp.runs)
    envs = sorted({str(r.config["env_id"]) for r in exp.runs if "env_id" in r.config})
    budgets = sorted({r.total_steps for r in exp.runs if r.total_steps is not None})
    items = [
        f"preset: `{exp.preset or '?'}`; environment: {', '.join(f'`{e}`' for e in envs) or '?'}",
        f"training budget (total_steps): {', '.join(_steps(b) for b in budgets) or '?'}",
        f"runs finished: {n_done} of {len(exp.runs)}"
        + ("" if n_done == len(exp.runs) else " (see [Missing and unfinished runs](#missing-and-unfinished-runs))"),
        f"configurations: {', '.join(f'`{g.key}`' for g in exp.configs)}",
        f"confidence intervals: 95%, percentile bootstrap over seeds (seed {SEED}); IQM and probability of "
        f"improvement: stratified bootstrap via {bootstrap_backend()}",
        f"readings and verdicts need at least {MIN_SEEDS_FOR_VERDICT} finished seeds in every configuration "
        "compared (MIN_SEEDS_FOR_VERDICT); with fewer the report says 'too few seeds for a verdict'",
    ]
    peers = [g for g in exp.configs if g.peer]
    if peers:
        items.append("reference arms, not trained by mcrl (peer.json): "
                     + ", ".join(f"`{g.key}` ({g.peer})" for g in peers))
    if exp.extra_sources:
        items.append("runs added from: " + ", ".join(_code(str(p)) for p in exp.extra_sources))
    out: list[Block] = [("h", 1, f"mcrl report: {exp.dir.name}")]
    if exp.provenance:
        out += [("p", "**Provenance** (from provenance.json):"), ("ul", _provenance(exp.provenance))]
    for path, prov in exp.extra_provenance.items():
        out += [("p", f"**Provenance of {_code(path.name)}** (from {_code(str(path / 'provenance.json'))}):"),
                ("ul", _provenance(prov))]
    return out + [("ul", items)]


def _provenance(prov: dict[str, object]) -> list[str]:
    """provenance.json's items, the known keys first; "machines" (run -> machine) is what "machine" summarises."""
    known = {"commit": "code commit", "machine": "machine", "command": "command", "rerun_one_seed": "re-run one seed"}
    order = [k for k in known if k in prov] + sorted(k for k in prov if k not in known and k != "machines")
    return [f"{known.get(k, k)}: {_code(str(prov[k]))}" for k in order]


def _curves_by_config(series: Sequence[tuple[str, dict[str, np.ndarray]]], col: str) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(config key, CSV columns) per run -> (step grid, {config key: curves (n_runs, n_grid)})."""
    grid, curves = align_curves([(cols["step"], cols[col]) for _, cols in series])
    keys = [k for k, _ in series]
    return grid, {k: curves[[i for i, kk in enumerate(keys) if kk == k]] for k in dict.fromkeys(keys)}


def _colors(exp: Experiment) -> dict[str, str]:
    return {g.key: COLORS[i % len(COLORS)] for i, g in enumerate(exp.configs)}


def _learning_curves(exp: Experiment) -> list[Block]:
    fig, (ax_s, ax_r) = panel_grid(2)
    colors = _colors(exp)
    for ax, col, title, ylabel in ((ax_s, "success_rate", "eval success rate", "success rate"),
                                   (ax_r, "mean_return", "eval mean return", "return")):
        for peers, style in ((False, "-"), (True, "--")):  # reference arms dashed
            series = [(g.key, r.eval) for g in exp.configs if bool(g.peer) == peers
                      for r in g.runs if r.has_eval and has_data(r.eval, col)]
            if series or not peers:
                grid, by_cfg = _curves_by_config(series, col)
                plot_curves_with_band(ax, grid, by_cfg, title=title, ylabel=ylabel, colors=colors, seed=SEED,
                                      linestyle=style)
    partial = sum(r.status == "partial" and r.has_eval for r in exp.runs)
    return [
        ("h", 2, "Learning curves"),
        ("fig", "learning_curves.png", figure_to_png(fig),
         "Deterministic evaluation during training: mean over seeds, shaded 95% bootstrap band over seeds."
         + (" Dashed: reference arms (not trained by mcrl)." if any(g.peer for g in exp.configs) else "")
         + (f" {partial} unfinished run(s) are included up to their last evaluation." if partial else "")),
    ]


def _final_table(exp: Experiment) -> list[Block]:
    rows = []
    for g in exp.configs:
        s, m = g.finals()
        ms, cs = _mean_ci(s)
        mm, cm = _mean_ci(m)
        budgets = sorted({r.total_steps for r in g.finished if r.total_steps is not None})
        rows.append([_name(g), _f(g.mc_alpha, 2), f"{s.size} / {len(g.runs)}", ", ".join(map(_steps, budgets)) or "?",
                     f"{_f(ms, 3)} {_ci(cs, 3)}", _f(_var(s), 4), f"{_f(mm, 2)} {_ci(cm, 2)}", _source(g.finished)])
    return [
        ("h", 2, "Final performance per configuration"),
        ("p", "Final evaluation of each finished run across seeds: mean with 95% bootstrap CI, and sample variance "
              "(ddof=1) of the success rate, as in the thesis' tables. A run's final numbers come from its "
              "final_eval.json (the evaluation at the end of training, with final_eval_episodes episodes) when it "
              "has one, else from the last row of its eval.csv; the last column says which, and over how many "
              "episodes."),
        ("table", ["configuration", "mc_alpha", "seeds finished", "total_steps", "mean success [95% CI]",
                   "variance of success", "mean final return [95% CI]", "final numbers from"], rows),
    ]


def _per_seed_table(exp: Experiment) -> list[Block]:
    rows = []
    for g in exp.configs:
        for r in g.runs:
            fin, src = r.final, r.final_source
            status = {"missing": "missing", "partial": "unfinished"}.get(r.status, "no evaluation")
            rows.append([_name(g), "?" if r.seed is None else str(r.seed), f"`{r.name}`",
                         _f(fin[0], 3) if fin else status, _f(fin[1], 2) if fin else "-",
                         f"{'final_eval.json' if src[0] == 'final_eval.json' else 'last eval.csv row'}, "
                         f"{'?' if src[1] is None else src[1]} episodes" if src else "-"])
    return [
        ("h", 2, "Final performance per seed"),
        ("p", "The final evaluation of every run, by configuration and seed."),
        ("table", ["configuration", "seed", "run", "final success", "final return", "from"], rows),
    ]


def _reading(p: Interval, nx: int, ny: int, y: str) -> str:
    few = too_few(nx, ny)
    if few:
        return few
    if p[1] > 0.5:
        return f"better than {y} (CI above 0.5)"
    if p[2] < 0.5:
        return f"worse than {y} (CI below 0.5)"
    return "no clear difference (CI contains 0.5)"


def _robust_stats(exp: Experiment) -> list[Block]:
    out: list[Block] = [("h", 2, "IQM and probability of improvement")]
    groups = [g for g in exp.configs if g.finished]
    succ = stratified_iqm_ci({g.key: g.finals()[0] for g in groups}, conf=CONF, seed=SEED)
    ret = stratified_iqm_ci({g.key: g.finals()[1] for g in groups}, conf=CONF, seed=SEED)
    out += [
        ("p", "Interquartile mean (25% trimmed mean) of the final evaluation over finished seeds, with "
              "stratified-bootstrap 95% CIs (rliable's method; the overview names the implementation that ran). "
              "With fewer than 4 seeds the IQM is the plain mean."),
        ("table", ["configuration", "seeds", "IQM success [95% CI]", "IQM final return [95% CI]"],
         [[_name(g), str(len(g.finished)), f"{_f(succ[g.key][0], 3)} {_ci(succ[g.key][1:], 3)}",
           f"{_f(ret[g.key][0], 2)} {_ci(ret[g.key][1:], 2)}"] for g in groups]),
    ]
    sac, mc = _sac_and_mc(exp)
    if not sac or not mc:
        missing = "no finished SAC configuration (mc_alpha = 0)" if not sac else "no finished SAC-MC configuration (mc_alpha > 0)"
        out.append(("p", f"Probability of improvement of SAC-MC over SAC: not computed, the sweep has {missing}."))
    pairs = _comparisons(exp)
    if not pairs:
        return out
    rows = []
    for x, y in pairs:
        (sx, mx), (sy, my) = x.finals(), y.finals()
        ps = probability_of_improvement(sx, sy, conf=CONF, seed=SEED)
        pm = probability_of_improvement(mx, my, conf=CONF, seed=SEED)
        yname = f"`{y.key}`" if y.peer else "SAC"
        rows.append([f"`{x.key}` > `{y.key}`", f"{sx.size} / {sy.size}", f"{_f(ps[0], 3)} {_ci(ps[1:], 3)}",
                     _reading(ps, sx.size, sy.size, yname), f"{_f(pm[0], 3)} {_ci(pm[1:], 3)}",
                     _reading(pm, mx.size, my.size, yname)])
    return out + [
        ("p", "Probability of improvement P(X > Y): the chance that a random finished seed of configuration X "
              "ends above a random seed of configuration Y (ties count half; 0.5 = no difference), with "
              "stratified-bootstrap 95% CIs (rliable's method; the overview names the implementation that ran). "
              "X is each SAC-MC configuration against mcrl's SAC, and mcrl's SAC against each reference arm."),
        ("table", ["comparison", "seeds X / Y", "P(X > Y), success [95% CI]", "reading (success)",
                   "P(X > Y), final return [95% CI]", "reading (return)"], rows),
    ]


def _detectable(exp: Experiment) -> list[Block]:
    """How large a difference in mean final success these seeds can detect, per comparison."""
    out: list[Block] = [("h", 2, "How large a difference can these seeds detect")]
    pairs = _comparisons(exp)
    if not pairs:
        return out + [("p", "Not computed: no finished SAC configuration (mc_alpha = 0) and another finished "
                            "configuration to compare it with.")]
    rows = []
    for x, y in pairs:
        sx, sy = x.finals()[0], y.finals()[0]
        sx, sy = sx[np.isfinite(sx)], sy[np.isfinite(sy)]
        few = too_few(sx.size, sy.size)
        diff = float(sx.mean() - sy.mean()) if sx.size and sy.size else math.nan
        mde = minimum_detectable_difference(sx, sy, ALPHA, POWER)
        need = seeds_to_detect(sx, sy, diff, ALPHA, POWER)
        rows.append([f"`{x.key}` vs `{y.key}`", f"{sx.size} / {sy.size}",
                     f"{_f(math.sqrt(_var(sx)), 3)} / {_f(math.sqrt(_var(sy)), 3)}", _f(diff, 3),
                     few or _f(mde, 3), few or ("n/a" if need is None else str(need))])
    return out + [
        ("p", f"The minimum detectable difference (MDE) is the smallest true difference in mean final success "
              f"that a two-sided two-sample test at alpha = {ALPHA} finds with probability {POWER}, given the "
              "seed counts and the standard deviations of final success observed here (Welch/normal "
              "approximation: MDE = (z_0.975 + z_0.8) * sqrt(s_X^2/n_X + s_Y^2/n_Y)). A true difference smaller "
              "than the MDE is likely to go unnoticed with these seeds. The last column is the number of seeds "
              "per configuration at which the MDE would shrink to the observed difference (same spread assumed)."),
        ("table", ["comparison", "seeds X / Y", "sd of final success X / Y", "observed difference X - Y",
                   "minimum detectable difference", "seeds each to detect the observed difference"], rows),
    ]


def _verdict(what: str, thesis: float, ours: float, ci: tuple[float, float] | None, n: int, digits: int) -> str:
    few = too_few(n)
    if few or ci is None:
        return f"{what}: {few or 'no confidence interval'} (thesis {thesis:.{digits}f}, ours {_f(ours, digits)})."
    where = ("inside" if ci[0] <= thesis <= ci[1] else "above" if thesis > ci[1] else "below")
    text = f"{what}: the thesis' {thesis:.{digits}f} lies {where} our 95% CI {_ci(ci, digits)} (our mean {ours:.{digits}f})"
    if where == "inside":
        return text + ": consistent with the thesis."
    return text + (": our runs do worse than the thesis reports." if where == "above"
                   else ": our runs do better than the thesis reports.")


def _thesis_comparison(exp: Experiment) -> list[Block]:
    name = thesis_experiment(exp.preset)
    if name is None:
        return []
    t = THESIS_RESULTS[name]
    out: list[Block] = [("h", 2, f"Comparison with the thesis ({name})")]
    ours_all = _mcrl(exp)
    budgets = sorted({r.total_steps for g in ours_all for r in g.runs if r.total_steps is not None})
    notes = []
    if budgets != [t["total_steps"]]:
        notes.append(f"**Not like-for-like:** our runs trained for {', '.join(map(_steps, budgets)) or 'an unknown number of'} "
                     f"env steps, the thesis' for {_steps(t['total_steps'])}; final numbers after a different "
                     "budget are not expected to match.")
    notes.append(f"The thesis used {t['seeds']} seeds per configuration ({t['tables']}); it does not say how its "
                 "'variance of success rate' was computed, ours is the sample variance of the final success rate "
                 "across seeds. Its 'mean reward' is compared with our mean final evaluation return.")
    notes.append(t["caveat"])
    if min((len(g.finished) for g in ours_all if g.finished), default=0) < 5:
        notes.append("With fewer than 5 seeds a percentile-bootstrap CI is too narrow (it covers the true mean "
                     "less than 95% of the time), so an 'outside our CI' verdict is weaker than it reads.")
    rows, verdicts = [], []
    for alpha, th in t["by_alpha"].items():
        label = "SAC" if alpha == 0 else f"SAC-MC alpha={alpha:g}"
        # mcrl's configurations, then reference arms trained at the same mc_alpha
        ours = [g for g in [*ours_all, *(g for g in exp.configs if g.peer)]
                if g.mc_alpha is not None and math.isclose(g.mc_alpha, alpha)]
        if not ours:
            rows.append([label, f"{th['success_mean']:.2f}", "not in this sweep", f"{th['success_var']:.2f}", "",
                         f"{th['mean_reward']:.1f}", "not in this sweep"])
            continue
        for g in ours:
            s, m = g.finals()
            ms, cs = _mean_ci(s)
            mm, cm = _mean_ci(m)
            row_label = f"{label}, reference" if g.peer else label
            row_label += ", the thesis' code's variant" if alpha > 0 and _is_code_variant(g) else ""
            rows.append([f"{row_label} (`{g.key}`)", f"{th['success_mean']:.2f}", f"{_f(ms, 3)} {_ci(cs, 3)}",
                         f"{th['success_var']:.2f}", _f(_var(s), 4), f"{th['mean_reward']:.1f}",
                         f"{_f(mm, 2)} {_ci(cm, 2)}"])
            verdicts.append(_verdict(f"{row_label} (`{g.key}`) success rate", th["success_mean"], ms, cs, s.size, 2))
            verdicts.append(_verdict(f"{row_label} (`{g.key}`) mean return", th["mean_reward"], mm, cm, m.size, 1))
    verdicts += _claims(exp, t["by_alpha"])
    return out + [
        ("table", ["algorithm", "thesis success", "ours success [95% CI]", "thesis variance", "our variance",
                   "thesis mean reward", "our mean final return [95% CI]"], rows),
        ("ul", verdicts or ["No configuration of this sweep has the thesis' mc_alpha (0 or 0.2) with finished runs."]),
        ("p", "**Caveats:**"),
        ("ul", notes),
    ]


CODE_VARIANT = "the thesis' code's variant of SAC-MC alpha=0.2 (one batch-mean KL, the whole observation)"


def _claims(exp: Experiment, by_alpha: dict[float, dict[str, float]]) -> list[str]:
    """A verdict on each claim "SAC-MC alpha=0.2 beats SAC", for the algorithm as the thesis' text describes it
    and for its code's variant; a claim without finished runs on both sides is not decidable, and says so."""
    if 0.2 not in by_alpha or 0 not in by_alpha:
        return []
    claimed = by_alpha[0.2]["success_mean"] - by_alpha[0]["success_mean"]
    sac, mc = _sac_and_mc(exp)
    out = []
    for what, is_variant in (("SAC-MC alpha=0.2", False), (CODE_VARIANT, True)):
        claim = f"the thesis' claim that {what} reaches a higher final success rate than SAC (thesis: {claimed:+.2f})"
        xs = [g for g in mc if math.isclose(g.mc_alpha or 0.0, 0.2) and _is_code_variant(g) == is_variant]
        if not xs or not sac:
            side = "SAC (mc_alpha = 0)" if not sac else what
            hint = " (add its experiment with `--with DIR`)" if sac and is_variant else ""
            out.append(f"**{NOT_DECIDABLE.capitalize()}**: {claim}: this report has no finished run of {side}, "
                       f"0 seeds{hint}.")
        for x in xs:
            for y in sac:
                verdict, why = claim_verdict(x.finals()[0], y.finals()[0], claimed, MIN_SEEDS_FOR_VERDICT, conf=CONF,
                                             seed=SEED)
                out.append(f"**{verdict.capitalize()}**: {claim}, X = `{x.key}`, Y = `{y.key}`: {why}.")
    return out


def _mc_section(exp: Experiment) -> list[Block]:
    out: list[Block] = [("h", 2, "MC reward and raw KL during training")]
    groups = [g for g in exp.configs if any(has_data(r.metrics, "mean_mc_reward") for r in g.runs)]
    if not groups:
        return out + [("p", "No run has MC reward data (metrics.csv `mean_mc_reward` is empty: no MC models).")]
    colors = _colors(exp)
    fig, axes = panel_grid(2)
    cols = ("mean_mc_reward", "mean_raw_kl")
    for ax, col, title, ylabel in zip(axes, cols, ("mean MC reward (normalised)", "mean raw KL"), ("reward", "nats")):
        series = [(g.key, r.metrics) for g in groups for r in g.runs if has_data(r.metrics, col)]
        grid, by_cfg = _curves_by_config(series, col)
        plot_curves_with_band(ax, grid, by_cfg, title=title, ylabel=ylabel, colors=colors, seed=SEED)

    def last_mean(g: ConfigGroup, col: str) -> float | None:
        """Mean over seeds of each run's last logged value of ``col``."""
        v = [r.metrics[col][np.isfinite(r.metrics[col])][-1] for r in g.runs if has_data(r.metrics, col)]
        return float(np.mean(v)) if v else None

    rows = [[_name(g), _f(g.mc_alpha, 2), *(_f(last_mean(g, c), 4) for c in cols)] for g in groups]
    return out + [
        ("p", "The MC reward added to the replay batches and the raw per-transition KL (nats) it is normalised "
              "from, per configuration (mean over seeds, 95% bootstrap band), like the thesis' Fig. 4.7. As the "
              "thesis notes, the MC reward is relative (normalised by percentiles of past KL values): compare "
              "its course over training, not its level, across tasks."),
        ("fig", "mc_reward_kl.png", figure_to_png(fig), "MC reward and raw KL from metrics.csv."),
        ("table", ["configuration", "mc_alpha", "last mean MC reward (mean over seeds)", "last mean raw KL (nats)"], rows),
    ]


def _missing_section(exp: Experiment) -> list[Block]:
    out: list[Block] = [("h", 2, "Missing and unfinished runs")]
    bad = [(g, r) for g in exp.configs for r in g.runs if r.status != "finished" or r.final is None]
    if not bad:
        return out + [("p", f"None: all {len(exp.runs)} runs finished.")]
    rows = []
    for g, r in sorted(bad, key=lambda gr: exp.runs.index(gr[1])):
        status = {"missing": "missing (no run directory)", "partial": "unfinished (no `done` file)",
                  "finished": "finished, but eval.csv has no rows"}[r.status]
        rows.append([f"`{r.name}`", f"`{g.key}`", str(r.seed), status,
                     f"{_steps(r.last_step) if r.last_step is not None else '-'} / {_steps(r.total_steps or g.total_steps)}"])
    return out + [
        ("p", f"{len(bad)} of {len(exp.runs)} runs are left out of the final-performance statistics "
              "(unfinished runs still appear in the learning curves up to their last evaluation). Re-run or "
              "resume them, then write the report again."),
        ("table", ["run", "configuration", "seed", "status", "last logged step / total_steps"], rows),
    ]


def build_report(exp: Experiment) -> list[Block]:
    """Every section of the report, in order."""
    return (_overview(exp) + _learning_curves(exp) + _final_table(exp) + _per_seed_table(exp)
            + _robust_stats(exp) + _detectable(exp) + _thesis_comparison(exp) + _mc_section(exp)
            + _missing_section(exp))
