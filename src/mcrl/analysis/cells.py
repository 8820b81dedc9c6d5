"""What the report's sections share: how numbers read in a cell, seed-level summaries, and which arms are which."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from mcrl.algo.intrinsic import THESIS_REWARD
from mcrl.analysis.experiment import ConfigGroup, Experiment
from mcrl.analysis.stats import MIN_SEEDS_FOR_VERDICT, bootstrap_ci

CONF = 0.95
SEED = 0  # every bootstrap in a report uses it: the same runs give the same report


def num(x: float | None, digits: int) -> str:
    return "n/a" if x is None or not math.isfinite(x) else f"{x:.{digits}f}"


def interval(iv: Sequence[float] | None, digits: int) -> str:
    return "n/a" if iv is None else f"[{num(iv[0], digits)}, {num(iv[1], digits)}]"


def pvalue(p: float) -> str:
    return "n/a" if not math.isfinite(p) else (f"{p:.4f}" if p >= 1e-4 else f"{p:.1e}")


def steps(n: float | int | None) -> str:
    return "?" if n is None else f"{int(n):,}"


def code(s: Any) -> str:
    s = str(s)
    return f"`{s}`" if "`" not in s else s


def name(g: ConfigGroup) -> str:
    """A group's table cell: its label, marked when it is a reference arm."""
    return f"`{g.key}` (reference)" if g.peer else f"`{g.key}`"


def mean_ci(x: np.ndarray) -> tuple[float, tuple[float, float] | None]:
    """Mean and 95% percentile-bootstrap CI over seeds; no CI from fewer than MIN_SEEDS_FOR_VERDICT seeds
    (a bootstrap over two seeds is only their range, not a 95% interval)."""
    if x.size == 0:
        return math.nan, None
    return float(x.mean()), (bootstrap_ci(x, np.mean, conf=CONF, rng=SEED) if x.size >= MIN_SEEDS_FOR_VERDICT else None)


def mean_cell(est: float, ci: Sequence[float] | None, n: int, digits: int) -> str:
    """'0.557 [0.395, 0.698]'; from fewer than MIN_SEEDS_FOR_VERDICT seeds (n: the smallest arm's), the estimate
    and why it has no interval."""
    if n == 0 or not math.isfinite(est):
        return "n/a"
    if n < MIN_SEEDS_FOR_VERDICT or ci is None:
        return f"{num(est, digits)} (no CI from {n} seed{'s' if n > 1 else ''}, need >= {MIN_SEEDS_FOR_VERDICT})"
    return f"{num(est, digits)} {interval(ci, digits)}"


def sample_var(x: np.ndarray) -> float:
    """Sample variance across seeds (ddof=1); NaN for fewer than 2 seeds."""
    return float(x.var(ddof=1)) if x.size >= 2 else math.nan


def too_few(*ns: int) -> str | None:
    """The report's text for a reading from too few seeds, or None when every n is enough."""
    if min(ns) >= MIN_SEEDS_FOR_VERDICT:
        return None
    return f"too few seeds for a verdict: n = {' vs '.join(map(str, ns))}, need >= {MIN_SEEDS_FOR_VERDICT}"


# ------------------------------------------------------------------------------------ which arm is which


def mcrl_groups(exp: Experiment) -> list[ConfigGroup]:
    return [g for g in exp.configs if g.peer is None]


def is_scheduled(g: ConfigGroup) -> bool:
    """Runs whose intrinsic weight moves during training (`intrinsic_schedule` other than constant). Their
    intrinsic_alpha is only the weight they start from, so they are no point of the thesis' fixed-alpha claims or
    curve: they are an arm of their own, compared like another intrinsic reward (:func:`other_intrinsic`)."""
    return g.intrinsic_schedule != "constant"


def sac_and_mc(exp: Experiment) -> tuple[list[ConfigGroup], list[ConfigGroup]]:
    """mcrl's finished SAC (intrinsic_alpha 0) and SAC-MC (intrinsic_alpha > 0 with the thesis' reward,
    `THESIS_REWARD`) configurations, each at a constant weight."""
    with_data = [g for g in mcrl_groups(exp) if g.finished and g.intrinsic_alpha is not None and not is_scheduled(g)]
    return ([g for g in with_data if g.intrinsic_alpha == 0.0],
            [g for g in with_data if g.intrinsic_alpha > 0.0 and g.intrinsic == THESIS_REWARD])


def other_intrinsic(exp: Experiment) -> list[ConfigGroup]:
    """mcrl's finished configurations that mix in another intrinsic reward than the thesis' (RND, ICM,
    Disagreement, any registered), or any reward under a moving weight (:func:`is_scheduled`)."""
    return [g for g in mcrl_groups(exp) if g.finished and (
        is_scheduled(g) or ((g.intrinsic_alpha or 0.0) > 0.0 and g.intrinsic != THESIS_REWARD))]


def reference_sac(exp: Experiment) -> list[ConfigGroup]:
    """Finished reference arms (trained by another system) at intrinsic_alpha 0: other implementations of SAC."""
    return [g for g in exp.configs if g.peer and g.finished and (g.intrinsic_alpha or 0.0) == 0.0]


def is_code_variant(g: ConfigGroup) -> bool:
    """Runs with the thesis' code's MC reward: one batch-mean KL for all transitions, the whole observation."""
    started = [r for r in g.runs if r.config]  # a run not started yet has no config.json to tell
    return bool(started) and all(r.config.get("mc_reduction") == "batch" and r.config.get("intrinsic_state") == "full"
                                 for r in started)
