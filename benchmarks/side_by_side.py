"""Whole-run speed of presets alone and side by side: environment steps/s of the real training loop
(`harness.measure_loop`), each run in its own process pinned to one core as `mcrl sweep --threads-per-run 1` pins
its workers; first each preset alone (the other cores idle), then all of them at once, one core each.

    python benchmarks/side_by_side.py [--presets antmaze-sac,antmaze-sacmc] [--steps 1000] [--repeats 3]
                                      [--warmup 1000] [--set KEY=VALUE] [--json out.json]

Prints one Markdown table: per preset, steps/s alone, side by side, and their ratio (medians over `--repeats`
logging intervals of `--steps` after `--warmup` learning steps, as bench.py's loop column). Both numbers come from
one call on one machine, so the ratio holds across machines where the absolute speed does not. Two runs on a
2-core machine share its caches and memory bandwidth: the ratio says what that costs. Run it on an otherwise idle
machine (pause background runs with SIGSTOP, as for intrinsic_cost.py): "alone" means alone.
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import sys

import _common


def _one(preset: str, slot: int, steps: int, repeats: int, warmup: int, overrides: dict, barrier, results) -> None:
    from mcrl.sweep.worker import pin_cores

    cores = pin_cores(1, slot)  # before jax is imported: XLA sizes its thread pool by these cores
    from harness import measure_loop

    barrier.wait()  # the runs of a side-by-side start together, so their timed intervals overlap
    out = measure_loop(preset, steps=steps, repeats=repeats, warmup=warmup, overrides=overrides)
    results.put({"slot": slot, "preset": preset, "cores": cores, **out})


def run_together(presets: list[str], a, overrides: dict) -> list[dict]:
    """Each preset in its own spawned process on its own core, started together; their measure_loop results, in
    the order of `presets`."""
    ctx = mp.get_context("spawn")
    barrier, results = ctx.Barrier(len(presets)), ctx.Queue()
    procs = [ctx.Process(target=_one, args=(p, i, a.steps, a.repeats, a.warmup, overrides, barrier, results))
             for i, p in enumerate(presets)]
    for p in procs:
        p.start()
    out = sorted((results.get(timeout=7200) for _ in procs), key=lambda r: r["slot"])
    for p in procs:
        p.join()
        if p.exitcode:
            sys.exit(f"side_by_side: a worker exited with {p.exitcode}")
    return out


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--presets", default="antmaze-sac,antmaze-sacmc")
    p.add_argument("--steps", type=int, default=1000, help="env steps per timed interval")
    p.add_argument("--repeats", type=int, default=3, help="timed intervals per run")
    p.add_argument("--warmup", type=int, default=1000, help="learning steps before the first timed interval")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config override (repeatable)")
    p.add_argument("--json")
    a = p.parse_args()
    from mcrl.config import parse_set  # after _common: this checkout's src/ when mcrl is not installed

    overrides = parse_set(a.set)
    presets = a.presets.split(",")
    if _common.usable_cores() < len(presets):
        sys.exit(f"side_by_side: {len(presets)} presets need as many cores, this process may use "
                 f"{_common.usable_cores()}; pass fewer --presets")
    alone = []
    for name in presets:
        _common.log(f"{name} alone ...")
        alone += run_together([name], a, overrides)
    _common.log(f"{', '.join(presets)} side by side ...")
    together = run_together(presets, a, overrides)
    print(f"{_common.cpu_label() or 'CPU model unknown'}, {_common.usable_cores()} usable cores; one core a run; "
          f"median env steps/s over {a.repeats} intervals of {a.steps} after {a.warmup} learning steps")
    print()
    print("\n".join(_common.md_head(["preset", "alone", "side by side", "side by side / alone"])))
    for name, x, y in zip(presets, alone, together):
        x, y = x["steps_per_s"], y["steps_per_s"]
        print(_common.md_row([name, f"{x:.1f}", f"{y:.1f}", f"{y / x:.2f}x"]))
    if a.json:
        _common.write_json(a.json, {"machine": _common.cpuinfo().get("model name"), "cpu": _common.cpu_label(),
                                    "args": vars(a), "alone": alone, "side_by_side": together})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
