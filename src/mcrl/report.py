"""``mcrl report``: one self-contained report of an experiment (a sweep of runs over seeds).

Reads ``EXP/sweep.json`` and ``EXP/runs/<name>/`` (see docs/run-directory.md) and writes
Markdown with PNG figures beside it, or one HTML file with the PNGs embedded. Works on a partial
sweep: statistics of final values use finished runs only, learning curves use every run that has
data, and a section lists the runs that are missing or unfinished.
"""

from __future__ import annotations

import base64
import html
import json
import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from mcrl.errors import MCRLError
from mcrl.plots import COLORS, figure_to_png, has_data, panel_grid, plot_curves_with_band, read_csv
from mcrl.stats import (
    Interval,
    align_curves,
    bootstrap_backend,
    bootstrap_ci,
    probability_of_improvement,
    stratified_iqm_ci,
)

# Thesis chapter 4 (Tables 4.2-4.5; /work/shared/FACTS.md). "variance" is the thesis' "Variance of
# Success Rate" (its definition is not stated there); "mean_reward" its "Mean Reward", which in
# range matches a mean evaluation-episode return (FetchPush: 50 steps of -1/0).
THESIS_RESULTS: dict[str, dict[str, Any]] = {
    "FetchPush": {
        "tables": "Tables 4.2 and 4.3",
        "total_steps": 150_000,
        "seeds": 6,
        "by_alpha": {
            0.0: {"success_mean": 0.52, "success_var": 0.2, "mean_reward": -31.3},
            0.2: {"success_mean": 0.75, "success_var": 0.2, "mean_reward": -23.0},
        },
        "caveat": "The thesis also reports alpha 0.4 and 0.6 about equal to SAC and 0.8, 1.0 worse, "
                  "without table values.",
    },
    "AntMaze": {
        "tables": "Tables 4.4 and 4.5",
        "total_steps": 400_000,
        "seeds": 4,
        "by_alpha": {
            0.0: {"success_mean": 0.38, "success_var": 0.14, "mean_reward": 155.3},
            0.2: {"success_mean": 0.52, "success_var": 0.16, "mean_reward": 206.5},
        },
        "caveat": "The thesis ran its own AntGym maze (action scale 0.4, map not recoverable from the "
                  "text); mcrl's dense UMaze is a public stand-in, so the task itself differs.",
    },
}
# Preset name prefix (lower case) -> THESIS_RESULTS key.
THESIS_PRESET_PREFIXES: dict[str, str] = {"fetchpush": "FetchPush", "antmaze": "AntMaze"}

CONF = 0.95
SEED = 0  # every bootstrap in a report uses it: the same runs give the same report


# ------------------------------------------------------------------------------------ loading


@dataclass
class Run:
    """One run of the sweep and what it has written so far."""

    name: str
    config_key: str
    seed: int | None
    dir: Path
    status: Literal["finished", "partial", "missing"]
    config: dict[str, Any] = field(default_factory=dict)
    overrides: dict[str, Any] = field(default_factory=dict)
    eval: dict[str, np.ndarray] = field(default_factory=dict)
    metrics: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def has_eval(self) -> bool:
        return has_data(self.eval, "step") and has_data(self.eval, "success_rate")

    @property
    def final(self) -> tuple[float, float] | None:
        """(success rate, mean return) of the final evaluation, for finished runs only."""
        if self.status != "finished" or not self.has_eval:
            return None
        ret = self.eval.get("mean_return", np.array([math.nan]))
        return float(self.eval["success_rate"][-1]), float(ret[-1])

    @property
    def last_step(self) -> float | None:
        steps = [c["step"][np.isfinite(c["step"])] for c in (self.eval, self.metrics) if "step" in c]
        steps = [s for s in steps if s.size]
        return float(max(s.max() for s in steps)) if steps else None

    @property
    def total_steps(self) -> int | None:
        v = self.config.get("total_steps", self.overrides.get("total_steps"))
        return int(v) if v is not None else None


