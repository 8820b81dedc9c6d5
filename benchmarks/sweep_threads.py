"""Do a local sweep's workers keep to their cores? The cores they run on, CPU time over wall time and gradient steps
per second of worker processes started as `mcrl sweep --backend local` starts them, pinned or not.

    python benchmarks/sweep_threads.py [--seconds 8] [--repeats 3] [--preset fetchpush-sacmc-0.2]

Each worker is a fresh 'spawn' process, like a local sweep's. It pins itself with
`mcrl.sweep.worker.pin_cores(threads, slot)`, as a sweep's worker does with `--threads-per-run N`, or stays on
every core (a sweep's default; before issue 52 also with the option, whose XLA flags did not limit it,
`xla_threads.py`); then it imports jax, compiles the preset's SAC-MC gradient step (what a run compiles)
on a random replay batch, waits for the other workers and runs the step for `--seconds`. It reports the cores it
may use (its affinity), the cores its threads were seen running on (sampled every 10 ms), its CPU time (all of its
threads) over that wall time, and its gradient steps per second. Variants: one worker on every core
and on one core (`--threads-per-run 1`), then one worker per core, unpinned and pinned. Prints the medians over the
repeats (per worker: the mean over the workers of one repeat).
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import statistics
import sys
import threading
import time

import _common


def _worker(preset: str, threads: int, slot: int, pin: bool, seconds: float, barrier, results) -> None:
    from mcrl.sweep.worker import pin_cores

    cores = pin_cores(threads, slot) if pin else sorted(os.sched_getaffinity(0))
    import jax
    import numpy as np

    from mcrl.algo.sac import Agent, Batch
    from mcrl.config import resolve_config

    cfg = resolve_config(preset)
    agent = Agent(31, 4, 25, cfg)  # FetchPush's sizes: 31-d policy input, 4-d action, 25-d observation part
    rng = np.random.default_rng(slot)
    b = cfg.batch_size
    batch = Batch(rng.normal(size=(b, 31)).astype(np.float32), rng.uniform(-1, 1, (b, 4)).astype(np.float32),
                  -np.ones(b, np.float32), rng.normal(size=(b, 31)).astype(np.float32), np.zeros(b, np.float32))
    step = jax.jit(agent.update, donate_argnums=(0,))
    state, _ = step(agent.init(slot), batch)
    jax.block_until_ready(state)
    barrier.wait()
    ran_on, done = set(), threading.Event()
    sampler = threading.Thread(target=_sample_cores, args=(ran_on, done), daemon=True)
    sampler.start()
    t0, c0, n = time.perf_counter(), os.times(), 0
    while time.perf_counter() - t0 < seconds:
        state, _ = step(state, batch)
        n += 1
    jax.block_until_ready(state)
    wall, c1 = time.perf_counter() - t0, os.times()
    done.set()
    sampler.join()
    results.put({"cores": len(cores), "cpu_per_wall": ((c1.user - c0.user) + (c1.system - c0.system)) / wall,
                 "steps_per_s": n / wall, "ran_on": len(ran_on)})


def _sample_cores(ran_on: set, done) -> None:
    """Every 10 ms, the core each running thread of this process is on (/proc/self/task/*/stat, field 39)."""
    while not done.wait(0.01):
        for task in os.listdir("/proc/self/task"):
            try:
                with open(f"/proc/self/task/{task}/stat") as f:
                    fields = f.read().rsplit(")", 1)[1].split()
            except OSError:
                continue
            if fields[0] == "R":
                ran_on.add(int(fields[36]))


def run_variant(preset: str, workers: int, threads: int, pin: bool, seconds: float) -> list[dict]:
    ctx = mp.get_context("spawn")
    barrier, results = ctx.Barrier(workers), ctx.Queue()
    procs = [ctx.Process(target=_worker, args=(preset, threads, i, pin, seconds, barrier, results))
             for i in range(workers)]
    for p in procs:
        p.start()
    out = [results.get(timeout=600) for _ in procs]
    for p in procs:
        p.join()
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=8.0)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--preset", default="fetchpush-sacmc-0.2")
    a = p.parse_args()
    if not hasattr(os, "sched_setaffinity"):
        sys.exit("sweep_threads: this platform has no os.sched_setaffinity (Linux only)")
    cores = _common.usable_cores()
    variants = [("1 worker, every core (default)", 1, cores, False), ("1 worker, --threads-per-run 1", 1, 1, True),
                (f"{cores} workers, every core (default)", cores, 1, False),
                (f"{cores} workers, --threads-per-run 1", cores, 1, True)]
    print(f"{cores} usable cores ({_common.cpu_label() or 'CPU model unknown'}); {a.preset}'s gradient step, "
          f"{a.seconds:g} s per worker, median of {a.repeats}")
    print(f"  {'variant':38s} {'may use':>7s} {'ran on':>6s} {'cpu/wall each':>13s} {'steps/s each':>12s} "
          f"{'steps/s all':>11s}")
    for name, workers, threads, pin in variants:
        reps = [run_variant(a.preset, workers, threads, pin, a.seconds) for _ in range(a.repeats)]
        med = lambda f: statistics.median(f(r) for r in reps)  # noqa: E731
        each = lambda k: med(lambda r: statistics.mean(w[k] for w in r))  # noqa: E731
        print(f"  {name:38s} {each('cores'):7.0f} {each('ran_on'):6.1f} {each('cpu_per_wall'):13.2f} "
              f"{each('steps_per_s'):12.1f} {med(lambda r: sum(w['steps_per_s'] for w in r)):11.1f}", flush=True)


if __name__ == "__main__":
    main()
