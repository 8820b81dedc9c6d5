"""What the committed FetchPush runs say about a `success` schedule (issue 67, item 5), before any run of one.

For the reproduction's SAC and SAC-MC arms (150,000 steps, final evaluation of 100 episodes), the training
episodes' success (metrics.csv `train_success_rate`, mean of the log rows in the 5,000 steps up to t, roughly the
last 100 training episodes: the default `intrinsic_success_window`) over training, and the weight
`alpha0 (1 - s_t)` a `success` schedule from alpha0 would have given a run with that success. Exploratory: no
claim is tested here.

    python docs/intrinsic/schedule/curve.py        # prints the Markdown table quoted in docs/intrinsic.md
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from mcrl.renames import new_names
from mcrl.run.rundir import read_json, read_rows

ROOT = Path(__file__).resolve().parents[2] / "reproduction" / "fetchpush"
ARMS = {"SAC": ("main", 0.0), "SAC-MC 0.2": ("main", 0.2), "SAC-MC 0.4": ("alpha-curve", 0.4),
        "SAC-MC 0.6": ("alpha-curve", 0.6), "SAC-MC 0.8": ("alpha-curve", 0.8)}
AT = (10_000, 25_000, 50_000, 100_000, 150_000)
WINDOW = 5_000  # env steps: 100 FetchPush episodes of 50 steps


def arm_success(exp: str, alpha: float) -> tuple[np.ndarray, np.ndarray]:
    """(seeds, len(AT)) training success near each step of AT, and each seed's final evaluation success."""
    curves, finals = [], []
    for rd in sorted((ROOT / exp / "runs").iterdir()):
        if float(new_names(read_json(rd / "config.json")).get("intrinsic_alpha", -1)) != alpha:
            continue
        rows = [r for r in read_rows(rd / "metrics.csv") if r.get("train_success_rate") is not None]
        curves.append([np.mean([r["train_success_rate"] for r in rows if t - WINDOW < r["step"] <= t]) for t in AT])
        finals.append(read_json(rd / "final_eval.json")["success_rate"])
    return np.array(curves), np.array(finals)


def main() -> int:
    print("| arm | seeds | training success at " + " / ".join(f"{t // 1000}k" for t in AT)
          + " | final eval success | alpha0 (1 - s) at 150k as a share of alpha0: seeds' range |")
    print("| --- | --- | --- | --- | --- |")
    for name, (exp, alpha) in ARMS.items():
        c, f = arm_success(exp, alpha)
        share = 1 - c[:, -1]
        print(f"| {name} | {len(c)} | " + " / ".join(f"{v:.2f}" for v in c.mean(0)) + f" | {f.mean():.2f} | "
              f"{share.min():.2f} - {share.max():.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