@dataclass
class ConfigGroup:
    """The runs of one configuration (same config_key, different seeds)."""

    key: str
    runs: list[Run]

    @property
    def mc_alpha(self) -> float | None:
        for r in self.runs:
            for src in (r.config, r.overrides):
                if src.get("mc_alpha") is not None:
                    return float(src["mc_alpha"])
        return None

    @property
    def total_steps(self) -> int | None:
        """The budget its runs were configured with (the first one known)."""
        return next((r.total_steps for r in self.runs if r.total_steps is not None), None)

    @property
    def finished(self) -> list[Run]:
        return [r for r in self.runs if r.final is not None]

    def finals(self) -> tuple[np.ndarray, np.ndarray]:
        """Final eval success rates and returns of the finished runs, in seed order."""
        f = [r.final for r in self.finished]
        return np.array([s for s, _ in f], dtype=float), np.array([m for _, m in f], dtype=float)


@dataclass
class Experiment:
    dir: Path
    preset: str
    runs: list[Run]
    configs: list[ConfigGroup]


def _read_json(path: Path) -> dict[str, Any]:
    try:
        obj = json.loads(path.read_text())
    except OSError:
        return {}
    except ValueError as e:
        raise MCRLError(f"{path} is not valid JSON ({e}): fix or delete it and re-run that step") from e
    return obj if isinstance(obj, dict) else {}


def load_experiment(experiment_dir: str | Path) -> Experiment:
    """Read sweep.json and every run directory it lists; raise MCRLError when there is nothing to report."""
    d = Path(experiment_dir)
    if not d.is_dir():
        raise MCRLError(f"experiment directory {d} does not exist: pass the directory `mcrl sweep` wrote "
                        "(the one holding sweep.json)")
    if not (d / "sweep.json").is_file():
        raise MCRLError(f"{d} has no sweep.json: pass the experiment directory `mcrl sweep` wrote "
                        "(for a single run use `mcrl plot RUN_DIR`)")
    sweep = _read_json(d / "sweep.json")
    entries = sweep.get("runs") or []
    if not entries:
        raise MCRLError(f"{d / 'sweep.json'} lists no runs: re-create the experiment with `mcrl sweep`")

    runs = []
    for e in entries:
        name = str(e["name"])
        rd = d / "runs" / name
        status = "finished" if (rd / "done").exists() else ("partial" if rd.is_dir() else "missing")
        overrides = dict(e.get("overrides") or {})
        runs.append(Run(name=name, config_key=str(e.get("config_key") or name), seed=e.get("seed"), dir=rd,
                        status=status, config=_read_json(rd / "config.json"), overrides=overrides,
                        eval=read_csv(rd / "eval.csv"), metrics=read_csv(rd / "metrics.csv")))
    if not any(r.has_eval for r in runs):
        started = sum(r.status != "missing" for r in runs)
        raise MCRLError(f"no run in {d} has written an evaluation yet ({started} of {len(runs)} runs started): "
                        "wait for the first evaluation (eval.csv), then run `mcrl report` again")

    groups: dict[str, list[Run]] = {}
    for r in runs:
        groups.setdefault(r.config_key, []).append(r)
    configs = [ConfigGroup(k, sorted(v, key=lambda r: (r.seed is None, r.seed or 0))) for k, v in groups.items()]
    # SAC first, then increasing alpha: the order of the thesis' tables and figures.
    configs.sort(key=lambda g: (g.mc_alpha is None, g.mc_alpha or 0.0, g.key))
    preset = str(sweep.get("preset") or next((r.config["preset"] for r in runs if "preset" in r.config), ""))
    return Experiment(d, preset, runs, configs)


# ------------------------------------------------------------------------------- formatting


def _f(x: float | None, digits: int) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def _ci(iv: tuple[float, float] | None, digits: int) -> str:
    return "n/a" if iv is None else f"[{_f(iv[0], digits)}, {_f(iv[1], digits)}]"


def _steps(n: float | int | None) -> str:
    return "?" if n is None else f"{int(n):,}"


def _mean_ci(x: np.ndarray) -> tuple[float, tuple[float, float] | None]:
    """Mean and 95% percentile-bootstrap CI over seeds; no CI from fewer than 2 seeds."""
    if x.size == 0:
        return math.nan, None
    return float(x.mean()), (bootstrap_ci(x, np.mean, conf=CONF, rng=SEED) if x.size >= 2 else None)


def _var(x: np.ndarray) -> float:
    """Sample variance across seeds (ddof=1); NaN for fewer than 2 seeds."""
    return float(x.var(ddof=1)) if x.size >= 2 else math.nan


# Blocks the report is made of, rendered to Markdown or HTML:
# ("h", level, text) | ("p", text) | ("ul", [text]) | ("table", headers, rows) | ("fig", file, png, caption)
Block = tuple[Any, ...]


