"""The gradient step's cost with each intrinsic reward: SAC, SAC-MC, SAC+RND, SAC+ICM and SAC+Disagreement at the
thesis' FetchPush sizes (`fetchpush-sacmc-0.2` with `intrinsic=...`; SAC is `fetchpush-sac`), measured in one run.

    python benchmarks/intrinsic_cost.py [--repeats 7] [--calls 50] [--threads N] [--json out.json]

Each configuration's jitted step (what the training loop compiles) is compiled first; then the timed blocks of
`--calls` steps go round-robin over the configurations, `--repeats` rounds, so that a change in the machine's load
falls on all of them alike. Prints ms per step (median), gradient steps/s, GFLOP per step (XLA's cost analysis),
GFLOP/s and each one's cost relative to SAC. Results: docs/performance.md, "The intrinsic rewards' cost".
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys

from _common import cpu_label, md_head, md_row, write_json

CONFIGS = [("SAC", "fetchpush-sac", {}), ("SAC-MC", "fetchpush-sacmc-0.2", {}),
           ("SAC+RND", "fetchpush-sacmc-0.2", {"intrinsic": "rnd"}),
           ("SAC+ICM", "fetchpush-sacmc-0.2", {"intrinsic": "icm"}),
           ("SAC+Disagreement", "fetchpush-sacmc-0.2", {"intrinsic": "disagreement"})]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--calls", type=int, default=50)
    p.add_argument("--threads", type=int, help="XLA threads (default: all cores)")
    p.add_argument("--json")
    a = p.parse_args()
    if a.threads:  # before jax is imported
        os.environ["XLA_FLAGS"] = (f"--xla_cpu_multi_thread_eigen={'true' if a.threads > 1 else 'false'} "
                                   f"intra_op_parallelism_threads={a.threads}")
    from harness import update_timer

    timers = {name: update_timer(preset, over) for name, preset, over in CONFIGS}
    times: dict[str, list[float]] = {name: [] for name in timers}
    for _ in range(a.repeats):
        for name, (time_block, _) in timers.items():
            times[name].append(time_block(a.calls))
    base = statistics.median(times["SAC"])
    rows = []
    for name, (_, gflop) in timers.items():
        ms = statistics.median(times[name])
        rows.append({"config": name, "ms_per_grad_step": ms, "grad_steps_per_s": 1e3 / ms, "gflop": gflop,
                     "gflop_per_s": gflop / ms * 1e3, "cost_vs_sac": ms / base, "ms_all": times[name]})
    print(f"# gradient step at FetchPush sizes, {cpu_label()}, {os.environ.get('XLA_FLAGS', 'all cores')}")
    print("\n".join(md_head(["config", "ms / step (median)", "steps/s", "GFLOP / step", "GFLOP/s", "x SAC"])))
    for r in rows:
        print(md_row([r["config"], f"{r['ms_per_grad_step']:.2f}", f"{r['grad_steps_per_s']:.1f}", f"{r['gflop']:.2f}",
                      f"{r['gflop_per_s']:.0f}", f"{r['cost_vs_sac']:.2f}"]))
    if a.json:
        write_json(a.json, {"cpu": cpu_label(), "xla_flags": os.environ.get("XLA_FLAGS"), "repeats": a.repeats,
                            "calls": a.calls, "rows": rows})
    return 0


if __name__ == "__main__":
    sys.exit(main())
