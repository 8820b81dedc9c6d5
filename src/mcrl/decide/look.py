"""One look of a sequential plan: the statistic on every seed so far, the bounds, and each claim's decision.

Pure: a look is a function of the plan, the finals so far and the earlier looks' records (`take_look`), so it can be
recomputed and simulated (docs/confirmatory/fetchpush/simulate.py runs this very function).

The statistic is the rank-sum statistic of "X tends to be larger than Y", standardised with its tie-corrected null
variance (mid-ranks), so a success rate's ties (k / 100 episodes) do not inflate it. Its information is
``I = n_x n_y / (n_x + n_y + 1)`` (`mcrl.decide.boundaries`). Per claim, at its current level:

- efficacy bounds by the claim's alpha-spending function over I / I_max (I_max: both arms at the plan's maximum),
  recomputed at every look from the information actually reached (Lan-DeMets);
- a claim whose z reaches its bound is **reproduced**. With ``multiplicity: holm`` its level then passes to the
  claims not yet confirmed (split equally), which are tested again with bounds at their larger level at this look
  and every earlier one (Maurer and Bretz 2013's graphical procedure for group-sequential designs); with
  ``bonferroni`` every claim keeps its share. Either keeps the family's error rate at or under the plan's level.
- a futility bound by beta-spending under the planning effect; it is non-binding (the efficacy bounds ignore it),
  so a claim below it is **futile** and stops, and the error rate holds whether or not futility stops are obeyed;
- at the maximum the two bounds meet: a claim not reproduced by then is **not reproduced**.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from functools import lru_cache
from typing import Any

import numpy as np

from mcrl.analysis.hypothesis import midranks, on_grid, rank_sum_test
from mcrl.decide.boundaries import lower_bounds, upper_bounds
from mcrl.decide.plan import Claim, Plan

CONTINUE, REPRODUCED, FUTILE, NOT_REPRODUCED = "continue", "reproduced", "futile", "not reproduced"
DECIDED = (REPRODUCED, FUTILE, NOT_REPRODUCED)
NO_BOUND = 40.0  # an efficacy bound nothing reaches (no error spent yet); boundaries._HIGH


def rank_sum_z(x: Any, y: Any) -> float:
    """The standardised rank-sum statistic of "X tends to be larger than Y": (W - E W) / sd W, W the mid-rank sum of
    X, sd with the tie correction; 0 when every value is tied."""
    a, b = on_grid(x), on_grid(y)
    nx, ny = a.size, b.size
    if nx == 0 or ny == 0:
        raise ValueError(f"rank_sum_z needs values in both samples, got {nx} and {ny}")
    n = nx + ny
    pooled = np.concatenate([a, b])
    w = midranks(pooled)[:nx].sum()
    _, ties = np.unique(pooled, return_counts=True)
    var = nx * ny / 12.0 * ((n + 1) - float(np.sum(ties ** 3 - ties)) / (n * (n - 1)))
    return 0.0 if var <= 0 else float((w - nx * (n + 1) / 2.0) / math.sqrt(var))


def information(n_x: int, n_y: int) -> float:
    return n_x * n_y / (n_x + n_y + 1.0)


def shift_interval(x: Any, y: Any, bound: float, step: float = 0.005) -> tuple[float, float] | None:
    """The shifts d with |z(X - d, Y)| < ``bound``: a confidence interval for a location shift by test inversion.
    At a look's efficacy bound it is a repeated confidence interval (two-sided coverage at least 1 - 2 alpha
    across all looks, Jennison and Turnbull ch. 9), on a grid of ``step``. None while no error is spent."""
    if bound >= NO_BOUND - 1:
        return None
    a, b = np.asarray(x, float), np.asarray(y, float)
    span = float(max(a.max(), b.max()) - min(a.min(), b.min())) + step
    grid = np.arange(-span, span + step / 2, step)
    inside = [d for d in grid if abs(rank_sum_z(a - d, b)) < bound]
    return (float(min(inside)), float(max(inside))) if inside else None


def _level_in_force(plan: Plan, claim: Claim, reproduced: set[str]) -> float:
    """The claim's share, plus (holm) an equal part of each confirmed claim's level among those not confirmed."""
    level = claim.level
    if plan.multiplicity == "holm" and reproduced:
        open_ = [c for c in plan.claims if c.name not in reproduced]
        level += sum(c.level for c in plan.claims if c.name in reproduced) / max(1, len(open_))
    return min(level, plan.level)


def claim_bounds(plan: Plan, claim: Claim, infos: Sequence[float], level: float
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(efficacy bounds, cumulative alpha spent, futility bounds) of `claim` at looks with information `infos`, at
    `level`. A look's bounds depend only on the looks up to it, so a plan's simulation can compute them once."""
    return _claim_bounds(plan.max_seeds, claim, tuple(float(i) for i in infos), float(level))