# ---------------------------------------------------------------------------------- sections


def _overview(exp: Experiment) -> list[Block]:
    n_done = sum(r.status == "finished" for r in exp.runs)
    envs = sorted({str(r.config["env_id"]) for r in exp.runs if "env_id" in r.config})
    budgets = sorted({r.total_steps for r in exp.runs if r.total_steps is not None})
    return [
        ("h", 1, f"mcrl report: {exp.dir.name}"),
        ("ul", [
            f"preset: `{exp.preset or '?'}`; environment: {', '.join(f'`{e}`' for e in envs) or '?'}",
            f"training budget (total_steps): {', '.join(_steps(b) for b in budgets) or '?'}",
            f"runs finished: {n_done} of {len(exp.runs)}"
            + ("" if n_done == len(exp.runs) else " (see [Missing and unfinished runs](#missing-and-unfinished-runs))"),
            f"configurations: {', '.join(f'`{g.key}`' for g in exp.configs)}",
            f"confidence intervals: 95%, percentile bootstrap over seeds (seed {SEED}); IQM and probability of "
            f"improvement: stratified bootstrap via {bootstrap_backend()}",
        ]),
    ]


def _curves_by_config(series: Sequence[tuple[str, dict[str, np.ndarray]]], col: str) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(config key, CSV columns) per run -> (step grid, {config key: curves (n_runs, n_grid)})."""
    grid, curves = align_curves([(cols["step"], cols[col]) for _, cols in series])
    keys = [k for k, _ in series]
    return grid, {k: curves[[i for i, kk in enumerate(keys) if kk == k]] for k in dict.fromkeys(keys)}


def _learning_curves(exp: Experiment) -> list[Block]:
    fig, (ax_s, ax_r) = panel_grid(2)
    colors = {g.key: COLORS[i % len(COLORS)] for i, g in enumerate(exp.configs)}
    for ax, col, title, ylabel in ((ax_s, "success_rate", "eval success rate", "success rate"),
                                   (ax_r, "mean_return", "eval mean return", "return")):
        series = [(g.key, r.eval) for g in exp.configs for r in g.runs if r.has_eval and has_data(r.eval, col)]
        grid, by_cfg = _curves_by_config(series, col)
        plot_curves_with_band(ax, grid, by_cfg, title=title, ylabel=ylabel, colors=colors, seed=SEED)
    partial = sum(r.status == "partial" and r.has_eval for r in exp.runs)
    return [
        ("h", 2, "Learning curves"),
        ("fig", "learning_curves.png", figure_to_png(fig),
         "Deterministic evaluation during training: mean over seeds, shaded 95% bootstrap band over seeds."
         + (f" {partial} unfinished run(s) are included up to their last evaluation." if partial else "")),
    ]


def _final_table(exp: Experiment) -> list[Block]:
    rows = []
    for g in exp.configs:
        s, m = g.finals()
        ms, cs = _mean_ci(s)
        mm, cm = _mean_ci(m)
        budgets = sorted({r.total_steps for r in g.finished if r.total_steps is not None})
        rows.append([f"`{g.key}`", _f(g.mc_alpha, 2), f"{s.size} / {len(g.runs)}", ", ".join(map(_steps, budgets)) or "?",
                     f"{_f(ms, 3)} {_ci(cs, 3)}", _f(_var(s), 4), f"{_f(mm, 2)} {_ci(cm, 2)}"])
    return [
        ("h", 2, "Final performance per configuration"),
        ("p", "Final evaluation of each finished run (the last row of its eval.csv), across seeds: mean with 95% "
              "bootstrap CI, and sample variance (ddof=1) of the success rate, as in the thesis' tables."),
        ("table", ["configuration", "mc_alpha", "seeds finished", "total_steps", "mean success [95% CI]",
                   "variance of success", "mean final return [95% CI]"], rows),
    ]


def _sac_and_mc(exp: Experiment) -> tuple[list[ConfigGroup], list[ConfigGroup]]:
    with_data = [g for g in exp.configs if g.finished and g.mc_alpha is not None]
    return [g for g in with_data if g.mc_alpha == 0.0], [g for g in with_data if g.mc_alpha > 0.0]


def _reading(p: Interval) -> str:
    if p[1] > 0.5:
        return "better than SAC (CI above 0.5)"
    if p[2] < 0.5:
        return "worse than SAC (CI below 0.5)"
    return "no clear difference (CI contains 0.5)"


def _robust_stats(exp: Experiment) -> list[Block]:
    out: list[Block] = [("h", 2, "IQM and probability of improvement")]
    groups = [g for g in exp.configs if g.finished]
    succ = stratified_iqm_ci({g.key: g.finals()[0] for g in groups}, conf=CONF, seed=SEED)
    ret = stratified_iqm_ci({g.key: g.finals()[1] for g in groups}, conf=CONF, seed=SEED)
    out += [
        ("p", "Interquartile mean (25% trimmed mean) of the final evaluation over finished seeds, with "
              "stratified-bootstrap 95% CIs (rliable's method; the overview names the implementation that ran). With fewer than 4 seeds the IQM is the plain mean."),
        ("table", ["configuration", "seeds", "IQM success [95% CI]", "IQM final return [95% CI]"],
         [[f"`{g.key}`", str(len(g.finished)), f"{_f(succ[g.key][0], 3)} {_ci(succ[g.key][1:], 3)}",
           f"{_f(ret[g.key][0], 2)} {_ci(ret[g.key][1:], 2)}"] for g in groups]),
    ]
    sac, mc = _sac_and_mc(exp)
    if not sac or not mc:
        missing = "no finished SAC configuration (mc_alpha = 0)" if not sac else "no finished SAC-MC configuration (mc_alpha > 0)"
        return out + [("p", f"Probability of improvement: not computed, the sweep has {missing}.")]
    rows = []
    for x in mc:
        for y in sac:
            (sx, mx), (sy, my) = x.finals(), y.finals()
            ps = probability_of_improvement(sx, sy, conf=CONF, seed=SEED)
            pm = probability_of_improvement(mx, my, conf=CONF, seed=SEED)
            rows.append([f"`{x.key}` > `{y.key}`", f"{sx.size} / {sy.size}", f"{_f(ps[0], 3)} {_ci(ps[1:], 3)}",
                         _reading(ps), f"{_f(pm[0], 3)} {_ci(pm[1:], 3)}", _reading(pm)])
    return out + [
        ("p", "Probability of improvement P(X > Y): the chance that a random finished seed of the SAC-MC "
              "configuration X ends above a random seed of the SAC configuration Y (ties count half; 0.5 = "
              "no difference), with stratified-bootstrap 95% CIs (rliable's method; the overview names the implementation that ran)."),
        ("table", ["comparison", "seeds X / Y", "P(X > Y), success [95% CI]", "reading (success)",
                   "P(X > Y), final return [95% CI]", "reading (return)"], rows),
    ]


def thesis_experiment(preset: str) -> str | None:
    """The THESIS_RESULTS key a preset reproduces, by name prefix; None if it matches none."""
    p = preset.lower()
    return next((v for k, v in THESIS_PRESET_PREFIXES.items() if p.startswith(k)), None)


def _verdict(what: str, thesis: float, ours: float, ci: tuple[float, float] | None, n: int, digits: int) -> str:
    if ci is None:
        return (f"{what}: {n} finished seed(s) give no confidence interval, so no verdict "
                f"(thesis {thesis:.{digits}f}, ours {_f(ours, digits)}).")
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
    budgets = sorted({r.total_steps for r in exp.runs if r.total_steps is not None})
    notes = []
    if budgets != [t["total_steps"]]:
        notes.append(f"**Not like-for-like:** our runs trained for {', '.join(map(_steps, budgets)) or 'an unknown number of'} "
                     f"env steps, the thesis' for {_steps(t['total_steps'])}; final numbers after a different "
                     "budget are not expected to match.")
    notes.append(f"The thesis used {t['seeds']} seeds per configuration ({t['tables']}); it does not say how its "
                 "'variance of success rate' was computed, ours is the sample variance of the final success rate "
                 "across seeds. Its 'mean reward' is compared with our mean final evaluation return.")
    notes.append(t["caveat"])
    if min((len(g.finished) for g in exp.configs if g.finished), default=0) < 5:
        notes.append("With fewer than 5 seeds a percentile-bootstrap CI is too narrow (it covers the true mean "
                     "less than 95% of the time), so an 'outside our CI' verdict is weaker than it reads.")
    rows, verdicts = [], []
    for alpha, th in t["by_alpha"].items():
        label = "SAC" if alpha == 0 else f"SAC-MC alpha={alpha:g}"
        ours = [g for g in exp.configs if g.mc_alpha is not None and math.isclose(g.mc_alpha, alpha)]
        if not ours:
            rows.append([label, f"{th['success_mean']:.2f}", "not in this sweep", f"{th['success_var']:.2f}", "",
                         f"{th['mean_reward']:.1f}", "not in this sweep"])
            continue
        for g in ours:
            s, m = g.finals()
            ms, cs = _mean_ci(s)
            mm, cm = _mean_ci(m)
            rows.append([f"{label} (`{g.key}`)", f"{th['success_mean']:.2f}", f"{_f(ms, 3)} {_ci(cs, 3)}",
                         f"{th['success_var']:.2f}", _f(_var(s), 4), f"{th['mean_reward']:.1f}",
                         f"{_f(mm, 2)} {_ci(cm, 2)}"])
            verdicts.append(_verdict(f"{label} (`{g.key}`) success rate", th["success_mean"], ms, cs, s.size, 2))
            verdicts.append(_verdict(f"{label} (`{g.key}`) mean return", th["mean_reward"], mm, cm, m.size, 1))
    sac, mc = _sac_and_mc(exp)
    for x in (g for g in mc if math.isclose(g.mc_alpha or 0.0, 0.2)):
        for y in sac:
            p = probability_of_improvement(x.finals()[0], y.finals()[0], conf=CONF, seed=SEED)
            claim = ("supported" if p[1] > 0.5 else "contradicted (SAC-MC does worse)" if p[2] < 0.5
                     else "not supported at 95% (the CI contains 0.5)")
            verdicts.append(f"The thesis' claim that SAC-MC alpha=0.2 reaches a higher success rate than SAC: "
                            f"P(`{x.key}` > `{y.key}`) = {_f(p[0], 3)} {_ci(p[1:], 3)}, so the claim is {claim} "
                            "by our runs.")
    return out + [
        ("table", ["algorithm", "thesis success", "ours success [95% CI]", "thesis variance", "our variance",
                   "thesis mean reward", "our mean final return [95% CI]"], rows),
        ("ul", verdicts or ["No configuration of this sweep has the thesis' mc_alpha (0 or 0.2) with finished runs."]),
        ("p", "**Caveats:**"),
        ("ul", notes),
    ]


def _mc_section(exp: Experiment) -> list[Block]:
    out: list[Block] = [("h", 2, "MC reward and raw KL during training")]
    groups = [g for g in exp.configs if any(has_data(r.metrics, "mean_mc_reward") for r in g.runs)]
    if not groups:
        return out + [("p", "No run has MC reward data (metrics.csv `mean_mc_reward` is empty: no MC models).")]
    colors = {g.key: COLORS[i % len(COLORS)] for i, g in enumerate(exp.configs)}
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

    rows = [[f"`{g.key}`", _f(g.mc_alpha, 2), *(_f(last_mean(g, c), 4) for c in cols)] for g in groups]
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
    bad = [r for r in exp.runs if r.status != "finished" or not r.has_eval]
    if not bad:
        return out + [("p", f"None: all {len(exp.runs)} runs finished.")]
    budget = {r.name: g.total_steps for g in exp.configs for r in g.runs}
    rows = []
    for r in bad:
        status = {"missing": "missing (no run directory)", "partial": "unfinished (no `done` file)",
                  "finished": "finished, but eval.csv has no rows"}[r.status]
        rows.append([f"`{r.name}`", f"`{r.config_key}`", str(r.seed), status,
                     f"{_steps(r.last_step) if r.last_step is not None else '-'} / {_steps(r.total_steps or budget[r.name])}"])
    return out + [
        ("p", f"{len(bad)} of {len(exp.runs)} runs are left out of the final-performance statistics "
              "(unfinished runs still appear in the learning curves up to their last evaluation). Re-run or "
              "resume them, then write the report again."),
        ("table", ["run", "configuration", "seed", "status", "last logged step / total_steps"], rows),
    ]


# --------------------------------------------------------------------------------- rendering


def _md_cell(s: str) -> str:
    return s.replace("|", "\\|").replace("\n", " ")


def _to_markdown(blocks: Sequence[Block], out_dir: Path) -> str:
    parts = []
    for b in blocks:
        if b[0] == "h":
            parts.append(f"{'#' * b[1]} {b[2]}")
        elif b[0] == "p":
            parts.append(b[1])
        elif b[0] == "ul":
            parts.append("\n".join(f"- {item}" for item in b[1]))
        elif b[0] == "table":
            head, rows = b[1], b[2]
            lines = ["| " + " | ".join(map(_md_cell, head)) + " |", "|" + "---|" * len(head)]
            lines += ["| " + " | ".join(map(_md_cell, row)) + " |" for row in rows]
            parts.append("\n".join(lines))
        elif b[0] == "fig":
            (out_dir / b[1]).write_bytes(b[2])
            parts.append(f"![{b[3]}]({b[1]})\n\n*{b[3]}*")
    return "\n\n".join(parts) + "\n"


def _inline_html(s: str) -> str:
    """Escape, then the little Markdown the report uses: `code`, **bold**, [text](#anchor)."""
    s = html.escape(s, quote=False)
    s = re.sub(r"`([^`]+)`", r"<code>\1</code>", s)
    s = re.sub(r"\*\*([^*]+)\*\*", r"<strong>\1</strong>", s)
    return re.sub(r"\[([^\]]+)\]\((#[^)]+)\)", r'<a href="\2">\1</a>', s)


def _slug(text: str) -> str:
    return re.sub(r"[^a-z0-9 -]", "", text.lower()).strip().replace(" ", "-")


_CSS = ("body{font-family:sans-serif;max-width:70em;margin:2em auto;padding:0 1em;line-height:1.4}"
        "table{border-collapse:collapse;margin:1em 0}th,td{border:1px solid #ccc;padding:.3em .6em;text-align:left}"
        "th{background:#f3f3f3}img{max-width:100%}code{background:#f3f3f3;padding:0 .2em}figcaption{font-style:italic}")


def _to_html(blocks: Sequence[Block], title: str) -> str:
    parts = [f"<!DOCTYPE html>\n<html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
             f"<style>{_CSS}</style></head><body>"]
    for b in blocks:
        if b[0] == "h":
            parts.append(f"<h{b[1]} id='{_slug(b[2])}'>{_inline_html(b[2])}</h{b[1]}>")
        elif b[0] == "p":
            parts.append(f"<p>{_inline_html(b[1])}</p>")
        elif b[0] == "ul":
            parts.append("<ul>" + "".join(f"<li>{_inline_html(i)}</li>" for i in b[1]) + "</ul>")
        elif b[0] == "table":
            head = "".join(f"<th>{_inline_html(h)}</th>" for h in b[1])
            body = "".join("<tr>" + "".join(f"<td>{_inline_html(c)}</td>" for c in row) + "</tr>" for row in b[2])
            parts.append(f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>")
        elif b[0] == "fig":
            data = base64.b64encode(b[2]).decode("ascii")
            parts.append(f"<figure><img alt='{html.escape(b[3])}' src='data:image/png;base64,{data}'>"
                         f"<figcaption>{_inline_html(b[3])}</figcaption></figure>")
    return "\n".join(parts) + "\n</body></html>\n"


def write_report(experiment_dir: str | Path, out_dir: str | Path | None = None,
                 fmt: Literal["md", "html"] = "md") -> Path:
    """Write the report of an experiment directory; returns the report file's path.

    ``fmt="md"``: ``OUT/report.md`` with its PNG figures beside it; ``fmt="html"``: one
    self-contained ``OUT/report.html`` (figures embedded). ``out_dir`` defaults to ``EXP/report``.
    Raises MCRLError when the directory does not exist, has no sweep.json, lists no runs, or no
    run has evaluated yet.
    """
    if fmt not in ("md", "html"):
        raise MCRLError(f"unknown report format {fmt!r}: use --format md or --format html")
    exp = load_experiment(experiment_dir)
    out = Path(out_dir) if out_dir is not None else exp.dir / "report"
    out.mkdir(parents=True, exist_ok=True)
    blocks = (_overview(exp) + _learning_curves(exp) + _final_table(exp) + _robust_stats(exp)
              + _thesis_comparison(exp) + _mc_section(exp) + _missing_section(exp))
    if fmt == "md":
        path = out / "report.md"
        path.write_text(_to_markdown(blocks, out))
    else:
        path = out / "report.html"
        path.write_text(_to_html(blocks, f"mcrl report: {exp.dir.name}"))
    return path
