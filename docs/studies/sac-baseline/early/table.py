"""The early-course table of issue 49 item 3 (docs/studies/sac-baseline/README.md): mcrl's SAC with each tanh
correction beside stable-baselines3's SAC over the first 20,000 steps of FetchPush, from committed run directories.

    python docs/studies/sac-baseline/early/table.py docs/studies/sac-baseline/early

Arms: mcrl `exact` and `epsilon` (HERE/mcrl, squash_correction=...), stable-baselines3 re-run with the extra
diagnostics (HERE/sb3), the committed stable-baselines3 arm (docs/reproduction/fetchpush/sb3-sac, its first 20,000
steps) and the committed mcrl SAC arm (docs/reproduction/fetchpush/main alpha=0, the same). Each quantity is a
per-run mean over a window of metrics.csv rows (by their step: a row is the mean of the 1,000 steps up to it),
then the mean over seeds with a 95% bootstrap interval; each mcrl arm is compared with each stable-baselines3 arm
by the difference of means [95% bootstrap CI] and a two-sided exact rank-sum p (seeds as the unit).
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from mcrl.analysis.hypothesis import rank_sum_test
from mcrl.analysis.stats import mean_difference_ci
from mcrl.run.rundir import read_columns

REPO = Path(__file__).resolve().parents[4]
# (column, first step, last step, digits): the windows the audit used, plus the start of learning
QUANTITIES = (("mean_ext_reward", 1_000, 20_000, 4), ("mean_ext_reward", 3_000, 20_000, 4),
              ("q_mean", 10_000, 20_000, 2), ("ent_coef", 10_000, 20_000, 3), ("ent_coef", 1_000, 5_000, 3),
              ("saturated_share", 1_000, 5_000, 4), ("saturated_share", 1_000, 20_000, 4),
              ("logp_gap", 1_000, 20_000, 3), ("train_goal_moved", 1_000, 5_000, 3),
              ("train_goal_moved", 1_000, 20_000, 3), ("train_success_rate", 10_000, 20_000, 3),
              ("eval_success_rate", 20_000, 20_000, 2))


def runs(exp: Path, keep=lambda cfg: True, upto: int = 20_000) -> list[dict[str, np.ndarray]]:
    out = []
    for d in sorted((exp / "runs").glob("*")):
        cfg = json.loads((d / "config.json").read_text())
        if not keep(cfg) or not (d / "metrics.csv").is_file():
            continue
        cols = read_columns(d / "metrics.csv")
        if cols and np.nanmax(cols["step"]) >= upto:
            out.append(cols)
    return out


def window(cols: dict[str, np.ndarray], col: str, lo: int, hi: int) -> float:
    if col not in cols:
        return np.nan
    sel = (cols["step"] >= lo) & (cols["step"] <= hi)
    v = cols[col][sel]
    return float(np.nanmean(v)) if np.isfinite(v).any() else np.nan


def main(here: Path) -> int:
    arms = {
        "mcrl exact": runs(here / "mcrl", lambda c: c.get("squash_correction") == "exact"),
        "mcrl epsilon": runs(here / "mcrl", lambda c: c.get("squash_correction") == "epsilon"),
        "SB3 (re-run)": runs(here / "sb3"),
        "SB3 (committed 0-5)": runs(REPO / "docs/reproduction/fetchpush/sb3-sac"),
        "mcrl exact (committed 0-11)": runs(REPO / "docs/reproduction/fetchpush/main",
                                            lambda c: c.get("mc_alpha") == 0.0),
    }
    per = {a: {q: np.array([window(c, q[0], q[1], q[2]) for c in rs]) for q in QUANTITIES}
           for a, rs in arms.items()}
    def label(q):
        return f"`{q[0]}`, {q[1] // 1000}k-{q[2] // 1000}k" if q[1] != q[2] else f"`{q[0]}` at {q[1] // 1000}k"

    def finite(v):
        return v[np.isfinite(v)]

    print("| quantity | " + " | ".join(f"{a} ({len(rs)})" for a, rs in arms.items()) + " |")
    print("|---|" + "---|" * len(arms))
    for q in QUANTITIES:
        cells = [f"{finite(per[a][q]).mean():.{q[3]}f}" if finite(per[a][q]).size else "-" for a in arms]
        print(f"| {label(q)} | " + " | ".join(cells) + " |")
    print()
    print("| quantity | mcrl arm | SB3 arm | difference [95% CI] | rank-sum p (two-sided) |")
    print("|---|---|---|---|---|")
    for q in QUANTITIES:
        for m in ("mcrl exact", "mcrl epsilon", "mcrl exact (committed 0-11)"):
            for s in ("SB3 (re-run)", "SB3 (committed 0-5)"):
                x, y = finite(per[m][q]), finite(per[s][q])
                if x.size < 3 or y.size < 3:
                    continue
                est, lo, hi = mean_difference_ci(x, y)
                d = q[3]
                print(f"| {label(q)} | {m} ({x.size}) | {s} ({y.size}) | {est:+.{d}f} [{lo:+.{d}f}, {hi:+.{d}f}] | "
                      f"{rank_sum_test(x, y, 'two-sided'):.3g} |")
    return 0


if __name__ == "__main__":
    sys.exit(main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parent))
