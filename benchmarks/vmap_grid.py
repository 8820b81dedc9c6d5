"""Aggregate training throughput of a grid: vmapped groups vs the local backend vs one run alone.

    python benchmarks/vmap_grid.py [--preset fetchpush-sacmc-0.2] [--runs 2,6,12] [--steps 500] [--repeats 3]
                                   [--precision float32,bfloat16] [--layout split|one] [--json out.json]
    python benchmarks/vmap_grid.py --step-only [--runs 1,2,6] [--threads 1,2]   # the gradient step alone

Every configuration trains real runs of the preset (thesis sizes, HER, MC models) in fresh processes and
measures env steps/s over a window of `--steps` steps after learning starts and compilation (from the runs'
own metrics.csv: time and step of the first logged row past warm-up and of the last one before the final
evaluation):

- alone: one run in one process with every core's threads;
- local: as `--backend local` runs a grid, `cores` runs at a time, one process and one thread each (the
  aggregate is the sum of their rates; more runs only mean more waves of the same);
- vmap N: N runs (alphas 0 and the preset's, alternating; seeds 0..) as `--backend vmap` lays them out: with
  `--layout split` (its CPU default) one group per core, each in its own process with one thread; with
  `--layout one` (its GPU default) one group of all N in one process with every core's threads. The
  aggregate is the sum of runs x group steps/s.

Each figure is the median over `--repeats`; ratios are against the local backend measured in the same call.
"""
from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import write_json
from mcrl.config import resolve_config
from mcrl.run.rundir import read_rows
from mcrl.sweep.worker import cpu_count, thread_env

WARMUP = 300  # steps before the window: learning starts at 100, the first update compiles


def _window_rate(run_dir: Path) -> float:
    """Steps/s between the first row past warm-up and the row before the last (the last holds the final
    evaluation, and its first evaluation compiles)."""
    rows = read_rows(run_dir / "metrics.csv")[:-1]
    rows = [r for r in rows if r["step"] >= WARMUP]
    first, last = rows[0], rows[-1]
    return (last["step"] - first["step"]) / (last["time_s"] - first["time_s"])


def _overrides(steps: int, precision: str) -> dict:
    return {"total_steps": WARMUP + steps, "eval_every": 0, "log_every": 100, "checkpoint_every": 10**9,
            "final_eval_episodes": 1, "eval_episodes": 1, "save_buffer": False, "matmul_precision": precision}


_CHILD = """
import json, sys
from pathlib import Path
from mcrl.config import Config
spec = json.loads(sys.argv[1])
cfgs = [Config.from_dict(c) for c in spec["configs"]]
if spec["group"]:
    from mcrl.run.group import train_group
    train_group(cfgs, spec["dirs"])
else:
    from mcrl.run.trainer import train
    train(cfgs[0], Path(spec["dirs"][0]), progress=False)
"""


def _start(cfgs, dirs, group: bool, threads: int) -> subprocess.Popen:
    spec = json.dumps({"configs": [c.to_dict() for c in cfgs], "dirs": [str(d) for d in dirs], "group": group})
    import os

    return subprocess.Popen([sys.executable, "-c", _CHILD, spec], env={**os.environ, **thread_env(threads)})


def _wait(procs) -> None:
    for p in procs:
        if p.wait() != 0:
            raise SystemExit(f"a benchmark process failed (exit {p.returncode})")


def grid_configs(preset: str, n: int, steps: int, precision: str):
    alpha = resolve_config(preset).intrinsic_alpha
    return [resolve_config(preset, {**_overrides(steps, precision), "seed": i // 2,
                                    "intrinsic_alpha": alpha if i % 2 else 0.0}) for i in range(n)]


