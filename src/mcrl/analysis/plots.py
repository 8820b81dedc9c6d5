"""Learning-curve figures: one run (``mcrl plot``) and the shared drawing code the report uses.

Figures are built with ``matplotlib.figure.Figure`` directly (no pyplot), which renders through
Agg, needs no display and leaves matplotlib's global backend alone.
"""

from __future__ import annotations

import io
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter, MaxNLocator

from mcrl.algo.intrinsic import THESIS_REWARD, About, about
from mcrl.analysis.stats import DEFAULT_N_BOOT, MIN_SEEDS_FOR_VERDICT, align_curves, mean_ci_band
from mcrl.errors import MCRLError
from mcrl.renames import new_names
from mcrl.run.rundir import CONFIG, EVAL, METRICS, is_done, read_columns, read_json

COLORS = [f"C{i}" for i in range(10)]


def arm_colors(keys: Sequence[str]) -> dict[str, str]:
    """Each arm's colour, by its place among the report's arms: the same in every figure of a report."""
    return {k: COLORS[i % len(COLORS)] for i, k in enumerate(keys)}


def curves_by_config(series: Sequence[tuple[str, Mapping[str, np.ndarray]]],
                     col: str) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """(config key, CSV columns) per run -> (step grid, {config key: curves (n_runs, n_grid)})."""
    grid, curves = align_curves([(cols["step"], cols[col]) for _, cols in series])
    keys = [k for k, _ in series]
    return grid, {k: curves[[i for i, kk in enumerate(keys) if kk == k]] for k in dict.fromkeys(keys)}


def has_data(cols: Mapping[str, np.ndarray], name: str) -> bool:
    """Whether column ``name`` exists and holds at least one finite value."""
    return name in cols and bool(np.isfinite(cols[name]).any())


def steps_in_thousands(ax: Axes) -> None:
    """Label an env-steps x axis in thousands ('50k'), at most 6 ticks: full numbers run together on a panel
    ("100000120000140000")."""
    ax.xaxis.set_major_locator(MaxNLocator(nbins=6, steps=[1, 2, 2.5, 5, 10]))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: "0" if v == 0 else f"{v / 1000:g}k"))


def plot_curves_with_band(
    ax: Axes,
    steps: Any,
    curves_by_config: Mapping[str, Any],
    *,
    title: str = "",
    ylabel: str = "",
    xlabel: str = "env steps",
    colors: Mapping[str, str] | None = None,
    logy: bool = False,
    n_boot: int = DEFAULT_N_BOOT,
    seed: int = 0,
    linestyle: str = "-",
) -> None:
    """Draw, per configuration, the mean curve over seeds and its 95% bootstrap band.

    ``curves_by_config`` maps a label to curves (n_seeds, n_points) (a 1-D curve is one seed)
    sampled at ``steps`` (env steps, labelled in thousands); NaN marks points a seed lacks. The
    band is shaded only where at least ``MIN_SEEDS_FOR_VERDICT`` seeds have the point (a bootstrap
    over two seeds is just their range); where fewer do, the seeds' own curves are drawn thin
    beside the mean instead. One seed is drawn as its curve alone, which is how :func:`plot_run`
    draws a single run.
    """
    x = np.asarray(steps, dtype=float)
    for i, (label, curves) in enumerate(curves_by_config.items()):
        c = np.atleast_2d(np.asarray(curves, dtype=float))
        mean, lo, hi = mean_ci_band(c, n_boot=n_boot, rng=seed)
        color = (colors or {}).get(label, COLORS[i % len(COLORS)])
        n = c.shape[0]
        ax.plot(x, mean, color=color, linestyle=linestyle, lw=1.5,
                label=label if n == 1 else f"{label} (n={n})")
        if n == 1:
            continue
        banded = np.isfinite(c).sum(0) >= MIN_SEEDS_FOR_VERDICT
        if banded.any():
            ax.fill_between(x, np.where(banded, lo, np.nan), np.where(banded, hi, np.nan),
                            color=color, alpha=0.2, lw=0)
        if not banded.all():
            for curve in c:
                ax.plot(x, np.where(banded, np.nan, curve), color=color, linestyle=linestyle, lw=0.6, alpha=0.5)
    if logy:
        ax.set_yscale("log")
    steps_in_thousands(ax)
    ax.set_title(title, fontsize=10)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.grid(alpha=0.3)
    if curves_by_config:
        ax.legend(fontsize=7, loc="best")


def panel_grid(n_panels: int, ncols: int = 2, panel_size: tuple[float, float] = (5.0, 3.2)) -> tuple[Figure, list[Axes]]:
    """A figure with ``n_panels`` axes in a grid (unused cells removed)."""
    ncols = max(1, min(ncols, n_panels))
    nrows = max(1, math.ceil(n_panels / ncols))
    fig = Figure(figsize=(panel_size[0] * ncols, panel_size[1] * nrows), layout="constrained")
    axes = [fig.add_subplot(nrows, ncols, i + 1) for i in range(n_panels)]
    return fig, axes


