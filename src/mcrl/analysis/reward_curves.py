"""The report's section on the intrinsic rewards during training: each arm's normalised reward and its reward's raw
value, from metrics.csv, named as the reward's `About` names them (`mcrl.algo.intrinsic.about`: its title, its raw
value's column and label), so a reward registered outside mcrl shows like the built-in ones.

Where the thesis' reward (`THESIS_REWARD`) is among the arms, or no arm names a reward, the section keeps the words
of the thesis' Fig. 4.7 it reproduces (MC reward and raw KL), so committed reports regenerate byte for byte.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mcrl.algo.intrinsic import THESIS_REWARD, About, about
from mcrl.analysis.cells import SEED, name, num
from mcrl.analysis.experiment import ConfigGroup, Experiment
from mcrl.analysis.markdown import Block, Figure, Heading, Paragraph, Table
from mcrl.analysis.plots import arm_colors, curves_by_config, figure_to_png, has_data, panel_grid, plot_curves_with_band
from mcrl.analysis.stats import MIN_SEEDS_FOR_VERDICT

NORMALISED = "mean_intrinsic_reward"  # every reward's normalised reward: one column, one panel


@dataclass(frozen=True)
class _Words:
    heading: str
    empty: str  # the section's text when no run has data
    text: str
    png: str
    caption: str
    normalised: str  # the normalised reward's panel
    raw_column: str  # the table's column of each arm's raw value


# the words of the thesis' Fig. 4.7: its reward, MC, and the raw KL it is normalised from
_THESIS = _Words(
    "MC reward and raw KL during training",
    "No run has MC reward data (metrics.csv `mean_intrinsic_reward` is empty: no MC models).",
    "The MC reward added to the replay batches and the raw per-transition KL (nats) it is normalised "
    f"from, per configuration (mean over seeds, 95% bootstrap band where >= {MIN_SEEDS_FOR_VERDICT} seeds have "
    "the point), like the thesis' Fig. 4.7. As the "
    "thesis notes, the MC reward is relative (normalised by percentiles of past KL values): compare "
    "its course over training, not its level, across tasks. An arm with another intrinsic reward "
    "(RND, ICM, Disagreement) logs its normalised reward in the same column and its own raw value "
    "(docs/intrinsic.md): prediction error or ensemble variance, not a KL.",
    "mc_reward_kl.png", "MC reward and raw KL from metrics.csv.", "mean MC reward (normalised)",
    "last mean raw KL (nats) or raw intrinsic value")


def _any(rewards: list[About]) -> _Words:
    """The words for arms of other rewards, each named by its `About`."""
    each = "; ".join(f"{a.title}: {a.raw_label} (`{a.raw_metric}`)" for a in rewards)
    return _Words(
        "Intrinsic reward and raw value during training",
        "No run has intrinsic reward data (metrics.csv `mean_intrinsic_reward` is empty: no intrinsic models).",
        "The normalised intrinsic reward added to the replay batches (`mean_intrinsic_reward`) and the raw value it "
        f"is normalised from, per configuration (mean over seeds, 95% bootstrap band where >= {MIN_SEEDS_FOR_VERDICT} "
        f"seeds have the point): {each}. The normalised reward is relative (percentiles of the run's past raw "
        "values): compare its course over training, not its level.",
        "intrinsic_reward.png", "Intrinsic reward and raw value from metrics.csv.",
        "mean intrinsic reward (normalised)", "last mean raw value")


def _last_mean(g: ConfigGroup, col: str) -> float | None:
    """Mean over seeds of each run's last logged value of ``col``."""
    v = [r.metrics[col][np.isfinite(r.metrics[col])][-1] for r in g.runs if has_data(r.metrics, col)]
    return float(np.mean(v)) if v else None


def reward_section(exp: Experiment) -> list[Block]:
    """The normalised reward of every arm with intrinsic models on one panel, each reward's raw value on its own
    (its unit), and each arm's last values."""
    groups = [g for g in exp.configs if any(has_data(r.metrics, NORMALISED) for r in g.runs)]
    named = [g.intrinsic for g in groups] or [g.intrinsic for g in exp.configs if (g.intrinsic_alpha or 0.0) > 0.0]
    order = sorted(dict.fromkeys(named), key=lambda n: n != THESIS_REWARD)  # the thesis' reward first
    words = _THESIS if THESIS_REWARD in order or not order else _any([about(n) for n in order])
    out: list[Block] = [Heading(2, words.heading)]
    if not groups:
        return out + [Paragraph(words.empty)]
    colors = arm_colors([g.key for g in exp.configs])
    # the thesis' words name MC's reward; the panel names the reward it holds (MC's alone, or every arm's)
    normalised = words.normalised if len(order) == 1 else "mean intrinsic reward (normalised)"
    panels = [(NORMALISED, normalised, "reward", groups)] + [
        (a.raw_metric, f"{a.title}: mean {a.raw_label}", "raw value", [g for g in groups if g.intrinsic == n])
        for n, a in ((n, about(n)) for n in order)]
    fig, axes = panel_grid(len(panels))
    for ax, (col, title, ylabel, arms) in zip(axes, panels):
        series = [(g.key, r.metrics) for g in arms for r in g.runs if has_data(r.metrics, col)]
        grid, by_cfg = curves_by_config(series, col)
        plot_curves_with_band(ax, grid, by_cfg, title=title, ylabel=ylabel, colors=colors, seed=SEED)
    rows = [[name(g), num(g.intrinsic_alpha, 2), g.intrinsic, num(_last_mean(g, NORMALISED), 4),
             num(_last_mean(g, about(g.intrinsic).raw_metric), 4)] for g in groups]
    return out + [
        Paragraph(words.text),
        Figure(words.png, figure_to_png(fig), words.caption),
        Table(["configuration", "intrinsic_alpha", "intrinsic", "last mean intrinsic reward (mean over seeds)",
               words.raw_column], rows),
    ]