@lru_cache(maxsize=4096)
def _claim_bounds(max_seeds: int, claim: Claim, infos: tuple[float, ...], level: float):
    info_max = information(max_seeds, max_seeds)
    upper, spent = upper_bounds(infos, info_max, level, claim.spending, claim.rho)
    f = claim.futility
    if f is None:
        lower = np.where(np.asarray(infos) >= info_max * (1 - 1e-12), upper, -np.inf)
    else:
        lower = lower_bounds(infos, info_max, upper, f.beta, f.theta, f.spending, f.rho)
    for a in (upper, spent, lower):
        a.setflags(write=False)  # shared by the cache
    return upper, spent, lower


def _finite(v: float) -> float | None:
    return float(v) if math.isfinite(v) and abs(v) < NO_BOUND - 1 else None


def take_look(plan: Plan, finals: Mapping[str, Sequence[float]], history: Sequence[Mapping[str, Any]],
              describe: bool = True) -> dict:
    """The record of the next look: every claim's statistic, bounds and decision (see the module's docstring).

    ``finals``: each arm's finals so far, in the plan's seed order; ``history``: the earlier looks' records.
    ``describe``: add the descriptive numbers that decide nothing (the fixed-sample p, the repeated confidence
    interval); a simulation leaves them out."""
    k = len(history) + 1
    prev = history[-1]["claims"] if history else {}
    decided = {n: c for n, c in prev.items() if c["decision"] in DECIDED}
    reproduced = {n for n, c in decided.items() if c["decision"] == REPRODUCED}
    claims: dict[str, dict] = {}
    series: dict[str, tuple[list[float], list[float]]] = {}  # open claims: z and information at their looks
    for c in plan.claims:
        if c.name in decided:
            claims[c.name] = dict(decided[c.name])
            continue
        x, y = np.asarray(finals[c.better], float), np.asarray(finals[c.than], float)
        z, info = rank_sum_z(x, y), information(x.size, y.size)
        zs = [h["claims"][c.name]["z"] for h in history] + [z]
        infos = [h["claims"][c.name]["information"] for h in history] + [info]
        series[c.name] = (zs, infos)
        claims[c.name] = {"better": c.better, "than": c.than, "n_x": int(x.size), "n_y": int(y.size), "z": z,
                          "information": info,
                          "information_fraction": min(1.0, info / information(plan.max_seeds, plan.max_seeds)),
                          "mean_x": float(x.mean()), "mean_y": float(y.mean()),
                          "difference": float(x.mean() - y.mean()),
                          "decision": CONTINUE}
        if describe:
            claims[c.name]["p_fixed_sample"] = rank_sum_test(x, y, "greater")
    changed = True
    while changed:  # a confirmed claim's level may confirm another at this look (holm)
        changed = False
        for c in plan.claims:
            r = claims[c.name]
            if c.name not in series or r["decision"] != CONTINUE:
                continue
            zs, infos = series[c.name]
            level = _level_in_force(plan, c, reproduced)
            upper, spent, lower = claim_bounds(plan, c, infos, level)
            r.update(level=level, upper=_finite(upper[-1]), lower=_finite(lower[-1]), alpha_spent=float(spent[-1]),
                     bounds={"upper": [_finite(u) for u in upper], "lower": [_finite(v) for v in lower]})
            crossed = [j + 1 for j, (zj, uj) in enumerate(zip(zs, upper)) if zj >= uj]
            if crossed:
                r.update(decision=REPRODUCED, decided_at=k, reason=(
                    f"z {zs[crossed[0] - 1]:+.3f} reached the efficacy bound {upper[crossed[0] - 1]:.3f} at look "
                    f"{crossed[0]}" + (f", with the level {level:g} in force at look {k}" if crossed[0] < k else "")))
                reproduced.add(c.name)
                changed = True
    for c in plan.claims:
        r = claims[c.name]
        if c.name not in series:
            continue
        zs, infos = series[c.name]
        x, y = np.asarray(finals[c.better], float), np.asarray(finals[c.than], float)
        upper = r["upper"] if r["upper"] is not None else NO_BOUND
        if describe:
            r["shift_rci"] = shift_interval(x, y, upper)
        if r["decision"] != CONTINUE:
            continue
        at_max = r["n_x"] >= plan.max_seeds and r["n_y"] >= plan.max_seeds
        lower = r["lower"] if r["lower"] is not None else -math.inf
        if at_max:
            r.update(decision=NOT_REPRODUCED, decided_at=k,
                     reason=f"the maximum ({plan.max_seeds} seeds an arm) reached with z {zs[-1]:+.3f} below "
                            f"the bound {upper:.3f}")
        elif zs[-1] <= lower:
            r.update(decision=FUTILE, decided_at=k,
                     reason=f"z {zs[-1]:+.3f} at or below the futility bound {lower:.3f}")
    open_arms = [a for a in plan.arms if any(claims[c.name]["decision"] == CONTINUE
                                             for c in plan.claims if a in c.arms)]
    p = claims[plan.primary.name]
    return {"look": k, "seeds_per_arm": {a: len(finals[a]) for a in plan.arms},
            "finals": {a: [float(v) for v in finals[a]] for a in plan.arms},
            "primary": plan.primary.name, "z": p["z"], "upper": p.get("upper"), "lower": p.get("lower"),
            "alpha_spent": p.get("alpha_spent"), "decision": p["decision"], "claims": claims,
            "continue_arms": open_arms, "done": not open_arms, "plan_hash": plan.hash}