# (title, ylabel, [(column, label)], source, log y) for each panel a run can have
_RUN_PANELS: list[tuple[str, str, list[tuple[str, str]], str, bool]] = [
    ("success rate", "success rate", [("success_rate", "eval"), ("train_success_rate", "train")], "both", False),
    ("intrinsic weight in force", "alpha", [("intrinsic_alpha", "alpha")], "metrics", False),  # a moving schedule's
    ("mean episode return", "return", [("mean_return", "eval"), ("train_return", "train")], "both", False),
    ("actor loss", "loss", [("actor_loss", "actor")], "metrics", False),
    ("critic loss", "loss", [("critic_loss", "critic")], "metrics", False),
    ("entropy coefficient", "alpha (entropy)", [("ent_coef", "ent_coef")], "metrics", True),
]


def _reward_panels(a: About) -> list[tuple[str, str, list[tuple[str, str]], str, bool]]:
    """A run's panels of its intrinsic reward, as its `About` names it: its models' losses (its metrics but the
    raw value), its normalised reward, its raw value."""
    losses = [(c, c) for c in a.metrics if c != a.raw_metric]
    return ([(f"{a.title} model losses", "loss", losses, "metrics", False)] if losses else []) + [
        (f"mean {a.title} reward (replay batches)", "reward", [("mean_intrinsic_reward", f"{a.title} reward")],
         "metrics", False),
        (f"{a.raw_label} ({a.title})", "raw value", [(a.raw_metric, a.raw_label)], "metrics", False)]


def plot_run(run_dir: str | Path, out_png: str | Path | None = None) -> Path:
    """Plot the learning curves of one run into a multi-panel PNG; returns its path.

    Panels: eval success rate and eval mean return (from eval.csv; the training-episode values
    from metrics.csv dashed beside them), the intrinsic weight if the run's schedule moves it, actor and
    critic loss, entropy coefficient, and the run's intrinsic reward as its `About` names it (MC: its model
    losses, mean MC reward, raw KL); a panel is left out when its columns are empty (e.g. the intrinsic panels of a
    plain SAC run). Default output: ``RUN_DIR/curves.png``.
    """
    run = Path(run_dir)
    if not run.is_dir():
        raise MCRLError(f"run directory {run} does not exist: pass a directory written by `mcrl train`")
    ev, mt = read_columns(run / EVAL), read_columns(run / METRICS)
    if not (has_data(ev, "step") or has_data(mt, "step")):
        raise MCRLError(f"{run} has no eval.csv or metrics.csv rows yet: wait for the run's first log "
                        "interval, or pass a run directory written by `mcrl train`")

    cfg = new_names(read_json(run / CONFIG))  # {} when unreadable: a plot must not fail on it
    moving = cfg.get("intrinsic_schedule", "constant") != "constant"  # a constant weight is a flat line: left out
    panels = []
    reward = about(str(cfg.get("intrinsic") or THESIS_REWARD))  # the config's default where it names none
    for title, ylabel, cols, source, logy in _RUN_PANELS + _reward_panels(reward):
        if cols[0][0] == "intrinsic_alpha" and not moving:
            continue
        series = []  # (steps, values, label, linestyle)
        for col, label in cols:
            # eval.csv names the eval columns plainly; metrics.csv prefixes them (eval_*).
            if col in ("success_rate", "mean_return") and has_data(ev, col):
                series.append((ev["step"], ev[col], label, "-"))
            elif has_data(mt, col):
                series.append((mt["step"], mt[col], label, "--" if source == "both" else "-"))
        if series:
            panels.append((title, ylabel, series, logy))

    fig, axes = panel_grid(len(panels))
    fig.suptitle(f"{run.name}  ({cfg.get('preset', '?')}, intrinsic_alpha={cfg.get('intrinsic_alpha', '?')}, "
                 f"seed={cfg.get('seed', '?')}){'' if is_done(run) else '  [unfinished]'}",
                 fontsize=11)
    for ax, (title, ylabel, series, logy) in zip(axes, panels):
        for k, (steps, values, label, ls) in enumerate(series):
            plot_curves_with_band(ax, steps, {label: values}, title=title, ylabel=ylabel,
                                  colors={label: COLORS[k]}, linestyle=ls,
                                  logy=logy and bool(np.nanmin(values) > 0))
    out = Path(out_png) if out_png is not None else run / "curves.png"
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=100)
    return out


def figure_to_png(fig: Figure, path: str | Path | None = None, dpi: int = 100) -> bytes:
    """Render ``fig`` to PNG bytes (and write them to ``path`` when given)."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    data = buf.getvalue()
    if path is not None:
        Path(path).write_bytes(data)
    return data


__all__ = ["plot_run", "plot_curves_with_band", "panel_grid", "has_data", "figure_to_png", "steps_in_thousands",
           "COLORS", "arm_colors", "curves_by_config"]
