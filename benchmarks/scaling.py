"""How the SAC-MC gradient step's cost grows with batch size and network width.

    python benchmarks/scaling.py [--preset fetchpush-sacmc-0.2] [--set matmul_precision=bfloat16] [--json out.json]

For each setting: ms per jitted gradient step (median of 3 blocks), XLA's FLOP count and the achieved
GFLOP/s. Width applies to the actor, the critics and the MC models (depths stay 3 and 5).
"""
from __future__ import annotations

import argparse
import sys

from _common import write_json
from harness import measure_update
from mcrl.config import parse_set


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="fetchpush-sacmc-0.2")
    p.add_argument("--batches", default="128,256,512,1024,2048")
    p.add_argument("--widths", default="64,128,256,512")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override (repeatable)")
    p.add_argument("--json")
    a = p.parse_args()
    fixed = parse_set(a.set)
    rows = []
    settings = [(int(b), 256) for b in a.batches.split(",")] + [(256, int(w)) for w in a.widths.split(",") if w != "256"]
    for batch, width in settings:
        over = {**fixed, "batch_size": batch, "hidden_sizes": [width] * 3, "intrinsic_hidden_sizes": [width] * 5}
        m = measure_update(a.preset, repeats=3, calls=max(10, 12_000 // batch), overrides=over)
        rows.append({"batch": batch, "width": width, **m,
                     "gflops_per_s": m["grad_step_gflop"] / (m["ms_per_grad_step"] / 1e3)})
        print(f"batch {batch:5d} width {width:4d}: {m['ms_per_grad_step']:8.2f} ms  "
              f"{m['grad_step_gflop']:7.3f} GFLOP  {rows[-1]['gflops_per_s']:6.1f} GFLOP/s", file=sys.stderr)
    print("| batch | width | ms / gradient step | GFLOP / step | GFLOP/s |\n| --- | --- | --- | --- | --- |")
    for r in rows:
        print(f"| {r['batch']} | {r['width']} | {r['ms_per_grad_step']:.2f} | {r['grad_step_gflop']:.3f} | "
              f"{r['gflops_per_s']:.0f} |")
    if a.json:
        write_json(a.json, rows)
    return 0


if __name__ == "__main__":
    sys.exit(main())