def measure(preset: str, runs: list[int], steps: int, precision: str, tmp: Path, layout: str = "split") -> dict:
    cores = cpu_count()
    out: dict = {}
    cfg = grid_configs(preset, 2, steps, precision)[1]  # a run of the preset itself (SAC-MC)
    d = tmp / f"alone-{time.monotonic_ns()}"
    _wait([_start([cfg], [d], False, cores)])
    out["alone"] = _window_rate(d)
    cfgs = grid_configs(preset, cores, steps, precision)
    dirs = [tmp / f"local-{time.monotonic_ns()}-{i}" for i in range(cores)]
    _wait([_start([c], [d], False, 1) for c, d in zip(cfgs, dirs)])
    out["local"] = sum(_window_rate(d) for d in dirs)
    for n in runs:
        cfgs = grid_configs(preset, n, steps, precision)
        dirs = [tmp / f"vmap{n}-{time.monotonic_ns()}-{i}" for i in range(n)]
        parts = min(cores, n) if layout == "split" else 1
        bounds = [round(k * n / parts) for k in range(parts + 1)]
        groups = [(cfgs[a:b], dirs[a:b]) for a, b in zip(bounds[:-1], bounds[1:])]
        _wait([_start(c, d, True, cores // parts) for c, d in groups])
        out[f"vmap{n}"] = sum(len(d) * _window_rate(d[0]) for _, d in groups)
    return out


_CHILD_STEP = """
import json, statistics, sys, time
import jax, jax.numpy as jnp
from mcrl.algo.sac import Agent, Batch, Hyper
from mcrl.config import resolve_config
from mcrl.run.policy import agent_for
spec = json.loads(sys.argv[1])
cfg = resolve_config(spec["preset"], {"intrinsic_models": True})
agent, es = agent_for(cfg)
def batch(i):
    k = jax.random.PRNGKey(i)
    return Batch(jax.random.normal(k, (cfg.batch_size, es.obs_dim)), jnp.tanh(jax.random.normal(k, (cfg.batch_size, es.act_dim))),
                 -jnp.ones(cfg.batch_size), jax.random.normal(k, (cfg.batch_size, es.obs_dim)), jnp.zeros(cfg.batch_size))
def ms(f, state, *args, calls=20):
    state = f(state, *args); jax.block_until_ready(state)
    times = []
    for _ in range(3):
        t = time.perf_counter()
        for _ in range(calls):
            state = f(state, *args)
        jax.block_until_ready(state); times.append((time.perf_counter() - t) / calls * 1e3)
    return statistics.median(times)
out = {}
for n in spec["runs"]:
    if n == 1:
        out[n] = ms(jax.jit(lambda s, b: agent.update(s, b)[0], donate_argnums=0), agent.init(0), batch(0))
    else:
        stack = lambda xs: jax.tree.map(lambda *a: jnp.stack(a), *xs)
        hyper = Hyper(*(jnp.full(n, v, jnp.float32) for v in Hyper.of(cfg)))
        out[n] = ms(jax.jit(jax.vmap(lambda s, b, h: agent.update(s, b, h)[0]), donate_argnums=0),
                    stack([agent.init(i) for i in range(n)]),
                    stack([batch(i) for i in range(n)]), hyper)
print(json.dumps(out))
"""


def step_only(preset: str, runs: list[int], threads: list[int]) -> None:
    """ms per (vmapped) gradient step of N runs, with each thread count, in fresh processes."""
    import os

    print(f"{preset} with MC models, ms per gradient step of N runs (median of 3 blocks of 20):")
    for t in threads:
        out = subprocess.run([sys.executable, "-c", _CHILD_STEP, json.dumps({"preset": preset, "runs": runs})],
                             env={**os.environ, **thread_env(t)}, capture_output=True, text=True, check=True)
        res = json.loads(out.stdout.strip().splitlines()[-1])
        print(f"  {t} thread(s): " + ", ".join(f"{n} run(s) {v:.1f} ms ({v / int(n):.1f} a run)"
                                                for n, v in res.items()))


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", default="fetchpush-sacmc-0.2")
    p.add_argument("--runs", default="2,6,12", help="group sizes of the vmap backend")
    p.add_argument("--steps", type=int, default=500, help="steps in each measured window")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--precision", default="float32", help="comma-separated: float32, bfloat16")
    p.add_argument("--layout", choices=("split", "one"), default="split",
                   help="vmap groups: one per core (split, the CPU default) or one for all runs")
    p.add_argument("--step-only", action="store_true", help="time the gradient step alone (random batches)")
    p.add_argument("--threads", default="1,2", help="--step-only: thread counts")
    p.add_argument("--json")
    a = p.parse_args()
    runs = [int(x) for x in a.runs.split(",")]
    if a.step_only:
        step_only(a.preset, runs, [int(x) for x in a.threads.split(",")])
        return 0
    results = {}
    with tempfile.TemporaryDirectory(prefix="mcrl-vmap-bench-") as tmp:
        for precision in a.precision.split(","):
            reps = [measure(a.preset, runs, a.steps, precision, Path(tmp), a.layout) for _ in range(a.repeats)]
            med = {k: statistics.median(r[k] for r in reps) for k in reps[0]}
            results[precision] = {"median": med, "repeats": reps}
            print(f"{a.preset}, {precision}, {cpu_count()} cores, vmap layout {a.layout}, medians of {a.repeats} "
                  f"(aggregate env steps/s; ratio to the local backend):")
            for k, v in med.items():
                print(f"  {k:>8}: {v:7.1f} steps/s  {v / med['local']:.2f}x")
            sys.stdout.flush()
    if a.json:
        write_json(a.json, {"preset": a.preset, "steps": a.steps, "cores": cpu_count(), "layout": a.layout,
                            "results": results})
    return 0


if __name__ == "__main__":
    sys.exit(main())
