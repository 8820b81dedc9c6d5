"""Does `mcrl sweep --threads-per-run 1` keep XLA on one core? CPU time over wall time of a jitted matmul loop.

    python benchmarks/xla_threads.py [--seconds 3] [--repeats 3] [--size 1024]

Each variant runs in a fresh process (XLA reads its flags when jax loads): `default` (no limits), `flags` (XLA's
thread flags, which `mcrl.sweep.worker.thread_env(1)` gave a sweep's runs before issue 52, with the thread pools'
environment variables) and `pinned` (no flags, the process bound to one core with `os.sched_setaffinity` before
jax loads, as a sweep's worker is since: `mcrl.sweep.worker.pin_cores`). A ratio above 1 means more than one
core's worth of work; beside other load every ratio shrinks, so compare the variants of one call. Prints the median
of the repeats. `sweep_threads.py` measures a sweep's workers themselves.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys

import _common  # noqa: F401  (puts src/ on sys.path where mcrl is not installed)

FLAGS = ("--xla_cpu_multi_thread_eigen=false", "intra_op_parallelism_threads=1")  # what sweeps passed before

_CHILD = r"""
import json, os, sys, time
size, seconds, pin = int(sys.argv[1]), float(sys.argv[2]), sys.argv[3] == "1"
if pin:
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
import jax, jax.numpy as jnp
f = jax.jit(lambda a: (a @ a) * 1e-3)
a = jnp.ones((size, size))
f(a).block_until_ready()
t0, c0, n = time.perf_counter(), os.times(), 0
while time.perf_counter() - t0 < seconds:
    f(a).block_until_ready()
    n += 1
wall, c1 = time.perf_counter() - t0, os.times()
cpu = (c1.user - c0.user) + (c1.system - c0.system)
threads = len(os.listdir("/proc/self/task"))
print(json.dumps({"cpu_per_wall": cpu / wall, "matmuls_per_s": n / wall, "threads": threads}))
"""


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=3.0)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--size", type=int, default=1024)
    a = p.parse_args()
    if not hasattr(os, "sched_setaffinity"):
        sys.exit("xla_threads: this platform has no os.sched_setaffinity (Linux only)")
    from mcrl.sweep.worker import thread_env

    limits = {**thread_env(1), "XLA_FLAGS": " ".join(FLAGS)}
    base = {k: v for k, v in os.environ.items() if k not in limits}
    variants = {"default": (base, "0"), "flags": ({**base, **limits}, "0"), "pinned": (base, "1")}
    print(f"{_common.usable_cores()} usable cores; {a.size}x{a.size} float32 matmul, {a.seconds:g} s, "
          f"median of {a.repeats}")
    for name, (env, pin) in variants.items():
        outs = []
        for _ in range(a.repeats):
            r = subprocess.run([sys.executable, "-c", _CHILD, str(a.size), str(a.seconds), pin], env=env,
                               capture_output=True, text=True, check=True)
            outs.append(json.loads(r.stdout.strip().splitlines()[-1]))
        med = {k: statistics.median(o[k] for o in outs) for k in outs[0]}
        print(f"  {name:8s} cpu/wall {med['cpu_per_wall']:.2f}   {med['matmuls_per_s']:6.1f} matmuls/s   "
              f"{med['threads']:.0f} threads")


if __name__ == "__main__":
    main()
