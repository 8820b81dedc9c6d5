"""What the committed FetchPush runs say about a `success` schedule (issue 67, item 5), before any run of one.

For the reproduction's SAC and SAC-MC arms (150,000 steps, final evaluation of 100 episodes), the training
episodes' success (metrics.csv `train_success_rate`, mean of the log rows in the 5,000 steps up to t, roughly the
last 100 training episodes: the default `intrinsic_success_window`) over training, and the weight
`alpha0 (1 - s_t)` a `success` schedule from alpha0 would have given a run with that success. Exploratory: no
claim is tested here.

    python docs/intrinsic/schedule/curve.py        # prints the Markdown table quoted in docs/intrinsic.md
    python docs/intrinsic/schedule/curve.py --arm  # the same for the `success` arm's finished runs (arm/runs),
                                                   # with the weight in force (metrics.csv `intrinsic_alpha`)
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from mcrl.renames import new_names
from mcrl.run.rundir import read_json, read_rows

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1] / "reproduction" / "fetchpush"
ARMS = {"SAC": ("main", 0.0), "SAC-MC 0.2": ("main", 0.2), "SAC-MC 0.4": ("alpha-curve", 0.4),
        "SAC-MC 0.6": ("alpha-curve", 0.6), "SAC-MC 0.8": ("alpha-curve", 0.8)}
AT = (10_000, 25_000, 50_000, 100_000, 150_000)
WINDOW = 5_000  # env steps: 100 FetchPush episodes of 50 steps


def near(rows: list[dict], column: str) -> list[float]:
    """The column's mean over the log rows in the WINDOW steps up to each step of AT."""
    return [np.mean([r[column] for r in rows if t - WINDOW < r["step"] <= t and r.get(column) is not None])
            for t in AT]


def arm_success(runs: Path, alpha: float | None, column: str = "train_success_rate"):
    """(seeds, len(AT)) of `column` near each step of AT, and each seed's final evaluation success, over the
    finished runs under `runs` (those at `alpha` unless it is None)."""
    curves, finals = [], []
    for rd in sorted(runs.iterdir()):
        if not (rd / "final_eval.json").exists():
            continue
        if alpha is not None and float(new_names(read_json(rd / "config.json")).get("intrinsic_alpha", -1)) != alpha:
            continue
        curves.append(near(read_rows(rd / "metrics.csv"), column))
        finals.append(read_json(rd / "final_eval.json")["success_rate"])
    return np.array(curves), np.array(finals)


def arm_table() -> None:
    """The `success` arm beside the fixed-weight arms (the reproduction's seeds 0-11 and the confirmatory experiment's
    fresh seeds): training success, the weight in force, finals."""
    heads = " / ".join(f"{t // 1000}k" for t in AT)
    print(f"| arm | seeds | training success at {heads} | weight in force at {heads} | final eval success: mean "
          "(range) | seeds with final >= 0.2 |")
    print("| --- | --- | --- | --- | --- | --- |")
    arms = [(name, ROOT / exp / "runs", alpha, None) for name, (exp, alpha) in ARMS.items() if alpha <= 0.4]
    fresh = HERE.parents[1] / "confirmatory" / "fetchpush" / "runs"
    arms += [(f"{name}, confirmatory seeds 1000-1017", fresh, alpha, None) for name, alpha in
             (("SAC", 0.0), ("SAC-MC 0.2", 0.2))]
    arms.append(("SAC-MC 0.4, `success` schedule", HERE / "arm" / "runs", None, "intrinsic_alpha"))
    for name, runs, alpha, weight in arms:
        c, f = arm_success(runs, alpha)
        w = (" / ".join(f"{v:.2f}" for v in arm_success(runs, alpha, weight)[0].mean(0)) if weight
             else " / ".join([f"{alpha:.2f}"] * len(AT)))
        print(f"| {name} | {len(c)} | " + " / ".join(f"{v:.2f}" for v in c.mean(0)) + f" | {w} | {f.mean():.2f} "
              f"({f.min():.2f}-{f.max():.2f}) | {int((f >= 0.2).sum())} of {len(f)} |")


def main() -> int:
    if "--arm" in sys.argv[1:]:
        arm_table()
        return 0
    print("| arm | seeds | training success at " + " / ".join(f"{t // 1000}k" for t in AT)
          + " | final eval success | alpha0 (1 - s) at 150k as a share of alpha0: seeds' range |")
    print("| --- | --- | --- | --- | --- |")
    for name, (exp, alpha) in ARMS.items():
        c, f = arm_success(ROOT / exp / "runs", alpha)
        share = 1 - c[:, -1]
        print(f"| {name} | {len(c)} | " + " / ".join(f"{v:.2f}" for v in c.mean(0)) + f" | {f.mean():.2f} | "
              f"{share.min():.2f} - {share.max():.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
