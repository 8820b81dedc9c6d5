"""Does a long run slow down? Steps/s of the first vs the last 10% of a real run, peak memory, and the
thesis-sized gradient step with an empty vs a full normaliser history.

    python benchmarks/flat_cost.py [--preset fetchpush-sacmc-0.2] [--steps 150000] [--hidden 64]
                                   [--json out.json]

The long run uses the real training loop (`mcrl.run.trainer.train`) with the preset's 1,000,000-transition
buffer and 400,000-value normaliser history, its networks shrunk to `--hidden` so that it fits in minutes; the
gradient step at the thesis' sizes is timed separately with the normaliser's history empty and full. Prints a
Markdown table; why it is measured this way, and the results: docs/performance.md, "Flat cost over a run".
"""
from __future__ import annotations

import argparse
import resource
import statistics
import sys
import tempfile
from pathlib import Path

from _common import write_json
from harness import measure_update
from mcrl.config import resolve_config
from mcrl.run.rundir import read_rows
from mcrl.run.trainer import train


def long_run(preset: str, steps: int, hidden: int) -> dict:
    log_every = max(steps // 100, 50)
    sizes = [hidden] * 3
    cfg = resolve_config(preset, {"total_steps": steps, "log_every": log_every, "eval_every": steps // 10,
                                  "eval_episodes": 5, "hidden_sizes": sizes, "intrinsic_hidden_sizes": [hidden] * 5,
                                  "checkpoint_every": steps // 5, "keep_checkpoints": 1})
    with tempfile.TemporaryDirectory() as d:
        run = train(cfg, Path(d) / "long", progress=True)
        rows = read_rows(run / "metrics.csv")
    t = [(int(r["step"]), r["time_s"]) for r in rows]
    tenth = steps // 10

    def rate(lo, hi):  # per-interval rates inside [lo, hi], median (robust to an eval or checkpoint interval)
        rates = [(s1 - s0) / (t1 - t0) for (s0, t0), (s1, t1) in zip(t, t[1:]) if lo <= s0 and s1 <= hi]
        return statistics.median(rates)

    first, last = rate(cfg.learning_starts + log_every, tenth), rate(steps - tenth, steps)
    return {"steps": steps, "hidden": hidden, "first_10pct_steps_per_s": first, "last_10pct_steps_per_s": last,
            "last_over_first": last / first,
            "peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="fetchpush-sacmc-0.2")
    p.add_argument("--steps", type=int, default=150_000)
    p.add_argument("--hidden", type=int, default=64)
    p.add_argument("--json")
    a = p.parse_args()
    out = {"update_empty_history": measure_update(a.preset, repeats=5, calls=50),
           "update_full_history": measure_update(a.preset, repeats=5, calls=50, full_history=True)}
    out["long_run"] = long_run(a.preset, a.steps, a.hidden)
    e, f = out["update_empty_history"]["ms_per_grad_step"], out["update_full_history"]["ms_per_grad_step"]
    lr = out["long_run"]
    print(f"| measure | value |\n| --- | --- |\n"
          f"| {a.preset} gradient step, thesis sizes, empty history | {e:.2f} ms |\n"
          f"| same, history full (400,000 values) | {f:.2f} ms ({f / e:.3f}x) |\n"
          f"| {a.steps}-step run ({a.hidden}-wide nets): first 10% | {lr['first_10pct_steps_per_s']:.1f} steps/s |\n"
          f"| last 10% | {lr['last_10pct_steps_per_s']:.1f} steps/s ({lr['last_over_first']:.3f}x) |\n"
          f"| peak resident memory (1,000,000-transition buffer) | {lr['peak_rss_gib']:.2f} GiB |")
    if a.json:
        write_json(a.json, out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
